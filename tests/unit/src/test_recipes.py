"""Each method's training recipe (conf/recipe/<model>.yaml) is what `model=<name>` trains with: its
batch, budget, optimiser, schedule and checkpoint selection reach the datamodule, the trainer and
RegistrationModule; every value cites the authors' file:line (the values live in the recipes only);
explicit overrides still win; the schedules RegistrationModule builds."""

from __future__ import annotations

import re
from pathlib import Path

import hydra
import lightning as L
import pytest
import torch
from omegaconf import OmegaConf
from torch import nn
from torch.optim.lr_scheduler import LambdaLR, MultiStepLR, OneCycleLR, ReduceLROnPlateau
from torch.utils.data import DataLoader

from src.utils.errors import ConfigError
from src.models.module import RegistrationModule, WarmupCosine
from src.train import train
from src.run.trainer import build_trainer
from tests.helpers.registration_helpers import (
    CONF,
    RESUME_RUN,
    RESUME_STEPS,
    assert_same_weights,
    compose_config,
    killed_and_resumed,
    last_weights,
    reload_via_checkpoint,
    tiny_config,
)

MODELS = sorted(p.stem for p in (CONF / "model").glob("*.yaml"))
RECIPES = sorted(p.stem for p in (CONF / "recipe").glob("*.yaml"))
SCHEDULER_TYPES = {"multistep": MultiStepLR, "plateau": ReduceLROnPlateau, "cosine": LambdaLR, "onecycle": OneCycleLR}

#: Recipes of this framework's own studies, not the authors' (their sources are named in their header).
OWN_RECIPES = ("omnet_cpu", "omnet_finetune")
#: A citation of a file and line of the authors' code (or paper): ``main.py:541``, ``params.json:12-13``.
CITATION = re.compile(r"[\w./-]+\.\w+:\d+")


def _compose(tmp_path: Path, *overrides: str):
    return compose_config(f"output_dir={tmp_path / 'run'}", f"data.cache_root={tmp_path / 'cache'}",
                          "trainer.accelerator=cpu", "model_scale=0.0625", *overrides)


def _assert_scheduler(module: RegistrationModule, spec: dict | None) -> None:
    """``configure_optimizers`` builds the scheduler that ``spec`` (a recipe's model.scheduler) names."""
    built = module.configure_optimizers()
    if spec is None:
        assert "lr_scheduler" not in built
        return
    config, scheduler = built["lr_scheduler"], built["lr_scheduler"]["scheduler"]
    assert type(scheduler) is SCHEDULER_TYPES[spec["name"]]
    if spec["name"] == "multistep":
        assert sorted(scheduler.milestones.elements()) == spec["milestones"] and scheduler.gamma == spec["gamma"]
        assert config["interval"] == spec["interval"]
    if spec["name"] == "plateau":
        assert (scheduler.factor, scheduler.patience, scheduler.min_lrs) == (spec["factor"], spec["patience"],
                                                                             [spec["min_lr"]])
        assert config["interval"] == "epoch" and config["monitor"] == spec["monitor"]


def test_each_model_has_a_recipe_and_each_recipe_a_model():
    """A recipe is a model's (``<model>.yaml``) or a named variant of one (``<model>_<what>.yaml``)."""
    assert set(MODELS) <= set(RECIPES) and set(OWN_RECIPES) <= set(RECIPES)
    assert all(name in MODELS or name.rsplit("_", 1)[0] in MODELS for name in RECIPES)


