"""benchmarks.studies.cpu_budget.budget: each method's recipe mapped onto one CPU budget, the width rule, the two-stage
PointNetLK plan, and resumable, chained runs (training itself replaced by a recorder)."""

import json
import re
from pathlib import Path

import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf

from benchmarks.studies.cpu_budget import budget as cpu_budget
from benchmarks.studies.cpu_budget.budget import MIN_STEPS, OVERHEAD, Stage, budget_schedule, compose_recipe, plan_method, stage_command


def _fractions(overrides: list[str]) -> list[float]:
    (spec,) = [o for o in overrides if o.startswith("+model.scheduler=")]
    return [float(x) for x in re.search(r"fractions: \[([^\]]*)\]", spec).group(1).split(",")]


@pytest.mark.parametrize("method", ["omnet", "dcp", "prnet", "idam"])
def test_milestones_become_the_same_fractions_of_the_budget_run(method):
    cfg = compose_recipe(method)
    spec = OmegaConf.to_container(cfg.model.scheduler)
    length = cfg.trainer.max_epochs if cfg.trainer.max_epochs > 0 else cfg.trainer.max_steps
    assert _fractions(budget_schedule(cfg)) == pytest.approx([m / length for m in spec["milestones"]], rel=1e-3)


def test_omnet_trains_with_the_official_codes_recipe():
    cfg = compose_recipe("omnet")
    assert cfg.data.batch_size == 16 and cfg.model.lr == pytest.approx(1e-4)
    assert _fractions(budget_schedule(cfg)) == pytest.approx([0.7, 0.9])


def test_plateau_patience_becomes_the_same_share_of_the_validations():
    cfg = compose_recipe("deepgmr")
    patience = round(cfg.model.scheduler.patience / cfg.trainer.max_epochs * cpu_budget.VALIDATIONS)
    assert budget_schedule(cfg) == [f"model.scheduler.patience={patience}", "+model.scheduler.interval=validation"]


@pytest.mark.parametrize("method", ["rpmnet", "fmr", "pointnetlk_revisited"])
def test_a_recipe_without_schedule_stays_without(method):
    assert budget_schedule(compose_recipe(method)) == []


def _cost(seconds_at_full_width: float):
    calls = []

    def probe(model: str, width: float, batch: int) -> float:
        calls.append((model, width, batch))
        return seconds_at_full_width * width**2
    return probe, calls


def test_the_widest_width_that_buys_the_minimum_steps_is_chosen():
    probe, calls = _cost(30.0)  # 1.0 -> 109 steps, 0.5 -> 436, 0.25 -> 1745 in an hour
    plan = plan_method("dcp", 1.0, probe=probe)
    assert [w for _, w, _ in calls] == [1.0, 0.5, 0.25] and plan["width"] == 0.25
    (stage,) = plan["stages"]
    assert stage["batch"] == compose_recipe("dcp").data.batch_size
    assert stage["max_steps"] == int(3600 / (30.0 * 0.25**2 * OVERHEAD)) >= MIN_STEPS


def test_the_authors_width_when_the_budget_buys_enough_steps():
    probe, calls = _cost(1.0)
    assert plan_method("fmr", 1.0, probe=probe)["width"] == 1.0 and len(calls) == 1


def test_a_step_that_never_fits_is_refused():
    with pytest.raises(cpu_budget.ConfigError, match="out of memory"):
        plan_method("prnet", 1.0, probe=lambda model, width, batch: float("inf"))


def test_pointnetlks_classifier_stage_takes_its_share_of_the_same_budget():
    probe, _ = _cost(2.0)
    plan = plan_method("pointnetlk", 1.0, probe=probe)
    classifier, lk = (Stage(**s) for s in plan["stages"])
    assert (classifier.model, lk.model) == ("pointnet_classifier", "pointnetlk")
    assert classifier.budget_cpu_h + lk.budget_cpu_h == pytest.approx(1.0)
    epochs = compose_recipe("pointnet_classifier").trainer.max_epochs, compose_recipe("pointnetlk").trainer.max_epochs
    assert classifier.budget_cpu_h / lk.budget_cpu_h == pytest.approx(epochs[0] / epochs[1])  # same step cost here
    assert "data=synthetic" in stage_command(classifier, Path("run"), [])  # the real airplanes have one category
    assert "data=modelnet40_npy" in stage_command(classifier, Path("run"), [], "unseen_categories_npy")


