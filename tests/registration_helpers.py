"""Small batches and checks shared by the network tests."""

import torch

from src.geometry import euler_to_matrix, se3_apply, se3_from_rt, se3_inverse


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


def assert_rigid(transform: torch.Tensor) -> None:
    """(B,4,4) finite, orthonormal rotation with det +1, last row (0,0,0,1)."""
    b = transform.shape[0]
    assert transform.shape == (b, 4, 4) and torch.isfinite(transform).all()
    rot = transform[:, :3, :3]
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3, dtype=rot.dtype).expand(b, 3, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(b, dtype=rot.dtype), atol=1e-5, rtol=0)
    torch.testing.assert_close(transform[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=rot.dtype).expand(b, 4))


def train_losses(model: torch.nn.Module, batch, steps: int, lr: float = 1e-3) -> list[float]:
    """Losses of ``steps`` Adam steps of ``model`` on one (src, ref, gt) batch."""
    src, ref, gt = batch
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        loss = model.loss(model(src, ref, gt), gt)["loss"]
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
