"""Helpers shared by the tests: small batches and checks for the network tests; configs of the
entry points on tiny synthetic data; runs killed and resumed."""

import time
from pathlib import Path

import lightning as L
import pytest
import torch
from hydra import compose, initialize_config_dir

from src.config import register_resolvers
from src.geometry import euler_to_matrix, se3_apply, se3_from_rt, se3_inverse
from tests.helpers.paths import CONF

#: Overrides of a run on tiny synthetic data (14 train shapes at batch 2), a tiny network, on the CPU.
TINY = [
    "data=synthetic",
    "data.build.num_train_per_category=2",
    "data.build.num_test_per_category=1",
    "data.build.num_samplings=3",
    "data.batch_size=2",
    "data.eval_batch_size=2",
    "data.num_workers=0",
    "data.pin_memory=false",
    "model_scale=0.0625",
    "trainer.accelerator=cpu",
    "trainer.enable_progress_bar=false",
]
# 7 batches an epoch; validation every 2 steps. last.ckpt is written after every step on train-batch
# end (the time-based checkpoint's code path).
RESUME_RUN = ["+exp=unseen_shapes", "test_after_fit=false", "trainer.val_check_interval=2",
              "trainer.check_val_every_n_epoch=null", "trainer.limit_val_batches=1",
              "callbacks.periodic_checkpoint.train_time_interval=null",
              "+callbacks.periodic_checkpoint.every_n_train_steps=1", "model.lr=1e-2"]
RESUME_STEPS = 9
register_resolvers()


def _random_transforms(b: int, g: torch.Generator) -> torch.Tensor:
    rot = euler_to_matrix(torch.rand(b, 3, generator=g) * 0.8, "zyx")
    return se3_from_rt(rot, torch.rand(b, 3, generator=g) - 0.5)


def exact_pair_batch(b: int = 3, n: int = 64, seed: int = 0):
    """Random anisotropic (asymmetric) clouds with ref = gt(src) exactly: (src, ref, gt)."""
    g = torch.Generator().manual_seed(seed)
    ref = torch.randn(b, n, 3, generator=g) * torch.tensor([0.6, 0.4, 0.2])
    gt = _random_transforms(b, g)
    return se3_apply(se3_inverse(gt), ref), ref, gt


def partial_pair_batch(b: int = 4, n: int = 64, seed: int = 0):
    """Noisy, partially overlapping halves of a random anisotropic blob: (src, ref, gt)."""
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(b, 2 * n, 3, generator=g) * torch.tensor([0.6, 0.4, 0.2]) + torch.tensor([0.2, 0.0, 0.0])
    ref = base[:, :n] + 0.02 * torch.randn(b, n, 3, generator=g)
    src = base[:, n // 2 : n // 2 + n] + 0.02 * torch.randn(b, n, 3, generator=g)
    gt = _random_transforms(b, g)
    return se3_apply(se3_inverse(gt), src), ref, gt


def turned_batch(b: int, n: int) -> dict[str, torch.Tensor]:
    """Random clouds turned 0.4 rad about z and shifted, with noise on the reference (torch's global RNG): the
    first batch of a lockstep start check."""
    src = torch.rand(b, n, 3) - 0.5
    angle = torch.tensor(0.4)
    rot = torch.tensor([[angle.cos(), -angle.sin(), 0.0], [angle.sin(), angle.cos(), 0.0], [0.0, 0.0, 1.0]])
    gt = se3_from_rt(rot.expand(b, 3, 3), torch.tensor([0.1, 0.0, -0.1]).expand(b, 3))
    return {"points_src": src, "points_ref": se3_apply(gt, src) + 0.01 * torch.randn(b, n, 3), "transform_gt": gt}


def assert_rigid(transform: torch.Tensor) -> None:
    """(B,4,4) finite, orthonormal rotation with det +1, last row (0,0,0,1)."""
    b = transform.shape[0]
    assert transform.shape == (b, 4, 4) and torch.isfinite(transform).all()
    rot = transform[:, :3, :3]
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3, dtype=rot.dtype).expand(b, 3, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(b, dtype=rot.dtype), atol=1e-5, rtol=0)
    torch.testing.assert_close(transform[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=rot.dtype).expand(b, 4))


def train_losses(model: torch.nn.Module, batch, steps: int, lr: float = 1e-3, **inputs) -> list[float]:
    """Losses of ``steps`` Adam steps of ``model`` on one (src, ref, gt) batch (and keyword ``inputs``: normals)."""
    src, ref, gt = batch
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        loss = model.loss(model(src, ref, gt, **inputs), gt)["loss"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    return losses


def warm_up_batchnorm(model: torch.nn.Module, src: torch.Tensor, ref: torch.Tensor, rounds: int = 40) -> None:
    """Settle the BatchNorm running statistics of a global-feature network (``model.features``) on the
    mean-centred clouds: LK runs on them in eval mode, as the official code."""
    with torch.no_grad():
        for _ in range(rounds):
            model.features(ref - ref.mean(1, keepdim=True))
            model.features(src - src.mean(1, keepdim=True))


def reload_via_checkpoint(module, path):
    """Save ``module`` as a Lightning checkpoint at ``path`` and load it back with
    ``RegistrationModule.load_from_checkpoint`` (which rebuilds the network from its config)."""
    import lightning

    from src.models.module import RegistrationModule

    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                "pytorch-lightning_version": lightning.__version__}, path)
    return RegistrationModule.load_from_checkpoint(path, map_location="cpu").eval()


