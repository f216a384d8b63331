"""Bad input never gives a wrong result: config values checked at composition, training
that would train nothing, checkpoints to resume from, and checkpoint files of killed saves."""

from __future__ import annotations

import glob
import importlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import hydra
import pytest
import torch

import src.eval
import src.train
from src.utils.errors import CheckpointError, ConfigError
from src.utils.files import remove_stale_temporaries, write_atomic
from src.models.base import check_network
from src.train import build_module, train
from src.run.trainer import build_trainer
from src.data.datamodule import check_pair_layout
from src.validation import validate_config
from tests.helpers.registration_helpers import CONF, TINY, compose_config

ROOT = CONF.parent
SHIPPED = ROOT / "checkpoints" / "omnet_unseen_categories_synthetic_ts_prnet.ckpt"

#: The module holding ``main`` of a command that is a package (``python -m benchmarks.grid``).
COMMAND_MODULES = {"benchmarks.grid": "benchmarks.grid.cli"}


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> str:
    return f"data.cache_root={tmp_path_factory.mktemp('cache')}"


def _tiny(cache: str, tmp_path: Path, *overrides: str):
    return compose_config(*TINY, cache, f"output_dir={tmp_path / 'run'}", "+exp=unseen_shapes", *overrides)


# --- config values ---------------------------------------------------------------------------------


@pytest.mark.parametrize("override, message", [
    ("data.pair.noise_sigma=-1", "data.pair.noise_sigma=-1 is invalid: it must be a number >= 0"),  # ran noise-free
    ("data.pair.noise_sigma=nan", "data.pair.noise_sigma=nan is invalid: it must be a number >= 0"),
    ("data.pair.noise_clip=0", "data.pair.noise_clip=0 is invalid: it must be a number > 0"),
    ("data.pair.rot_mag=-10", "data.pair.rot_mag=-10 is invalid: it must be a number in [0, 180]"),
    ("data.pair.trans_mag=-0.5", "data.pair.trans_mag=-0.5 is invalid: it must be a number >= 0"),
    ("data.pair.overlap_ratio=1.5", "data.pair.overlap_ratio=1.5 is invalid: it must be a number in (0, 1] (or null)"),
    ("data.pair.rpmnet_p_keep=0", "data.pair.rpmnet_p_keep=0 is invalid: it must be a number in (0, 1]"),
    ("data.pair.prnet_num_keep=0", "data.pair.prnet_num_keep=0 is invalid: it must be an integer >= 3"),
    ("data.batch_size=abc", "data.batch_size='abc' is invalid: it must be an integer >= 1 (or null)"),  # 74-line traceback
    ("data.batch_size=8.5", "data.batch_size=8.5 is invalid: it must be an integer >= 1 (or null)"),
    ("data.num_workers=-1", "data.num_workers=-1 is invalid: it must be an integer >= 0"),
    ("data.pin_memory=yes", "data.pin_memory='yes' is invalid: it must be true or false"),
    ("partial=yy", "partial='yy' is invalid: it must be one of prnet, rpmnet, none"),  # a 20-line traceback
    ("sampling=xs", "sampling='xs' is invalid: it must be one of os, ts, halves"),
    ("model_scale=0", "model_scale=0 is invalid: it must be a number > 0"),
    ("model.lr=-1e-3", "model.lr=-0.001 is invalid: it must be a number > 0"),
    ("model.network.num_iters=0", "model.network.num_iters=0 is invalid: it must be an integer >= 1"),
    ("model.network.trans_loss_weight=-4", "model.network.trans_loss_weight=-4 is invalid: it must be a number >= 0"),
    ("model.network.share_weights=yes", "model.network.share_weights='yes' is invalid: it must be true or false"),
    ("model.network.mask_class_weights=[0.7,-0.3]",
     "model.network.mask_class_weights=[0.7, -0.3] is invalid: it must be a list of numbers >= 0"),
])
def test_invalid_values_are_refused_at_composition(override, message):
    with pytest.raises(ConfigError) as info:
        validate_config(compose_config(override))
    assert str(info.value) == message


def _stems(group: str) -> list[str]:
    return sorted(Path(p).stem for p in glob.glob(f"{CONF}/{group}/*.yaml"))