def _cited_leaves(text: str):
    """(line number, key, cited) of every leaf value of a recipe's YAML text, read line by line. A value is
    cited by a file:line in its own line's comment, in the comments of the lines above it in its block
    (a block's comment may span its lines) or in an enclosing key's comment."""
    lines = [(len(line) - len(line.lstrip()), *line.partition("#")[::2]) for line in text.splitlines()]
    for number, (indent, body, comment) in enumerate(lines, start=1):
        key, _, value = body.partition(":")
        if not value.strip() or body.lstrip().startswith("-") or key.strip() == "defaults":
            continue
        comments, depth = [comment], indent  # depth: the indentation of the innermost key reached
        for above, above_body, above_comment in reversed(lines[:number - 1]):
            if depth == indent and (above >= indent or not above_body.strip()):  # a line of its block
                comments.append(above_comment)
            elif above_body.strip() and above < depth:  # an enclosing key
                comments.append(above_comment)
                depth = above
        yield number, key.strip(), any(CITATION.search(c) for c in comments)


@pytest.mark.parametrize("name", [name for name in RECIPES if name not in OWN_RECIPES])
def test_every_recipe_value_cites_its_source(name):
    uncited = [f"{name}.yaml:{number} {key}" for number, key, cited in _cited_leaves((CONF / "recipe" / f"{name}.yaml").read_text())
               if not cited]
    assert not uncited, f"values without a file:line of the authors' code in their comment: {uncited}"


def test_an_uncited_value_is_found():
    text = "data:\n  batch_size: 32   # --batch_size 32 (main.py:541)\nmodel:\n  lr: 1.0e-3   # the authors' rate\n"
    assert [(key, cited) for _, key, cited in _cited_leaves(text)] == [("batch_size", True), ("lr", False)]


def test_the_cpu_recipe_decays_at_its_fraction_of_any_budget(tmp_path):
    recipe = _recipe("omnet_cpu")
    cfg = _compose(tmp_path, "+exp=unseen_shapes", "recipe=omnet_cpu", "trainer.max_steps=500")
    assert (cfg.model_scale, cfg.trainer.max_steps) == (0.0625, 500)  # the command line wins
    assert (cfg.data.batch_size, cfg.model.lr) == (recipe.data.batch_size, recipe.model.lr)
    plain = compose_config(f"output_dir={tmp_path / 'run'}", "recipe=omnet_cpu")
    assert (plain.model_scale, plain.trainer.max_steps, plain.model.scheduler.fractions) == (
        recipe.model_scale, recipe.trainer.max_steps, recipe.model.scheduler.fractions)
    rates, _ = _fit({"name": "multistep", "fractions": [0.5], "gamma": 0.1}, max_steps=6)
    assert rates == pytest.approx([1.0] * 3 + [0.1] * 3)
    rates, _ = _fit({"name": "multistep", "fractions": [0.5], "gamma": 0.1}, max_epochs=4)  # 12 steps
    assert rates == pytest.approx([1.0] * 6 + [0.1] * 6)


def test_the_finetuning_recipe_is_the_cpu_recipe_at_its_final_rate_without_a_schedule(tmp_path):
    cpu, finetune = _recipe("omnet_cpu"), _recipe("omnet_finetune")
    assert finetune.model.lr == pytest.approx(cpu.model.lr * cpu.model.scheduler.gamma) and finetune.model.scheduler is None
    assert (finetune.model_scale, finetune.data.batch_size) == (cpu.model_scale, cpu.data.batch_size)
    cfg = _compose(tmp_path, "+exp=unseen_shapes", "recipe=omnet_finetune", "trainer.max_steps=50")
    assert cfg.model.lr == finetune.model.lr and cfg.model.scheduler is None and cfg.trainer.max_steps == 50


@pytest.mark.parametrize("name", MODELS)
def test_every_model_config_composes_with_or_without_a_recipe(name, tmp_path):
    cfg = _compose(tmp_path, f"model={name}")
    assert cfg.data.batch_size >= 1 and (cfg.trainer.max_steps > 0 or cfg.trainer.max_epochs > 0)


def _recipe(name: str):
    """``conf/recipe/<name>.yaml`` composed on its own (with the recipes it extends)."""
    return compose_config(config_name=f"recipe/{name}")


def _leaves(node, prefix: str = ""):
    """(dotted key, value) of every leaf of a plain nested dict."""
    for key, value in node.items():
        if isinstance(value, dict) and value:
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


