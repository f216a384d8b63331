"""Run a small comparison grid and render its table in the paper's Table-1 layout (Markdown and LaTeX).

Shows ``benchmarks.grid`` from Python: the grid's configuration (``conf/benchmark/default.yaml``) composed with
overrides, ``run_grid`` (every method x experiment x sampling x partial manner on the fixed test sets; finished
cells are reused when run again), and ``benchmarks.tables`` turning the tidy results into the paper's layout.
It runs on the embedded synthetic data (built on first use under $OMNET_CACHE_DIR): synthetic, not ModelNet40.

    python examples/small_grid.py                                  # ICP and FGR, 8 pairs per cell
    python examples/small_grid.py --methods icp,symmetric_icp --pairs 4 --out outputs/grid/example
    python -m benchmarks.grid 'benchmark.methods=[icp,fgr]' benchmark.max_pairs=8   # the same from the shell
"""

import argparse
from pathlib import Path

from hydra import compose, initialize_config_dir

from benchmarks.grid.plan import GRID_CONFIG
from benchmarks.grid.run import run_grid
from src.utils.paths import CONF_DIR
from benchmarks.tables.render import build_table, to_latex, to_markdown

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("--methods", default="icp,fgr", help="comma-separated keys of `python -m baselines`")
parser.add_argument("--pairs", type=int, default=8, help="pairs per cell (the first N of each test set)")
parser.add_argument("--out", type=Path, default=Path("outputs/grid/example"), help="the grid's output folder")
args = parser.parse_args()

with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
    cfg = compose(GRID_CONFIG, overrides=[
        f"benchmark.methods=[{args.methods}]", "benchmark.experiments=[unseen_shapes]", "benchmark.samplings=[os,ts]",
        "benchmark.partials=[prnet]", f"benchmark.max_pairs={args.pairs}", "workers=0", "progress=false",
        "paper=false", f"output_dir={args.out.resolve()}"])
result = run_grid(cfg)   # writes results.parquet|csv, pairs.parquet and cells/ into output_dir
print(f"{len(result.cells)} cells ({result.computed} computed, {result.reused} reused) in {result.output_dir}")

table = build_table(result.tidy, layout="table1")
(args.out / "table.md").write_text(to_markdown(table))
(args.out / "table.tex").write_text(to_latex(table))
print(to_markdown(table))
print(f"wrote {args.out / 'table.md'} and {args.out / 'table.tex'}")