def test_every_shipped_config_is_valid_and_keys_outside_objects_pass():
    choices = [[f"model={m}", "+exp=scan_pairs"] for m in _stems("model")] + [[f"+exp={e}"] for e in _stems("exp")]
    choices += [[f"{group}={name}"] for group in ("recipe", "trainer", "logger") for name in _stems(group)]
    for overrides in choices:
        validate_config(compose_config(*overrides))
    validate_config(compose_config("partial=rpmnet", "sampling=os"))


@pytest.mark.parametrize("override, message", [  # zero or negative budgets and intervals: tracebacks or nothing trained
    ("trainer.max_steps=0", "trainer.max_steps=0 is invalid: it must be an integer >= 1 (or -1: no limit)"),
    ("trainer.max_steps=-5", "trainer.max_steps=-5 is invalid: it must be an integer >= 1 (or -1: no limit)"),
    ("trainer.log_every_n_steps=0", "trainer.log_every_n_steps=0 is invalid: it must be an integer >= 1"),
    ("trainer.val_check_interval=0", "trainer.val_check_interval=0 is invalid: it must be a number > 0 (or null)"),
    ("callbacks.periodic_checkpoint.train_time_interval.minutes=-1",
     "callbacks.periodic_checkpoint.train_time_interval.minutes=-1 is invalid: it must be a number > 0"),
    ("+callbacks.periodic_checkpoint.every_n_train_steps=0",
     "callbacks.periodic_checkpoint.every_n_train_steps=0 is invalid: it must be an integer >= 1 (or null)"),
    # unknown keys added with + under a node that builds an object: a TypeError deep in its constructor
    ("+trainer.max_step=5", "trainer.max_step is not an option of lightning.Trainer: did you mean max_steps, max_time, "
                            "min_steps?"),
    ("+model.network.widht=0.5", "model.network.widht is not an option of src.models.omnet.OMNet: did you mean width?"),
    ("+callbacks.checkpoint.monitr=x",
     "callbacks.checkpoint.monitr is not an option of lightning.pytorch.callbacks.ModelCheckpoint: did you mean monitor?"),
    ("+data.a_new_switch=abc", "data.a_new_switch is not an option of src.data.datamodule.RegistrationDataModule: it "
                               "takes dataset, cache_root, splits, remove_axisymmetric, pair, batch_size, eval_batch_size, "
                               "num_workers, pin_memory, persistent_workers, seed, build, normals"),
])
def test_intervals_budgets_and_unknown_object_options_are_refused(override, message):
    with pytest.raises(ConfigError) as info:
        validate_config(compose_config(override))
    assert str(info.value) == message


@pytest.mark.parametrize("module, argv, message", [  # Hydra's multi-line report and exit status 1 before
    ("src.train", ["data.splits.test.slice=[-100,", "null]"],
     "error: an override does not parse (no viable alternative at input '[-100,'); quote values with brackets, "
     "commas or spaces, e.g. 'data.splits.test.slice=[-100, null]'"),
    ("src.eval", ["data=modelnet41"], "error: data=modelnet41: no such config in group data; choose one of: base, "
                                      "modelnet40, modelnet40_npy, modelnet40_resampled, scan_pairs, stanford, synthetic"),
    ("src.train", ["modle=dcp"], "error: modle is not a config key or group: did you mean model, model_scale? add a new "
                                 "key with +modle=VALUE"),
    ("src.train", ["trainer.max_step=5"], "error: trainer.max_step is not a key of trainer: did you mean "
                                          "trainer.max_steps, trainer.max_epochs? add a new key with +trainer.max_step=VALUE"),
    ("benchmarks.grid", ["+benchmark=nosuch"], "error: benchmark=nosuch: no such config in group benchmark; choose one "
                                               "of: default, demo, modelnet_real_airplane, modelnet_real_bathtub, "
                                               "published_weights, real_airplane, real_categories, scan_pairs, stanford, table1_npy"),
])
def test_hydra_override_errors_are_one_line_exit_2(module, argv, message, monkeypatch, capsys):
    main = importlib.import_module(COMMAND_MODULES.get(module, module)).main
    monkeypatch.setattr(sys, "argv", [module, *argv])
    monkeypatch.setenv("HYDRA_FULL_ERROR", "0")  # (restored after the test)
    with pytest.raises(SystemExit) as info:
        main()
    assert info.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [message]


