from benchmarks.grid.cli import main

main()