def test_runs_resume_and_chain_the_classifier_features(tmp_path, monkeypatch):
    probe, _ = _cost(2.0)
    monkeypatch.setattr(cpu_budget, "plan_method", lambda method, budget_h, *protocol: plan_method(method, budget_h, *protocol, probe=probe))
    commands = []

    def train(run_dir: Path, command: list[str]) -> int:
        commands.append(command)
        (run_dir / "checkpoints").mkdir(exist_ok=True)
        (run_dir / "checkpoints" / "best-9.ckpt").write_bytes(b"")
        return 0

    monkeypatch.setattr(cpu_budget, "train_logged", train)
    assert cpu_budget.run_method("pointnetlk", tmp_path, 1.0) == "pointnetlk: done"
    classifier, lk = commands
    best = tmp_path / "pointnetlk" / "classifier" / "checkpoints" / "best-9.ckpt"
    assert f"model.network.feature_init={best}" in lk and not any(c.startswith("model.network.feature_init") for c in classifier)
    assert "callbacks.clock.budget_cpu_hours=" + f"{json.loads((tmp_path / 'pointnetlk' / 'plan.json').read_text())['stages'][1]['budget_cpu_h']:.4f}" in lk
    assert (tmp_path / "pointnetlk" / "pointnetlk" / "command.txt").read_text().startswith("-m src.train")
    assert cpu_budget.run_method("pointnetlk", tmp_path, 1.0) == "pointnetlk: done" and len(commands) == 2  # done: skipped


def test_an_interrupted_stage_resumes_from_its_last_checkpoint(tmp_path):
    stage = Stage("dcp", "dcp", 0.25, 32, 1.0, 1.0, 1000)
    assert not any(c.startswith("ckpt_path=") for c in stage_command(stage, tmp_path, []))
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(b"")
    assert stage_command(stage, tmp_path, [])[-1] == f"ckpt_path={tmp_path / 'checkpoints' / 'last.ckpt'}"
    assert f"trainer.val_check_interval={1000 // cpu_budget.VALIDATIONS}" in stage_command(stage, tmp_path, [])


def test_a_stage_started_from_weights_resumes_from_its_own(tmp_path):
    stage = Stage("omnet", "omnet", 0.25, 16, 1.0, 1.0, 1000, ["recipe=omnet_finetune", "init_weights=start.ckpt"])
    assert "init_weights=start.ckpt" in stage_command(stage, tmp_path, [])
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(b"")
    resumed = stage_command(stage, tmp_path, [])
    assert "recipe=omnet_finetune" in resumed and not any(c.startswith("init_weights=") for c in resumed)
    assert resumed[-1] == f"ckpt_path={tmp_path / 'checkpoints' / 'last.ckpt'}"


def _fake_stage(run_dir: Path, rows: list[dict], test: dict | None = None, done: bool = True) -> None:

    (run_dir / "csv" / "version_0").mkdir(parents=True)
    pd.DataFrame(rows).to_csv(run_dir / "csv" / "version_0" / "metrics.csv", index=False)
    if test is not None:
        (run_dir / "metrics.json").write_text(json.dumps({"metrics": test}))
    if done:
        (run_dir / "done.json").write_text("{}")


def test_steps_trained_are_the_tested_count_until_an_extended_run_logs_further(tmp_path):
    _fake_stage(tmp_path, [{"step": 979, "time/cpu_hours": 0.5}])
    (tmp_path / "metrics.json").write_text(json.dumps({"global_step": 1000}))
    logs = cpu_budget.read_csv_logs(tmp_path)
    assert cpu_budget.steps_trained(tmp_path, logs) == 1000  # the last logged row comes before the last step
    more = pd.concat([logs, pd.DataFrame([{"step": 1499, "time/cpu_hours": 0.75}])], ignore_index=True)
    assert cpu_budget.steps_trained(tmp_path, more) == 1500