@pytest.mark.parametrize("entry, override, message", [
    (src.train, "data.batch_size=abc", "error: data.batch_size='abc' is invalid: it must be an integer >= 1"),
    (src.eval, "partial=yy", "error: partial='yy' is invalid: it must be one of prnet, rpmnet, none"),
    # a UserError raised inside a constructor Hydra instantiates (and wraps): still one line
    (src.train, "+data.splits.extra={split: train}", "error: data.splits has unknown stages ['extra']"),
    (src.train, "data.splits.train=5", "error: data.splits.train=5 is invalid: it must be a mapping such as "
                                       "{split: test, categories: [airplane], slice: [-100, null]}"),
])
def test_entry_points_stop_with_one_line(entry, override, message, tmp_path, capsys, cache):
    """``main`` below Hydra's decorator: exit_on_user_error(record_failures(...)), as the command runs it."""
    cfg = compose_config(*TINY, cache, override, f"output_dir={tmp_path}")
    with pytest.raises(SystemExit) as exit_info:
        entry.main.__wrapped__(cfg)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(message)
    assert (tmp_path / "failure.json").is_file()


def test_a_network_rejecting_its_config_is_one_line(tmp_path, cache):
    with pytest.raises(ConfigError, match=r"^model: src.models.omnet.OMNet rejects its config: mask_mode must be one of"):
        train(_tiny(cache, tmp_path, "model.network.mask_mode=foo"))


@pytest.mark.parametrize("device", ["meta", "cpu"])  # meta: the size overflows; cpu: no memory holds it
def test_a_network_too_large_to_build_is_one_line(device):
    cfg = compose_config("model_scale=605398.0" if device == "meta" else "model_scale=100000.0")
    with torch.device(device), pytest.raises(ConfigError, match=r"^model: src.models.omnet.OMNet is too large to build "
                                                                 r"\(.*\): lower model_scale"):
        build_module(cfg.model)


def test_a_network_without_the_two_methods_is_one_line():
    with pytest.raises(ConfigError, match=r"^model.network: torch.nn.Linear is not a registration network: it has no "
                                          r"loss method \(the two methods"):
        check_network(torch.nn.Linear(3, 3), "torch.nn.Linear")
    with pytest.raises(ConfigError, match="it has no forward or loss method"):
        check_network(object(), "builtins.object")
    translation = torch.nn.Linear(3, 3)
    translation.loss = lambda outputs, transform_gt: {"loss": torch.zeros(())}
    assert check_network(translation, "a.Translation") is translation


# --- training that would train nothing --------------------------------------------------------------


def test_training_set_smaller_than_one_batch_is_refused_before_training(tmp_path, cache):
    with pytest.raises(ConfigError) as info:  # was: global_step 0, no checkpoint, test metrics, exit 0
        train(_tiny(cache, tmp_path, "data.batch_size=64"))
    assert str(info.value).startswith("the training set has 14 shapes, fewer than one batch of data.batch_size=64; ")
    assert "set data.batch_size=14 or less" in str(info.value)
    assert not (tmp_path / "run" / "metrics.json").exists() and not (tmp_path / "run" / "checkpoints").exists()
    with pytest.raises(ConfigError, match=r"^data.batch_size is null \(a test-only data config\): set data.batch_size=N"):
        train(_tiny(cache, tmp_path, "data.batch_size=null"))


def test_a_run_without_optimisation_steps_is_not_tested(tmp_path, cache):
    with pytest.raises(ConfigError, match=r"training ended after 0 optimisation steps \(trainer.max_steps=0, "):
        train(_tiny(cache, tmp_path, "trainer.max_steps=0"))
    assert not (tmp_path / "run" / "metrics.json").exists()


# --- checkpoints to resume from ---------------------------------------------------------------------


def _foreign(tmp_path: Path) -> Path:
    path = tmp_path / "foreign.ckpt"
    torch.save(torch.nn.Linear(50, 100).state_dict(), path)  # a state-dict dump of another model
    return path


