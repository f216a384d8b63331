import sys

from benchmarks.speed.inference import main

sys.exit(main())
