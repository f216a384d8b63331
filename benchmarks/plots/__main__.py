import sys

from benchmarks.plots.sweep import main

sys.exit(main())
