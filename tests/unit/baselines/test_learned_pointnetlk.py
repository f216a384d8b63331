"""PointNetLK: rigid per-iteration estimates, BatchNorm handling, loss terms, training lowers the loss,
test-time iterations, and the two-stage recipe (classifier features as feature_init)."""

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader

from baselines.learned.pointnet_classifier import ClassificationModule
from baselines.learned.pointnetlk import PointNetLK
from baselines.learned.published import PUBLISHED
from src.utils.errors import CheckpointError
from src.geometry import se3_inverse
from tests.helpers.registration_helpers import eval_losses_before_after
from tests.helpers.registration_helpers import assert_rigid as _assert_rigid
from tests.helpers.registration_helpers import partial_pair_batch as _batch


def test_forward_returns_rigid_transforms_per_iteration():
    torch.manual_seed(0)
    model = PointNetLK(width=0.125, max_iter=6, eval_max_iter=9)
    src, ref, gt = _batch(b=3, n=96)
    out = model(src, ref, gt)
    assert len(out["transforms"]) == 6 and out["residual"].shape == (3, 128)
    for transform in out["transforms"]:
        _assert_rigid(transform)
    assert model.training and model.encoder.training  # eval mode inside LK only
    model.eval()
    with torch.no_grad():
        out = model(src, ref)
    assert len(out["transforms"]) == 9  # the official test's iteration count (20 by default)
    _assert_rigid(out["transforms"][-1])


def test_batchnorm_statistics_update_only_in_training():
    model = PointNetLK(width=0.125, max_iter=2)
    src, ref, _ = _batch()
    bn = next(m for m in model.modules() if isinstance(m, torch.nn.BatchNorm1d))
    model.eval()
    with torch.no_grad():
        model(src, ref)
    assert bn.num_batches_tracked.item() == 0
    model.train()
    model(src, ref)
    assert bn.num_batches_tracked.item() == 2  # one training-mode pass per cloud, then frozen in LK


def test_loss_terms_and_fixed_delta():
    model = PointNetLK(width=0.125, max_iter=3)
    assert "delta" not in dict(model.named_parameters())  # not learned by default
    src, ref, gt = _batch()
    out = model(src, ref, gt)
    losses = model.loss(out, gt)
    expected = ((out["transforms"][-1] @ se3_inverse(gt) - torch.eye(4)) ** 2).sum((1, 2)).mean()
    torch.testing.assert_close(losses["loss/transform"], expected)
    torch.testing.assert_close(losses["loss"], losses["loss/transform"] + (out["residual"] ** 2).sum())
    losses["loss"].backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())
    transform_only = PointNetLK(width=0.125, max_iter=3, feature_loss_weight=0.0, learn_delta=True)
    assert "delta" in dict(transform_only.named_parameters())
    loss = transform_only.loss(transform_only(src, ref, gt), gt)
    assert loss["loss"].item() == loss["loss/transform"].item()


def test_training_steps_lower_the_loss_on_a_tiny_batch():
    # transform loss only (the paper's loss; the official default adds the summed feature residual,
    # which on a 4-pair batch mostly shrinks the features)
    torch.manual_seed(0)
    before, after = eval_losses_before_after(PointNetLK(width=0.125, feature_loss_weight=0.0), _batch())
    assert after["loss"] < 0.5 * before["loss"]


def _classifier_checkpoint(tmp_path, width: float) -> str:
    """A tiny pointnet_classifier trained for two steps with Lightning and saved as src.train would."""
    torch.manual_seed(0)
    network = {"_target_": "baselines.learned.pointnet_classifier.PointNetClassifier", "num_classes": 3, "width": width}
    module = ClassificationModule(network)
    src, ref, _ = _batch(b=4)
    batches = [{"points_ref": ref[i], "points_src": src[i], "label": torch.tensor(i % 3)} for i in range(4)]
    trainer = L.Trainer(accelerator="cpu", max_steps=2, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=1)
    loader = DataLoader(batches, batch_size=2)
    trainer.fit(module, train_dataloaders=loader, val_dataloaders=loader)
    trainer.test(module, dataloaders=loader, verbose=False)
    assert set(module.test_results) == {"accuracy", "loss"} and 0 <= module.test_results["accuracy"] <= 1
    path = tmp_path / "classifier.ckpt"
    trainer.save_checkpoint(path)
    return str(path), module.network.encoder.state_dict()


def test_feature_init_from_a_classifier_checkpoint_when_training_starts(tmp_path):
    path, encoder = _classifier_checkpoint(tmp_path, 0.125)
    model = PointNetLK(width=0.125, feature_init=path)
    assert not torch.equal(model.encoder.state_dict()["mlp.layers.0.weight"], encoder["mlp.layers.0.weight"])
    model.train()
    for key, value in encoder.items():
        assert torch.equal(model.encoder.state_dict()[key], value)
    # a model whose weights were loaded (a checkpoint, imported weights) keeps them
    trained = PointNetLK(width=0.125, feature_init=path)
    trained.load_state_dict(PointNetLK(width=0.125).state_dict())
    before = {k: v.clone() for k, v in trained.encoder.state_dict().items()}
    trained.train()
    assert all(torch.equal(trained.encoder.state_dict()[k], v) for k, v in before.items())
    with pytest.raises(CheckpointError, match="does not fit this PointNetLK's encoder"):
        PointNetLK(width=0.25, feature_init=path).train()
    with pytest.raises(CheckpointError, match="does not exist"):
        PointNetLK(width=0.125, feature_init=str(tmp_path / "missing.ckpt")).train()


@pytest.mark.shared_data(f"weights/{PUBLISHED['learning3d_pointnet_classifier_features'].file}")
def test_feature_init_from_the_published_classifier_features():
    model = PointNetLK(feature_init="official:learning3d_pointnet_classifier_features")
    model.train()
    assert model.encoder.state_dict()["mlp.layers.1.num_batches_tracked"].item() > 0  # BatchNorm statistics came along