def test_report_shifts_a_second_stage_by_the_first_and_tabulates_each_method(tmp_path):
    from benchmarks.studies.cpu_budget.report import collect, report

    probe, _ = _cost(2.0)
    for method in ("dcp", "pointnetlk"):
        (tmp_path / method).mkdir()
        (tmp_path / method / "plan.json").write_text(json.dumps(plan_method(method, 1.0, probe=probe)))
    val = lambda step, hours, err: {"step": step, "time/cpu_hours": hours, "val/Error(R)": err, "val/Error(t)": err / 100}  # noqa: E731
    _fake_stage(tmp_path / "dcp" / "dcp", [val(9, 0.5, 30.0), val(19, 1.0, 20.0), {"step": 20, "time/cpu_hours": 1.01}],
                {"Error(R)": 21.0, "Error(t)": 0.2})
    _fake_stage(tmp_path / "pointnetlk" / "classifier", [{"step": 4, "time/cpu_hours": 0.25, "val/loss": 1.0}])
    _fake_stage(tmp_path / "pointnetlk" / "pointnetlk", [val(9, 0.25, 40.0), val(19, 0.5, 35.0)], done=False)
    curves, table = collect(tmp_path)
    lk = curves[curves["method"] == "pointnetlk"]
    assert list(lk["cpu_hours"]) == pytest.approx([0.5, 0.75]) and list(lk["Error(R)"]) == [40.0, 35.0]
    table = table.set_index("method")
    assert table.loc["dcp", "steps"] == 21 and table.loc["dcp", "CPU h"] == pytest.approx(1.01)
    assert table.loc["dcp", "best val Error(R)"] == 20.0 and table.loc["dcp", "test Error(R)"] == 21.0
    assert table.loc["pointnetlk", "steps"] == "5 + 20" and table.loc["pointnetlk", "CPU h"] == pytest.approx(0.75)
    assert not table.loc["pointnetlk", "done"] and pd.isna(table.loc["pointnetlk", "test Error(R)"])
    assert all(p.is_file() and p.stat().st_size > 0 for p in report(tmp_path, tmp_path / "out"))
    (tmp_path / "dcp" / "dcp" / "checkpoints").mkdir()
    (tmp_path / "dcp" / "dcp" / "checkpoints" / "last.ckpt").write_bytes(b"weights")
    (tmp_path / "dcp" / "dcp" / "command.txt").write_text(f"-m src.train model=dcp hydra.run.dir={tmp_path}/dcp/dcp\n")
    archive = tmp_path / "archive"
    assert cpu_budget.archive_runs(tmp_path, archive) == ["dcp", "pointnetlk"]
    assert not list(archive.rglob("*.ckpt"))
    assert (archive / "dcp" / "dcp" / "command.txt").read_text() == "-m src.train model=dcp hydra.run.dir=RUNS/dcp/dcp\n"
    archived_curves, archived_table = collect(archive)  # the report from the committed copy: the same numbers
    pd.testing.assert_frame_equal(archived_curves, curves)
    pd.testing.assert_frame_equal(archived_table, table.reset_index())


def test_the_probe_times_a_step_in_a_child_and_reports_one_that_does_not_fit_as_infinite(monkeypatch):
    import math

    assert 0 < cpu_budget.probe_step_seconds("pointnetlk_revisited", 0.0625, 4) < math.inf
    monkeypatch.setattr(cpu_budget, "PROBE_MEMORY_BYTES", 256 * 2**20)  # not even torch fits
    assert cpu_budget.probe_step_seconds("pointnetlk_revisited", 0.0625, 4) == math.inf


def test_run_archives_each_method_when_it_returns(tmp_path, monkeypatch):
    def fake_run(method, root, budget_h, planner=None):
        (root / method).mkdir(parents=True)
        (root / method / "plan.json").write_text(json.dumps({"stages": [{"name": method}]}))
        return f"{method}: done"

    monkeypatch.setattr(cpu_budget, "run_method", fake_run)
    assert cpu_budget.main(["run", "--root", str(tmp_path / "runs"), "--methods", "dcp,fmr", "--archive", str(tmp_path / "a")]) == 0
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["dcp", "fmr"] and (tmp_path / "a" / "fmr" / "plan.json").is_file()