@pytest.mark.parametrize("name", RECIPES)
def test_recipe_reaches_the_datamodule_trainer_and_module(name, tmp_path):
    recipe = _recipe(name)
    model = name if name in MODELS else name.rsplit("_", 1)[0]
    cfg = _compose(tmp_path, f"model={model}", f"recipe={name}")
    for key, value in _leaves(OmegaConf.to_container(recipe)):
        if key != "model_scale":  # (set on the command line by _compose)
            assert OmegaConf.select(cfg, key) == value, key
    datamodule, trainer = hydra.utils.instantiate(cfg.data), build_trainer(cfg)
    assert datamodule.batch_size == recipe.data.batch_size
    assert (trainer.max_steps, trainer.max_epochs) == (recipe.trainer.max_steps, recipe.trainer.max_epochs)
    assert trainer.checkpoint_callback.monitor == recipe.callbacks.checkpoint.monitor
    module = hydra.utils.instantiate(cfg.model)
    if isinstance(module, RegistrationModule):  # (a model may bring its own LightningModule)
        assert (module.hparams["lr"], module.hparams["weight_decay"]) == (recipe.model.lr, recipe.model.weight_decay)
        spec = OmegaConf.to_container(recipe.model).get("scheduler")
        assert module.hparams["scheduler"] == spec
        if "fractions" not in (spec or {}):  # (milestones from the run's length: test_the_cpu_recipe_...)
            _assert_scheduler(module, spec)


@pytest.mark.parametrize("name", MODELS)
def test_a_model_trains_with_its_recipe_by_default(name, tmp_path):
    cfg = _compose(tmp_path, f"model={name}")
    for key, value in _leaves(OmegaConf.to_container(_recipe(name))):
        assert OmegaConf.select(cfg, key) == value, key


def test_explicit_overrides_win_over_the_recipe(tmp_path):
    cfg = _compose(tmp_path, "model=dcp", "data.batch_size=8", "trainer.max_epochs=3", "model.lr=0.01",
                   "model.scheduler.milestones=[1]", "callbacks.checkpoint.monitor=val/score")
    datamodule, trainer = hydra.utils.instantiate(cfg.data), build_trainer(cfg)
    assert datamodule.batch_size == 8 and trainer.max_epochs == 3 and trainer.checkpoint_callback.monitor == "val/score"
    module = hydra.utils.instantiate(cfg.model)
    assert module.hparams["lr"] == 0.01
    _assert_scheduler(module, {"name": "multistep", "interval": "epoch", "milestones": [1], "gamma": 0.1})


def test_trainer_groups_keep_the_recipe_and_smoke_overrides_it(tmp_path):
    recipe = _recipe("dcp")
    gpu = _compose(tmp_path, "model=dcp", "trainer=gpu")
    assert (gpu.data.batch_size, gpu.trainer.max_steps, gpu.trainer.max_epochs) == (
        recipe.data.batch_size, recipe.trainer.max_steps, recipe.trainer.max_epochs)
    smoke = _compose(tmp_path, "model=dcp", "trainer=smoke")
    assert (smoke.data.batch_size, smoke.trainer.max_steps, smoke.model.lr) == (8, 16, 1e-3)
    demo = _compose(tmp_path, "+exp=unseen_shapes", "data=synthetic", "trainer=smoke")
    assert (demo.data.batch_size, demo.trainer.max_steps, demo.model.lr) == (8, 16, 1e-3)


def test_another_recipe_can_be_chosen(tmp_path):
    cfg, recipe = _compose(tmp_path, "model=dcp", "recipe=omnet"), _recipe("omnet")
    assert cfg.model.network._target_ == "baselines.learned.dcp.DCP"
    assert (cfg.data.batch_size, cfg.trainer.max_steps, cfg.model.scheduler.milestones) == (
        recipe.data.batch_size, recipe.trainer.max_steps, recipe.model.scheduler.milestones)