def _truncated(tmp_path: Path) -> Path:
    path = tmp_path / "truncated.ckpt"
    path.write_bytes(SHIPPED.read_bytes()[: SHIPPED.stat().st_size // 2])
    return path


@pytest.mark.parametrize("make, overrides, message", [
    (_foreign, (), "was not written by src.train (no network config inside)"),
    (_truncated, (), "is not a readable PyTorch checkpoint (RuntimeError: truncated or another kind of file)"),
    (lambda tmp: SHIPPED, ("model_scale=0.25",), "holds weights only, no training state to resume"),
    (lambda tmp: SHIPPED, ("model=dcp",), "holds a src.models.omnet.OMNet network but the config asks for"),
])
def test_resuming_from_a_wrong_checkpoint_is_one_line(make, overrides, message, tmp_path, cache):
    path = make(tmp_path)
    with pytest.raises(CheckpointError) as info:  # were 21 KB / 51-line tracebacks
        train(_tiny(cache, tmp_path, f"ckpt_path={path}", *overrides))
    assert message in str(info.value) and "\n" not in str(info.value)


# --- checkpoint files of killed saves ----------------------------------------------------------------

_KILLED_SAVE = """
import os, shutil, signal, sys
import torch
from hydra import compose, initialize_config_dir
from src.config import register_resolvers
from src.run.trainer import build_trainer
register_resolvers()
with initialize_config_dir(config_dir=sys.argv[1], version_base="1.3"):
    cfg = compose("config", overrides=["trainer.accelerator=cpu", "output_dir=" + sys.argv[2]])
trainer = build_trainer(cfg)
def killed(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGKILL)
os.replace = shutil.move = killed  # kill -9 once the bytes are written, before the rename
trainer.strategy.checkpoint_io.save_checkpoint({"weights": torch.zeros(500_000)}, sys.argv[2] + "/checkpoints/last.ckpt")
"""


def test_a_save_killed_midway_leaves_nothing_behind_after_the_next_start(tmp_path):
    system_tmp, run = tmp_path / "system_tmp", tmp_path / "run"
    system_tmp.mkdir()
    env = {**os.environ, "TMPDIR": str(system_tmp), "OMP_NUM_THREADS": "1"}
    result = subprocess.run([sys.executable, "-c", _KILLED_SAVE, str(CONF), str(run)], cwd=ROOT, env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == -signal.SIGKILL, result.stderr[-2000:]
    assert list(system_tmp.iterdir()) == []  # Lightning's writer staged a 2 MB file in the system temp folder
    left = list((run / "checkpoints").iterdir())
    assert len(left) == 1 and left[0].name.startswith(".last.ckpt.") and left[0].name.endswith(".tmp")
    build_trainer(compose_config("trainer.accelerator=cpu", f"output_dir={run}"))  # the next run starts
    assert list((run / "checkpoints").iterdir()) == []


def test_write_atomic_removes_its_temporary_on_failure_and_live_temporaries_stay(tmp_path):
    def failing(path: Path) -> None:
        path.write_text("half")
        raise OSError("disk full")

    with pytest.raises(OSError):
        write_atomic(tmp_path / "metrics.json", failing)
    assert list(tmp_path.iterdir()) == []
    mine = tmp_path / f".last.ckpt.{os.getpid()}.tmp"  # a save in progress in a running process
    mine.write_text("x")
    assert remove_stale_temporaries(tmp_path) == [] and mine.exists()


# --- what is recorded is what ran ----------------------------------------------------------


def test_an_fp16_precision_on_the_cpu_is_refused():
    """Lightning ran bf16-mixed instead, and config_resolved.yaml recorded 16-mixed."""
    with pytest.raises(ConfigError, match=r"^trainer.precision=16-mixed on the CPU: Lightning would run bf16-mixed"):
        validate_config(compose_config("trainer.accelerator=cpu", "trainer.precision=16-mixed"))
    validate_config(compose_config("trainer.accelerator=cpu", "trainer.precision=bf16-mixed"))


@pytest.mark.parametrize("override, message", [
    # an evaluation-time study printed identical numbers under different labels
    ("model.network.num_iters=2", "model.network.num_iters=2 cannot take effect: src.eval rebuilds the network from "
                                  "{ckpt}, which has model.network.num_iters=4"),
    ("model_scale=0.5", "model_scale=0.5 cannot take effect: src.eval rebuilds the network from {ckpt}, which has "
                        "model.network.width=0.25"),
    ("model.network.share_weights=true", "model.network.share_weights=true cannot take effect: src.eval rebuilds "
                                         "the network from {ckpt}, which has model.network.share_weights=False"),
])
def test_eval_refuses_overrides_the_checkpoint_overrides(override, message, tmp_path, cache):
    from src.run.recorded import refuse_unused_in_eval

    cfg = _tiny(cache, tmp_path, override, f"ckpt_path={SHIPPED}")
    hparams = torch.load(SHIPPED, map_location="cpu", weights_only=False, mmap=True)["hyper_parameters"]
    with pytest.raises(ConfigError) as info:
        refuse_unused_in_eval(cfg, hparams, str(SHIPPED), overrides=[override])
    assert str(info.value).startswith(message.format(ckpt=SHIPPED))
    same = ["model.network.num_iters=4", "model_scale=0.25", "data.batch_size=2"]  # the checkpoint's, or no effect
    refuse_unused_in_eval(_tiny(cache, tmp_path, *same), hparams, str(SHIPPED), overrides=same)


def test_eval_follows_the_experiments_metric_convention(tmp_path, cache):
    """The checkpoint's (PRNet manner: zyx) was used whatever partial=rpmnet asked for."""
    module = src.eval.load_checkpoint(str(SHIPPED), _tiny(cache, tmp_path, "partial=rpmnet"))
    assert module.hparams["euler_seq"] == "xyz" and module.test_metrics.euler_seq == "xyz"


def test_train_refuses_weights(tmp_path, cache):
    with pytest.raises(ConfigError, match=r"^weights=official:dcp_v1: src.train does not load published weights"):
        train(_tiny(cache, tmp_path, "weights=official:dcp_v1"))


# --- accepted but not used ----------------------------------------------------------------

#: A Hydra app run in this process leaves its logging alone (its handlers would hold capsys's closed stderr).
NO_LOGGING = ["hydra/job_logging=none", "hydra/hydra_logging=none"]
TOP_LEVEL = ("the top-level keys are callbacks, ckpt_path, data, force_precision, hydra, init_weights, logger, model, model_scale, on_failure, "
             "output_dir, pairs_per_scan, partial, real_train_categories, sampling, seed, task_name, test_after_fit, "
             "test_category, test_size, train_category, trainer, val_repeat, val_size, variant, weights, weights_importer, "
             "withheld")


@pytest.mark.parametrize("override, hint", [  # were written into config_resolved.yaml and read by nothing
    ("+trainer_max_steps=5", "did you mean trainer.max_steps? "),
    ("+foo=1", ""),
    ("+seeds=3", "did you mean seed? "),
])
def test_unknown_top_level_keys_are_refused(override, hint):
    key = override[1:].split("=")[0]
    with pytest.raises(ConfigError) as info:
        validate_config(compose_config(override))
    assert str(info.value) == f"{key} is not a top-level config key (nothing reads it): {hint}{TOP_LEVEL}"


@pytest.mark.parametrize("module, argv, message", [
    ("src.train", ["+trainer_max_steps=5"], "error: trainer_max_steps is not a top-level config key (nothing reads "
                                            "it): did you mean trainer.max_steps? the top-level keys are callbacks, "),
    ("benchmarks.grid", ["+max_pair=3"], "error: max_pair is not a top-level config key (nothing reads it): the "
                                         "top-level keys are benchmark, data, demo, hydra, method_options, output_dir, "),
])
def test_unknown_top_level_keys_stop_every_entry_point_in_one_line(module, argv, message, tmp_path, monkeypatch,
                                                                   capsys):
    main = importlib.import_module(COMMAND_MODULES.get(module, module)).main
    monkeypatch.setattr(sys, "argv", [module, *argv, f"hydra.run.dir={tmp_path}", f"output_dir={tmp_path}", *NO_LOGGING])
    with pytest.raises(SystemExit) as info:
        main()
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(message)


def test_a_pair_size_the_cache_layout_cannot_honour_is_refused(tmp_path, cache):
    """The synthetic cache's clouds are whole samplings of 2,048 points: num_points=1024 ran on 2,048."""
    datamodule = hydra.utils.instantiate(_tiny(cache, tmp_path, "data.pair.num_points=1024").data)
    with pytest.raises(ConfigError) as info:
        datamodule.setup("test")
    assert str(info.value) == (
        "data.pair.num_points=1024 cannot take effect on the synthetic cache (layout independent_samplings): each "
        "cloud is a whole sampling of 2048 points; sample 1024 points per sampling (data.build.num_points=1024), "
        "or use data.pair.num_points=2048")
    check_pair_layout({"num_points": 1024}, "disjoint_subsets", 10_000, "modelnet40_resampled")  # picks 1,024 points
    check_pair_layout({"num_points": 2048}, "single_sampling", 2048, "modelnet40")  # the sampling's own size
    with pytest.raises(ConfigError, match=r"^data.pair.num_points=1024 cannot take effect on the modelnet40 cache "
                                          r"\(layout single_sampling\).* \(python -m src.data.prepare modelnet40 "
                                          r"--source PATH --num-points 1024\)"):
        check_pair_layout({"num_points": 1024}, "single_sampling", 2048, "modelnet40")


@pytest.mark.parametrize("overrides, message", [  # accepted, recorded and read by nothing
    (["data.pair.rpmnet_p_keep=0.5"], "data.pair.rpmnet_p_keep=0.5 cannot take effect: it is read only with "
                                      "data.pair.partial=rpmnet, and this run has data.pair.partial=prnet"),
    (["partial=rpmnet", "data.pair.prnet_num_keep=512"], "data.pair.prnet_num_keep=512 cannot take effect: it is read "
                                                         "only with data.pair.partial=prnet, and this run has "
                                                         "data.pair.partial=rpmnet"),
    (["data.pair.twist_mag=0.4"], "data.pair.twist_mag=0.4 cannot take effect: it is read only with "
                                  "data.pair.perturbation=twist, and this run has data.pair.perturbation=euler"),
    (["+exp=pointnetlk_protocol", "data.pair.rot_mag=90"], "data.pair.rot_mag=90 cannot take effect: it is read only "
                                                           "with data.pair.perturbation=euler, and this run has "
                                                           "data.pair.perturbation=twist"),
    (["data.pair.noise_clip=0.1"], "data.pair.noise_clip=0.1 cannot take effect: it is read only with "
                                   "data.pair.noise_sigma other than 0, and this run has data.pair.noise_sigma=0.0"),
    (["+exp=scan_pairs", "sampling=os"], "sampling=os cannot take effect: it is read only with data.dataset other "
                                         "than scan_pairs, and this run has data.dataset=scan_pairs"),
])
def test_overrides_the_pair_pipeline_does_not_read_are_refused(overrides, message):
    from src.run.recorded import refuse_unread_overrides

    with pytest.raises(ConfigError) as info:
        refuse_unread_overrides(compose_config(*overrides), overrides=overrides)
    assert str(info.value).startswith(message)
    for read in (["partial=rpmnet", "data.pair.rpmnet_p_keep=0.5"], ["data.pair.noise_sigma=0.01", "data.pair.noise_clip=0.1"],
                 ["+exp=pointnetlk_protocol", "data.pair.twist_mag=0.4"], ["data.pair.rot_mag=90"]):
        refuse_unread_overrides(compose_config(*read), overrides=read)


def test_src_train_refuses_an_override_it_does_not_read(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["src.train", "data.pair.rpmnet_p_keep=0.5", f"hydra.run.dir={tmp_path}",
                                      f"output_dir={tmp_path}", *NO_LOGGING])
    with pytest.raises(SystemExit) as info:
        src.train.main()
    assert info.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: data.pair.rpmnet_p_keep=0.5 cannot take effect: it is read only with data.pair.partial=rpmnet, and "
        "this run has data.pair.partial=prnet; drop the override or change data.pair.partial"]


@pytest.mark.parametrize("override, message", [  # the test ran on the last weights, labelled as the selected ones
    ("trainer.limit_val_batches=0", "trainer.limit_val_batches=0 turns validation off, so callbacks.checkpoint "
                                    "(monitor val/score) never selects a checkpoint and the test would run on the last "
                                    "weights"),
    ("trainer.limit_val_batches=0.0", "trainer.limit_val_batches=0.0 turns validation off"),
    ("+callbacks.checkpoint.save_top_k=0", "callbacks.checkpoint.save_top_k=0 keeps no checkpoint selected on val/score"),
])
def test_train_refuses_a_checkpoint_selection_that_cannot_select(override, message, tmp_path, cache):
    from src.run.recorded import refuse_unused_in_train

    with pytest.raises(ConfigError) as info:
        train(_tiny(cache, tmp_path, override))
    assert str(info.value).startswith(message) and not (tmp_path / "run").exists()
    for fine in ([override, "callbacks.checkpoint.monitor=null"], ["trainer.limit_val_batches=null"],
                 ["trainer.limit_val_batches=1"], [override, "trainer.fast_dev_run=true"]):
        refuse_unused_in_train(_tiny(cache, tmp_path, *fine))
