"""The CPU-recipe study: command lines, resume, the report from CSV logs, and the training clock."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pandas as pd
import pytest

from benchmarks.studies.cpu_budget import recipes as cpu_recipes
from src.run.callbacks import TrainingClock


def test_command_has_budgeted_steps_a_step_decay_at_80_percent_and_resumes(tmp_path: Path):
    run_dir = tmp_path / "base"
    command = cpu_recipes.recipe_command("base", cpu_recipes.RECIPES["base"], run_dir, max_steps=1000, val_every=100)
    assert "trainer.max_steps=1000" in command and "model.scheduler.milestones=[800]" in command
    assert "data.batch_size=16" in command and not any(c.startswith("ckpt_path=") for c in command)
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "last.ckpt").write_bytes(b"")
    resumed = cpu_recipes.recipe_command("base", cpu_recipes.RECIPES["base"], run_dir, max_steps=1000, val_every=100)
    assert resumed[-1] == f"ckpt_path={run_dir / 'checkpoints' / 'last.ckpt'}"


def test_schedules_replace_the_whole_scheduler_block(tmp_path: Path):
    command = cpu_recipes.recipe_command("cosine_warmup", cpu_recipes.RECIPES["cosine_warmup"], tmp_path, 1000, 100)
    assert "~model.scheduler" in command and "+model.scheduler={name: cosine, warmup_steps: 50}" in command


def test_every_recipe_composes_into_a_training_config(tmp_path: Path):
    """Each recipe's overrides compose with src.train's config (catches a stale key such as an old schedule)."""
    from hydra import compose, initialize_config_dir

    from src.config import register_resolvers
    from src.utils.paths import REPO_ROOT

    register_resolvers()
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        for name, recipe in cpu_recipes.RECIPES.items():
            command = cpu_recipes.recipe_command(name, recipe, tmp_path / name, 1000, 100)
            overrides = [o for o in command[3:] if not o.startswith(("hydra.", "task_name="))]
            cfg = compose("config", overrides=overrides + [f"output_dir={tmp_path}"])
            assert cfg.trainer.max_steps == 1000 and cfg.data.batch_size == recipe["batch"]
            if "schedule" in recipe:
                assert cfg.model.scheduler.name in name and "milestones" not in cfg.model.scheduler
            else:
                assert cfg.model.scheduler.name == "multistep" and list(cfg.model.scheduler.milestones) == [800]


def _fake_run(root: Path, name: str, errors: list[float]) -> None:
    run = root / name
    (run / "csv" / "version_0").mkdir(parents=True)
    (run / "plan.json").write_text(json.dumps({"max_steps": 100}))
    rows = [{"step": 10 * (i + 1) - 1, "time/cpu_hours": 0.1 * (i + 1), "val/Error(R)": e, "val/Error(t)": e / 100}
            for i, e in enumerate(errors)]
    rows.insert(0, {"step": 4, "time/cpu_hours": 0.01, "train/loss": 3.0})  # a training row without validation
    pd.DataFrame(rows).to_csv(run / "csv" / "version_0" / "metrics.csv", index=False)


def test_report_writes_curves_summary_and_plot(tmp_path: Path):
    _fake_run(tmp_path, "base", [40.0, 20.0, 25.0])
    _fake_run(tmp_path, "lr_3e-3", [30.0, 10.0, 5.0])
    written = cpu_recipes.report([tmp_path], tmp_path / "out")
    assert all(p.is_file() and p.stat().st_size > 0 for p in written)
    curves = pd.read_csv(tmp_path / "out" / "cpu_recipes.csv")
    assert len(curves) == 6 and set(curves["recipe"]) == {"base", "lr_3e-3"}
    summary = cpu_recipes.summary(cpu_recipes.curves([tmp_path])).set_index("recipe")
    assert summary.loc["base", "best Error(R)"] == 20.0 and summary.loc["base", "best at CPU h"] == pytest.approx(0.2)
    assert summary.loc["base", "last Error(R)"] == 25.0
    assert list(summary.index) == ["lr_3e-3", "base"]  # ordered by the last validation


def test_report_without_runs_is_one_clear_error(tmp_path: Path, capsys):
    assert cpu_recipes.main(["report", "--root", str(tmp_path)]) == 2
    assert "run `python -m benchmarks.studies.cpu_budget.recipes run` first" in capsys.readouterr().err


def test_unknown_recipe_is_refused(tmp_path: Path, capsys):
    assert cpu_recipes.main(["run", "--root", str(tmp_path), "--recipes", "base,nope"]) == 2
    assert "unknown recipes ['nope']" in capsys.readouterr().err


def _busy(seconds: float) -> None:
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass


def test_training_clock_counts_cpu_time_and_carries_it_over_a_resume():
    clock = TrainingClock()
    clock.on_train_start(None, None)
    _busy(0.05)
    state = clock.state_dict()
    assert state["cpu_seconds"] >= 0.05 and state["wall_seconds"] >= 0.05
    resumed = TrainingClock()
    resumed.load_state_dict(state)
    resumed.on_train_start(None, None)
    _busy(0.05)
    assert resumed.state_dict()["cpu_seconds"] >= state["cpu_seconds"] + 0.05


def _fake_trainer(step: int = 1):
    from types import SimpleNamespace

    return SimpleNamespace(sanity_checking=False, state=SimpleNamespace(fn="fit"), global_step=step,
                           log_every_n_steps=1000, should_stop=False)


def test_training_clock_counts_validation_apart_and_stops_at_its_budget():
    clock, trainer = TrainingClock(budget_cpu_hours=0.12 / 3600), _fake_trainer()
    clock.on_train_start(trainer, None)
    _busy(0.05)
    clock.on_validation_start(trainer, None)
    _busy(0.1)
    clock.on_validation_end(trainer, None)
    state = clock.state_dict()
    assert 0.05 <= state["cpu_seconds"] < 0.1 and state["eval_cpu_seconds"] >= 0.1
    clock.on_train_batch_end(trainer, None, None, None, 0)
    assert not trainer.should_stop  # ~0.05 s of training, under the 0.12 s budget
    _busy(0.08)
    clock.on_train_batch_end(trainer, None, None, None, 0)
    assert trainer.should_stop


def test_runs_of_several_roots_are_labelled_by_their_root_when_names_collide(tmp_path: Path):
    _fake_run(tmp_path / "v1", "base", [40.0, 20.0])
    _fake_run(tmp_path / "v2", "base", [30.0, 10.0])
    _fake_run(tmp_path / "v2", "cosine_warmup", [30.0, 12.0])
    frame = cpu_recipes.curves([tmp_path / "v1", tmp_path / "v2"])
    assert set(frame["recipe"]) == {"base (v1)", "base (v2)", "cosine_warmup"}
    assert set(frame["code"]) == {"unknown"}  # plan.json without a recorded commit