def _checkpoint(path: Path, run_dir: Path, weight: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    folder = str(run_dir / "checkpoints")
    torch.save({"global_step": 7, "state_dict": {"w": torch.full((2,), weight)}, "optimizer_states": [{"m": 1.0}],
                "callbacks": {"ModelCheckpoint{'monitor': 'val/score'}": {
                    "dirpath": folder, "best_model_path": f"{folder}/best-3.ckpt",
                    "best_k_models": {f"{folder}/best-3.ckpt": torch.tensor(4.0)}}}}, path)


def test_an_unfinished_run_is_archived_with_its_checkpoints_and_goes_on_where_it_is_restored(tmp_path):
    """On a new machine the archived last.ckpt named the old run folder: the best checkpoint so far was lost."""
    root, archive, elsewhere = tmp_path / "runs", tmp_path / "archive", tmp_path / "other" / "runs"
    for method, done in (("dcp", False), ("fmr", True)):
        run_dir = root / method / method
        run_dir.mkdir(parents=True)
        (root / method / "plan.json").write_text(json.dumps({"stages": [{"name": method}]}))
        (run_dir / "command.txt").write_text(f"python -m src.train hydra.run.dir={run_dir}")
        _checkpoint(run_dir / "checkpoints" / "last.ckpt", run_dir, 1.0)
        _checkpoint(run_dir / "checkpoints" / "best-3.ckpt", run_dir, 2.0)
        if done:
            (run_dir / "done.json").write_text("{}")
    assert cpu_budget.main(["archive", "--root", str(root), "--out", str(archive)]) == 0
    assert sorted(p.name for p in (archive / "dcp" / "dcp" / "checkpoints").iterdir()) == ["best-3.ckpt", "last.ckpt"]
    assert not (archive / "fmr" / "fmr" / "checkpoints").exists()  # a finished run ships its checkpoint instead
    for path in archive.rglob("*"):
        assert path.is_dir() or str(root).encode() not in path.read_bytes(), path
    assert "optimizer_states" not in torch.load(archive / "dcp" / "dcp" / "checkpoints" / "best-3.ckpt", weights_only=False)

    assert cpu_budget.main(["restore", "--archive", str(archive), "--root", str(elsewhere)]) == 0
    run_dir = elsewhere / "dcp" / "dcp"
    last = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=False)
    (state,) = last["callbacks"].values()
    assert state["dirpath"] == str(run_dir / "checkpoints") and state["best_model_path"] == str(run_dir / "checkpoints" / "best-3.ckpt")
    assert list(state["best_k_models"]) == [str(run_dir / "checkpoints" / "best-3.ckpt")]
    assert torch.equal(last["state_dict"]["w"], torch.ones(2)) and last["optimizer_states"] == [{"m": 1.0}]
    assert (run_dir / "command.txt").read_text() == f"python -m src.train hydra.run.dir={run_dir}"
    (run_dir / "command.txt").write_text("going on")
    assert cpu_budget.restore_runs(archive, elsewhere) == ([], ["dcp", "fmr"])  # a run already there is left alone
    assert (run_dir / "command.txt").read_text() == "going on"


def test_a_run_beyond_the_budget_takes_its_recipe_as_it_is_and_is_reported_beside_the_method(tmp_path, monkeypatch):
    from benchmarks.studies.cpu_budget.report import collect

    recipe = compose_recipe("omnet", "omnet_cpu")
    plan = cpu_budget.plan_beyond("omnet", "omnet_cpu", 1.5, probe=lambda m, w, b: 2.0)
    assert (plan["stages"][0]["width"], plan["stages"][0]["batch"]) == (recipe.model_scale, recipe.data.batch_size)
    start = tmp_path / "start.ckpt"  # a fine-tune goes on at the width of the network it starts from
    torch.save({"state_dict": {}, "hyper_parameters": {"network": {"_target_": "omnet", "width": 0.5}}}, start)
    plan = cpu_budget.plan_beyond("omnet", "omnet_cpu", 1.5, str(start), probe=lambda m, w, b: 2.0 * w / 0.25)
    (stage,) = plan["stages"]
    assert (stage["width"], stage["batch"]) == (0.5, recipe.data.batch_size)
    assert stage["max_steps"] == int(1.5 * 3600 / (4.0 * OVERHEAD))  # probed at that width
    assert stage["overrides"] == ["recipe=omnet_cpu", f"init_weights={start}"] and plan["beyond"] == "omnet_cpu"
    commands = []

    def train(run_dir: Path, command: list[str]) -> int:
        commands.append(command)
        _fake_stage(run_dir, [{"step": 9, "time/cpu_hours": 0.7, "val/Error(R)": 15.0, "val/Error(t)": 0.1,
                               "time/mm_gflops": 50.0}],
                    {"Error(R)": 16.0, "Error(t)": 0.1}, done=False)
        return 0

    monkeypatch.setattr(cpu_budget, "train_logged", train)
    assert cpu_budget.run_method("omnet", tmp_path, 1.5, "omnet_beyond", lambda: plan) == "omnet_beyond: done"
    assert "recipe=omnet_cpu" in commands[0] and f"init_weights={start}" in commands[0] and "model_scale=0.5" in commands[0]
    assert cpu_budget.run_folders(tmp_path) == ["omnet_beyond"]
    curves, table = collect(tmp_path)
    assert list(curves["method"]) == ["omnet_beyond"] and table.loc[0, "test Error(R)"] == 16.0
    assert table.loc[0, "mm GFLOP/s"] == 50.0