@pytest.mark.parametrize(("partial", "points"), [("prnet", 768), ("rpmnet", 717)])
def test_fmr_decoder_reconstructs_the_datas_cloud_size(partial, points, tmp_path):
    module = hydra.utils.instantiate(_compose(tmp_path, "model=fmr", f"partial={partial}").model)
    assert module.hparams["network"]["decoder_points"] == points
    assert module.network.decoder.out.out_features == 3 * points
    assert reload_via_checkpoint(module, tmp_path / "fmr.ckpt").network.decoder.out.out_features == 3 * points


# --- the schedules, stepped by Lightning on a one-parameter network --------------------------------


class Translation(nn.Module):
    """A translation-only network; ``flat``: its loss is 1 whatever it predicts (no progress)."""

    def __init__(self, flat: bool = False) -> None:
        super().__init__()
        self.flat = flat
        self.t = nn.Parameter(torch.zeros(3))

    def forward(self, points_src, points_ref, transform_gt=None) -> dict:
        rows = torch.cat([torch.eye(3), self.t[:, None]], dim=1)
        transform = torch.cat([rows, torch.tensor([[0.0, 0, 0, 1]])])
        return {"transforms": [transform.expand(points_src.shape[0], 4, 4)]}

    def loss(self, outputs: dict, transform_gt) -> dict:
        error = ((outputs["transforms"][-1][:, :3, 3] - transform_gt[:, :3, 3]) ** 2).mean()
        return {"loss": error * 0 + 1 if self.flat else error}


class LearningRates(L.Callback):
    """The learning rate of every training step."""

    def __init__(self) -> None:
        self.rates: list[float] = []

    def on_train_batch_start(self, trainer: L.Trainer, *args) -> None:
        self.rates.append(trainer.optimizers[0].param_groups[0]["lr"])


def _pairs(count: int) -> DataLoader:
    gt = torch.eye(4)
    gt[:3, 3] = torch.tensor([0.1, -0.2, 0.3])
    pair = {"points_src": torch.rand(8, 3), "points_ref": torch.rand(8, 3), "transform_gt": gt}
    return DataLoader([pair] * count, batch_size=1)


def _fit(scheduler: dict | None, flat: bool = False, **limits) -> tuple[list[float], RegistrationModule]:
    """Learning rates of a fit at lr 1 on 3 batches an epoch (validation: 1 batch, every epoch)."""
    module = RegistrationModule({"_target_": f"{__name__}.Translation", "flat": flat}, lr=1.0, scheduler=scheduler)
    rates = LearningRates()
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, num_sanity_val_steps=0, callbacks=[rates], **limits)
    trainer.fit(module, train_dataloaders=_pairs(3), val_dataloaders=_pairs(1))
    return rates.rates, module


def test_multistep_in_epochs_follows_the_batches_per_epoch():
    rates, _ = _fit({"name": "multistep", "interval": "epoch", "milestones": [1], "gamma": 0.1}, max_epochs=2)
    assert rates == pytest.approx([1.0] * 3 + [0.1] * 3)


def test_plateau_halves_after_each_epoch_without_validation_progress():
    spec = {"name": "plateau", "monitor": "val/loss", "factor": 0.5, "patience": 0, "min_lr": 0.3}
    rates, _ = _fit(spec, flat=True, max_epochs=4)
    assert rates == pytest.approx([1.0] * 6 + [0.5] * 3 + [0.3] * 3)  # epoch 1 (0-based) is the first without progress


def test_plateau_per_validation_counts_patience_in_validations():
    """Validated every 2 steps over 3-batch epochs: the rate halves after each validation without progress."""
    spec = {"name": "plateau", "monitor": "val/loss", "factor": 0.5, "patience": 0, "min_lr": 0.1,
            "interval": "validation"}
    rates, _ = _fit(spec, flat=True, max_steps=8, val_check_interval=2, check_val_every_n_epoch=None)
    assert rates == pytest.approx([1.0] * 4 + [0.5] * 2 + [0.25] * 2)  # validations after steps 2, 4, 6


