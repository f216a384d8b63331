"""docs/reproduce.md: every command on the page, at smoke scale. The GPU trainings are composed (the paper's
recipe on the GPU) and one is run through the chain on the CPU, stopped by ``timeout`` and continued in place
to the end; its checkpoint is then evaluated, put through both grids and rendered with the paper beside it,
as the page says; the loader benchmark runs on tiny data; the data command is parsed (no download here)."""

from __future__ import annotations

import json
import math
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

import src.run.chain as chain_cli
from src.compose import compose_experiment
from tests.helpers.paths import ROOT

PAGE = ROOT / "docs" / "reproduce.md"
MODULES = {"src.run.chain", "src.eval", "benchmarks.grid", "benchmarks.tables", "benchmarks.speed.loader",
           "src.data.prepare"}
BEST = "best-<step>.ckpt"
TINY_DATA = ["data=synthetic", "data.build.num_train_per_category=2", "data.build.num_test_per_category=1",
             "data.build.num_samplings=3", "data.batch_size=2", "data.eval_batch_size=2", "data.num_workers=0",
             "data.pin_memory=false", "data.persistent_workers=false"]
SMOKE_TRAIN = [*TINY_DATA, "model_scale=0.0625", "trainer.accelerator=cpu", "trainer.enable_progress_bar=false",
               "trainer.max_steps=6", "trainer.val_check_interval=2", "trainer.check_val_every_n_epoch=null",
               "trainer.limit_val_batches=1", "trainer.limit_test_batches=1"]


def commands() -> list[list[str]]:
    """The argv of every command in the page's bash blocks (indented ones too), ``python -m`` included."""
    blocks = re.findall(r"^ *```bash\n(.*?)^ *```", PAGE.read_text(), flags=re.DOTALL | re.MULTILINE)
    lines = [line.strip() for block in blocks for line in block.replace("\\\n", " ").splitlines()]
    return [shlex.split(line) for line in lines if line and not line.startswith("#")]


def module_of(argv: list[str]) -> str:
    python = argv.index("python")
    assert argv[python + 1] == "-m", argv
    return argv[python + 2]


def args_of(argv: list[str]) -> list[str]:
    return argv[argv.index("python") + 3:]


def chain_parts(argv: list[str]) -> tuple[str, list[str], list[str]]:
    """A chain command's run folder, options and src.train overrides."""
    args = args_of(argv)
    split = args.index("--")
    return args[0], args[1:split], args[split + 1:]


def smoke(overrides: list[str], extra: list[str]) -> list[str]:
    """``overrides`` with ``extra`` replacing those of the same keys (Hydra refuses a key given twice)."""
    def key(override: str) -> str:
        return override.lstrip("+~").split("=", 1)[0]

    keys = {key(o) for o in extra}
    return [o for o in overrides if key(o) not in keys] + extra


def test_every_command_is_one_this_test_runs():
    found = [module_of(argv) for argv in commands()]
    assert set(found) <= MODULES and {"src.run.chain", "src.eval", "benchmarks.grid", "benchmarks.tables"} <= set(found)


def test_every_training_command_is_the_papers_recipe_on_the_gpu_one_run_per_folder(monkeypatch):
    runs: dict[str, list[str]] = {}
    for argv in commands():
        if module_of(argv) != "src.run.chain":
            continue
        run_dir, _, overrides = chain_parts(argv)
        assert runs.setdefault(run_dir, overrides) == overrides, f"{run_dir}: two commands, other overrides"
        cfg = compose_experiment([*overrides, "output_dir=unused"])
        assert (cfg.trainer.max_steps, cfg.data.batch_size, cfg.model.lr, list(cfg.model.scheduler.milestones),
                cfg.model.scheduler.gamma) == (260_000, 64, 1e-4, [220_000], 0.1)
        assert (cfg.trainer.accelerator, cfg.trainer.precision, cfg.model_scale, cfg.data.dataset) == \
            ("gpu", "32-true", 1.0, "modelnet40")
    assert all(d.startswith("outputs/reproduce/") for d in runs)
    trained = {(o[0], dict(x.split("=") for x in o[1:]).get("sampling"), dict(x.split("=") for x in o[1:]).get("partial", "prnet"))
               for o in runs.values()}
    assert trained == {(f"+exp={e}", s, p) for e in ("unseen_shapes", "gaussian_noise") for s in ("ts", "os")
                       for p in ("prnet", "rpmnet")} | {("+exp=unseen_categories", "ts", "prnet")}  # eight, and (b) again

    submitted = []
    monkeypatch.setattr(chain_cli, "submit", lambda *args: submitted.append(args))
    for argv in commands():
        if module_of(argv) == "src.run.chain" and "--submit" in argv:
            assert chain_cli.main(args_of(argv)) == 0
    (chain, options, cluster, requeues), = submitted
    assert (chain.minutes, options, cluster, requeues) == (240, {"slurm_partition": "gpu", "mem_gb": 64}, "slurm", 100)


@pytest.mark.parametrize(("trained", "tested"), [
    (["+exp=unseen_shapes"], ["+exp=unseen_categories"]),
    (["+exp=gaussian_noise", "partial=rpmnet"], ["+exp=unseen_categories", "partial=rpmnet", "data.pair.noise_sigma=0.01"]),
])
def test_the_unseen_categories_rows_need_no_training_of_their_own(trained, tested):
    """The page tests the first-half models on the other categories: the two configs train alike, only the test
    set (and the task's name) differ."""
    from omegaconf import OmegaConf

    configs = [OmegaConf.to_container(compose_experiment([*o, "output_dir=unused"]), resolve=True) for o in (trained, tested)]
    assert configs[0].pop("task_name") != configs[1].pop("task_name")
    assert configs[0]["callbacks"]["trained_on"].pop("task") != configs[1]["callbacks"]["trained_on"].pop("task")
    assert configs[0]["data"]["splits"].pop("test") != configs[1]["data"]["splits"].pop("test")
    assert configs[0] == configs[1]