def test_a_shipped_run_says_what_it_trained_on_how_long_and_from_what(tmp_path):
    from src.utils.errors import ConfigError

    start = tmp_path / "clean" / "best-10.ckpt"
    start.parent.mkdir()
    torch.save({"state_dict": {}, "hyper_parameters": {"network": {"_target_": "omnet", "width": 0.25}}}, start)
    plan = cpu_budget.plan_beyond("omnet", "omnet_cpu", 2.0, str(start), protocol="gaussian_noise_npy",
                                  probe=lambda m, w, b: 2.0)
    (tmp_path / "omnet_noisy").mkdir()
    (tmp_path / "omnet_noisy" / "plan.json").write_text(json.dumps(plan))
    run_dir = tmp_path / "omnet_noisy" / "omnet"
    _fake_stage(run_dir, [{"step": 9, "time/cpu_hours": 1.0}, {"step": 19, "time/cpu_hours": 1.93}], done=False)
    best = f"{run_dir}/checkpoints/best-19.ckpt"
    (run_dir / "metrics.json").write_text(json.dumps({"trained_precision": "32-true", "checkpoint": best,
                                                     "tested_weights": f"{best} (step 19), selected on val/loss (min)"}))
    note = cpu_budget.ship_note(tmp_path / "omnet_noisy", "a 2-core test CPU")
    assert note.startswith(cpu_budget.PROTOCOLS["gaussian_noise_npy"].description + ". Trained by")
    steps = plan["stages"][0]["max_steps"]
    assert f"recipe omnet_cpu; omnet: {steps:,} steps x batch 16 at width 0.25, planned for a 2-CPU-hour budget" in note
    assert "1.93 CPU hours used with validation), starting from best-10.ckpt, one torch thread, 32-true, on a 2-core test CPU" in note
    assert note.endswith("Weights: best-19.ckpt (step 19), selected on val/loss (min).") and str(tmp_path) not in note
    with pytest.raises(ConfigError, match="has not finished \\(no done.json\\): run it to the end first"):
        cpu_budget.ship(tmp_path / "omnet_noisy", "omnet_noisy_test", "a 2-core test CPU")


def test_extend_replans_a_run_whose_probe_overestimated_its_step_to_the_steps_its_budget_buys(tmp_path):
    from src.utils.errors import ConfigError

    plan = cpu_budget.plan_beyond("omnet", "omnet_cpu", 2.0, protocol="unseen_categories_npy", probe=lambda m, w, b: 2.0)
    planned = plan["stages"][0]["max_steps"]  # 2 h / (2 s x overhead): 3,272 steps
    (tmp_path / "omnet_beyond").mkdir()
    (tmp_path / "omnet_beyond" / "plan.json").write_text(json.dumps(plan))
    run_dir = tmp_path / "omnet_beyond" / "omnet"
    # the run measured 1.5 CPU s a step: its planned steps used 1.36 of its 2 CPU hours
    _fake_stage(run_dir, [{"step": planned // 2 - 1, "time/cpu_hours": planned / 2 * 1.5 / 3600},
                          {"step": planned - 1, "time/cpu_hours": planned * 1.5 / 3600}])
    assert cpu_budget.main(["extend", "--root", str(tmp_path), "--folder", "omnet_beyond"]) == 0
    (stage,) = json.loads((tmp_path / "omnet_beyond" / "plan.json").read_text())["stages"]
    assert stage["max_steps"] == int(2.0 * 3600 / 1.5) and stage["planned_steps"] == planned
    assert stage["step_cpu_s"] == pytest.approx(1.5) and not (run_dir / "done.json").exists()  # the driver goes on
    best = f"{run_dir}/checkpoints/best-9.ckpt"
    (run_dir / "metrics.json").write_text(json.dumps({"trained_precision": "32-true", "checkpoint": best,
                                                     "tested_weights": f"{best} (step 9), selected on val/score (min)"}))
    assert (f"{int(2.0 * 3600 / 1.5):,} steps x batch 16 at width 0.25, planned for a 2-CPU-hour budget from a probe of "
            f"its step cost ({planned:,} steps), then from the step cost the run measured (1.50 CPU s a step)"
            in cpu_budget.ship_note(tmp_path / "omnet_beyond", "a test CPU"))
    with pytest.raises(ConfigError, match="planned steps already use its 2 CPU hours at the measured 1.50 CPU s a step"):
        cpu_budget.extend_plan(tmp_path / "omnet_beyond")  # the steps trained so far: the same measure, nothing to add
