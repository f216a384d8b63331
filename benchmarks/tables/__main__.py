import sys

from benchmarks.tables.render import main

sys.exit(main())