def assert_reloads_the_same(module, path, src: torch.Tensor, ref: torch.Tensor):
    """``module`` (in eval mode) reloaded from a checkpoint at ``path`` (:func:`reload_via_checkpoint`) gives
    the same outputs on (src, ref); returns the reloaded module."""
    loaded = reload_via_checkpoint(module, path)
    with torch.no_grad():
        torch.testing.assert_close(loaded(src, ref), module(src, ref))
    return loaded


def eval_losses_before_after(model: torch.nn.Module, batch, steps: int = 20,
                             lr: float = 1e-3) -> tuple[dict[str, float], dict[str, float]]:
    """For a global-feature network (LK runs on the BatchNorm running statistics): its BatchNorm statistics
    warmed up on one (src, ref, gt) batch (:func:`warm_up_batchnorm`: their drift would otherwise mask the
    learning), then its eval-mode losses on the batch before and after ``steps`` Adam steps on it."""
    src, ref, gt = batch
    warm_up_batchnorm(model, src, ref)

    def eval_losses() -> dict[str, float]:
        model.eval()
        with torch.no_grad():
            losses = model.loss(model(src, ref, gt), gt)
        model.train()
        return {k: v.item() for k, v in losses.items()}

    before = eval_losses()
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    for _ in range(steps):
        optimizer.zero_grad()
        model.loss(model(src, ref, gt), gt)["loss"].backward()
        optimizer.step()
    return before, eval_losses()


def seeded_losses_before_after(model: torch.nn.Module, batch, steps: int, lr: float) -> tuple[float, float]:
    """For stochastic networks: the loss summed over 3 fixed seeds before and after ``steps`` Adam
    steps (each drawn with its own seed), so the comparison does not depend on the random draws."""
    src, ref, gt = batch
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)

    def loss_at(seed: int) -> torch.Tensor:
        torch.manual_seed(seed)
        return model.loss(model(src, ref, gt), gt)["loss"]

    with torch.no_grad():
        before = sum(loss_at(s).item() for s in range(3))
    for step in range(steps):
        loss = loss_at(100 + step)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        after = sum(loss_at(s).item() for s in range(3))
    return before, after


# --- configs of the entry points -------------------------------------------------------------------


def compose_config(*overrides: str, config_name: str = "config", hydra_cfg: bool = False):
    """``conf/<config_name>.yaml`` composed with ``overrides`` (and Hydra's own node with ``hydra_cfg``)."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name, overrides=list(overrides), return_hydra_config=hydra_cfg)


def tiny_config(tmp_path: Path, *overrides: str):
    """A :data:`TINY` run with its cache in ``tmp_path/cache`` and its output in ``tmp_path/run``."""
    return compose_config(*TINY, f"data.cache_root={tmp_path / 'cache'}", f"output_dir={tmp_path / 'run'}", *overrides)


# --- runs killed and resumed -----------------------------------------------------------------------


class KillAt(L.Callback):
    """Raises at the start of training step ``step``, like a process killed there (a time limit)."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_start(self, trainer: L.Trainer, *args) -> None:
        if trainer.global_step == self.step:
            raise RuntimeError(f"killed at step {self.step}")


class PauseAt(L.Callback):
    """At the start of training step ``step``: touch ``ready`` and wait (at most a minute) until the
    run's :class:`~src.run.signals.CheckpointOnSignal` has received a signal sent from outside."""

    def __init__(self, step: int, ready: str) -> None:
        self.step, self.ready = step, Path(ready)

    def on_train_batch_start(self, trainer: L.Trainer, *args) -> None:
        from src.run.signals import CheckpointOnSignal

        if trainer.global_step != self.step:
            return
        watcher = next(c for c in trainer.callbacks if isinstance(c, CheckpointOnSignal))
        self.ready.touch()
        deadline = time.monotonic() + 60
        while watcher.received is None and time.monotonic() < deadline:
            time.sleep(0.05)


def last_weights(run_dir: Path) -> dict[str, torch.Tensor]:
    return torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]


def killed_and_resumed(tmp_path: Path, run_dir: Path, stop: int, *overrides: str):
    """Train a :data:`TINY` run into ``run_dir``, killed at step ``stop``, then resume it from its
    ``last.ckpt``; returns the weights at the kill and at the end."""
    from src.train import train

    kill = [f"+callbacks.kill._target_={__name__}.KillAt", f"+callbacks.kill.step={stop}"]
    with pytest.raises(RuntimeError, match=f"killed at step {stop}"):
        train(tiny_config(tmp_path, *overrides, *kill, f"output_dir={run_dir}"))
    at_stop = last_weights(run_dir)
    train(tiny_config(tmp_path, *overrides, f"output_dir={run_dir}", f"ckpt_path={run_dir / 'checkpoints' / 'last.ckpt'}"))
    return at_stop, last_weights(run_dir)


def assert_same_weights(got: dict[str, torch.Tensor], expected: dict[str, torch.Tensor],
                        at_stop: dict[str, torch.Tensor]) -> None:
    """The resumed run's weights equal the uninterrupted run's exactly, and differ from those at the kill."""
    assert got.keys() == expected.keys()
    changed = [k for k in got if not torch.equal(got[k], expected[k])]
    assert not changed, f"resumed weights differ from the uninterrupted run in {changed[:5]}"
    assert any(not torch.equal(got[k], v) for k, v in at_stop.items())  # it did train further
