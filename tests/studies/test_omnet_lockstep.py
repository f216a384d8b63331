"""benchmarks.studies.lockstep.omnet's mapping between our OMNet and the authors' port (the port itself is not in the
repository: its side is checked by the script's float64 start check when it runs)."""

import pytest
import torch

from benchmarks.studies.lockstep.omnet import _layer_names, pose_of, scaled_nn
from src.geometry import quat_to_matrix, se3_from_rt
from src.models.omnet import OMNet


@pytest.mark.parametrize("width", [0.125, 0.25])
def test_every_weight_of_ours_has_a_counterpart_in_the_port(width):
    ours = OMNet(width=width)
    mapped = {name for i in range(ours.num_iters) for name, _ in _layer_names(i)}
    owners = {key.rsplit(".", 1)[0] for key in ours.state_dict() if key != "mask_class_weights"}  # (a constant)
    assert owners == mapped


def test_the_ports_layers_are_scaled_as_model_scale_scales_ours():
    nn = scaled_nn(0.25)
    ours = OMNet(width=0.25).iterations[0]
    assert nn.Conv1d(2048 + 64, 1024, 1).weight.shape[:2] == ours.fusion[0].linear.weight.shape  # 528 -> 256
    assert nn.Linear(3072, 2048).weight.shape == ours.regressor[0][0].weight.shape
    assert nn.Conv1d(3, 64, 1).in_channels == 3 and nn.Conv1d(256, 2, 1).out_channels == 2
    assert nn.Linear(256, 7).out_features == 7 and nn.BatchNorm1d(1024).num_features == 256


def test_pose_of_is_the_quaternion_with_non_negative_w_and_the_translation():
    quat = torch.tensor([[-0.8, 0.6, 0.0, 0.0]])  # w < 0: the same rotation as its negation
    transform = se3_from_rt(quat_to_matrix(quat), torch.tensor([[0.1, -0.2, 0.3]]))
    assert torch.allclose(pose_of(transform), torch.tensor([[0.8, -0.6, 0.0, 0.0, 0.1, -0.2, 0.3]]), atol=1e-6)