def test_cosine_warms_up_then_anneals_over_the_epochs_of_the_run():
    rates, module = _fit({"name": "cosine", "warmup_steps": 2, "min_lr": 0.1}, max_epochs=4)
    assert module.lr_schedulers().lr_lambdas[0].total_steps == 12  # 4 epochs of 3 batches
    assert rates[:3] == pytest.approx([0.5, 1.0, 1.0])
    assert all(a > b for a, b in zip(rates[2:], rates[3:])) and rates[-1] > 0.1
    assert WarmupCosine(2, 12, 0.1)(12) == pytest.approx(0.1)


def test_onecycle_spans_the_run():
    rates, _ = _fit({"name": "onecycle", "pct_start": 0.25, "div_factor": 10.0}, max_steps=8)
    assert len(rates) == 8 and rates[0] == pytest.approx(0.1) and max(rates) == pytest.approx(1.0)
    assert rates.index(max(rates)) == 1 and rates[-1] < rates[0]


def test_older_step_milestones_are_a_multistep_schedule():
    module = RegistrationModule({"_target_": f"{__name__}.Translation"}, lr_milestones=[5], lr_gamma=0.5)
    assert module.hparams["scheduler"] == {"name": "multistep", "milestones": [5], "gamma": 0.5, "interval": "step"}


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"scheduler": {"name": "exponential"}}, "must be one of"),
    ({"scheduler": {"name": "cosine", "milestones": [3]}}, "cosine takes"),
    ({"scheduler": {"name": "multistep", "milestones": [3]}, "lr_milestones": [3]}, "not both"),
])
def test_bad_scheduler_configs_are_refused(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        RegistrationModule({"_target_": f"{__name__}.Translation"}, **kwargs)


def test_multistep_counts_steps_or_epochs_only():
    module = RegistrationModule({"_target_": f"{__name__}.Translation"},
                                scheduler={"name": "multistep", "milestones": [3], "interval": "epochs"})
    with pytest.raises(ConfigError, match="step or epoch"):
        module.configure_optimizers()


@pytest.mark.parametrize(("spec", "message"), [
    ({"milestones": [3], "fractions": [0.5]}, "not both"),
    ({"fractions": [0.5], "interval": "epoch"}, "not both"),
    ({"fractions": [1.5]}, "must lie in"),
])
def test_multistep_fractions_are_checked(spec, message):
    module = RegistrationModule({"_target_": f"{__name__}.Translation"}, scheduler={"name": "multistep", **spec})
    with pytest.raises(ConfigError, match=message):
        module.configure_optimizers()


def test_a_schedule_over_the_run_needs_its_length():
    with pytest.raises(ConfigError, match="needs the run's length"):
        _fit({"name": "cosine"}, max_steps=-1, max_epochs=-1)


@pytest.mark.parametrize("schedule", [
    ("~model.scheduler", "+model.scheduler={name: cosine, warmup_steps: 2}"),
    ("~model.scheduler", "+model.scheduler={name: onecycle}"),
    ("model=deepgmr", "model.scheduler.patience=0"),
], ids=["cosine", "onecycle", "plateau"])
def test_schedules_resume_bit_for_bit(schedule, tmp_path):
    """Killed after the first epoch's end (step 8 of 9; 7 steps an epoch), resumed from last.ckpt."""
    run = [*RESUME_RUN, *schedule, f"trainer.max_steps={RESUME_STEPS}"]
    train(tiny_config(tmp_path, *run, f"output_dir={tmp_path / 'full'}"))
    at_stop, resumed = killed_and_resumed(tmp_path, tmp_path / "killed", 8, *run)
    assert_same_weights(resumed, last_weights(tmp_path / "full"), at_stop)