def test_the_download_command_is_the_one_docs_data_gives():
    from src.data.prepare import _parser

    data_page = (ROOT / "docs" / "data.md").read_text()
    prepares = [argv for argv in commands() if module_of(argv) == "src.data.prepare"]
    assert prepares
    for argv in prepares:
        args = _parser().parse_args(args_of(argv))
        assert args.download is True and args.dataset == "modelnet40"
        assert f"python -m src.data.prepare {args.dataset} --download " in data_page


@pytest.mark.shared_data("reference/paper_tables/table1_prnet_partial.csv",
                         "reference/paper_tables/table2_rpmnet_partial_ts_unseen_categories_noise.csv")
def test_the_page_runs_at_smoke_scale(tmp_path, monkeypatch):
    from benchmarks.grid.cli import _run as grid_run
    from benchmarks.speed import loader
    from benchmarks.tables.render import main as tables_main
    from src.compose import compose_conf
    from src.eval import evaluate

    monkeypatch.chdir(tmp_path)  # the page's relative folders (outputs/...) land here, never in the repository
    cache = [f"data.cache_root={tmp_path / 'cache'}"]
    pause = ["+callbacks.pause._target_=tests.helpers.registration_helpers.PauseAt", "+callbacks.pause.step=3",
             f"+callbacks.pause.ready={tmp_path / 'ready'}"]  # holds step 3 until a signal (at most a minute)
    env = {"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin"}
    all_commands = commands()
    first = next(argv for argv in all_commands if argv[0] == "timeout")
    run_dir, _, overrides = chain_parts(first)
    smoke_run = smoke(overrides, [*SMOKE_TRAIN, *cache, *pause])

    def chain(argv: list[str], timeout: list[str]) -> subprocess.CompletedProcess:
        run, options, _ = chain_parts(argv)
        command = [*timeout, sys.executable, "-m", "src.run.chain", run, *options, "--", *smoke_run]
        return subprocess.run(command, check=False, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)

    # the timeout form: stopped (at the pause, or earlier when starting is slow), recorded, resumable
    stopped = chain(first, ["timeout", "45s"])
    assert stopped.returncode == 124, stopped.stderr[-3000:]
    record = json.loads((tmp_path / run_dir / "chain.json").read_text())
    assert [c["stopped_by"] for c in record["calls"]] == ["a signal"] and not record["done"]

    # the page's --minutes form of the same row continues it in the same folder, to the end; then nothing to run
    minutes = next(argv for argv in all_commands if module_of(argv) == "src.run.chain" and argv[0] != "timeout"
                   and chain_parts(argv)[0] == run_dir and "--submit" not in argv)
    done = chain(minutes, [])
    assert done.returncode == 0, done.stderr[-3000:]
    record = json.loads((tmp_path / run_dir / "chain.json").read_text())
    assert record["done"] and len(record["calls"]) == 2 and record["calls"][-1]["to_step"] == 6
    assert (tmp_path / run_dir / "metrics.json").is_file() and not (ROOT / run_dir).exists()
    assert "nothing to run" in chain(minutes, []).stdout
    best, = (tmp_path / run_dir / "checkpoints").glob("best-*.ckpt")

    def rewrite(argv: list[str]) -> list[str]:  # every checkpoint of the page: the smoke run's best
        return [re.sub(r"outputs/reproduce/[a-z_]+/checkpoints/" + re.escape(BEST), str(best), a) for a in argv]

    evaluated = 0
    for k, argv in enumerate(all_commands):
        name, args = module_of(argv), rewrite(args_of(argv))
        if name == "src.eval":
            metrics = evaluate(compose_conf(smoke(args, [*TINY_DATA, *cache, "model_scale=0.0625", "trainer.accelerator=cpu",
                                                        "trainer.limit_test_batches=1", f"output_dir={tmp_path / f'eval{k}'}"])))
            assert metrics and all(math.isfinite(v) for v in metrics.values() if isinstance(v, float))
            evaluated += 1
        elif name == "benchmarks.grid":
            from hydra import compose, initialize_config_dir

            from src.utils.paths import CONF_DIR

            grid_overrides = smoke(args, [*TINY_DATA, *cache, "benchmark.max_pairs=2", "workers=0", "progress=false"])
            output = next(o for o in grid_overrides if o.startswith("benchmark.name=")).split("=", 1)[1]
            with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
                grid_run(compose("benchmark_grid", overrides=grid_overrides))
            assert (tmp_path / "outputs" / "grid" / output / "results.parquet").is_file()
        elif name == "benchmarks.tables":
            assert tables_main(args) == 0
            layout = args[args.index("--layout") + 1]
            assert (tmp_path / args[args.index("--out") + 1] / f"{layout}.md").is_file()
        elif name == "benchmarks.speed.loader":
            batches = args.index("--batches")
            real = ["test_size=1", "val_size=1", "val_repeat=1", "real_train_categories=[airplane,bed]"] \
                if "+exp=real_airplane" in args else []  # the real-airplane carve-outs, cut to the tiny data
            assert loader.main([*smoke(args[:batches] + args[batches + 2:], [*TINY_DATA, *cache, *real]), "--batches", "1"]) == 0
    assert evaluated == sum(module_of(a) == "src.eval" for a in all_commands) > 0
