"""benchmarks.studies.diagnostics.iteration_errors: the error after each iteration of a network, from the poses its forward pass returns."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.studies.diagnostics import iteration_errors
from src.geometry import euler_to_matrix


class Halfway(torch.nn.Module):
    """Iteration 1 returns the identity, iteration 2 the ground truth of each pair (read from ``ref``'s first row)."""

    def __init__(self, truths: torch.Tensor) -> None:
        super().__init__()
        self.truths, self.seen = truths, 0

    def forward(self, src, ref):
        truth = self.truths[self.seen:self.seen + len(src)].float()
        self.seen += len(src)
        return {"transforms": [torch.eye(4).expand(len(src), 4, 4), truth]}


def test_the_error_of_each_iteration_against_the_ground_truth():
    angles = torch.tensor([10.0, 20.0, 30.0], dtype=torch.float64)
    truths = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    truths[:, :3, :3] = euler_to_matrix(torch.stack([angles, 0 * angles, 0 * angles], 1), "zyx", degrees=True)
    truths[:, :3, 3] = torch.tensor([0.1, 0.0, 0.0])
    pairs = [(np.zeros((5, 3), np.float32), np.zeros((5, 3), np.float32), t.numpy()) for t in truths]
    table = iteration_errors.iteration_errors(Halfway(truths), pairs, "prnet", batch=2)
    assert table["iteration"].tolist() == [1, 2]
    assert table["Error(R)"].tolist() == pytest.approx([20.0, 0.0], abs=0.02)  # float32 poses: arccos near 1
    assert table["Error(R) median"].iloc[0] == pytest.approx(20.0, abs=1e-4)
    assert table["Error(t)"].tolist() == pytest.approx([0.1, 0.0], abs=1e-6)


def test_a_missing_checkpoint_is_one_line(tmp_path, capsys):
    assert iteration_errors.main(["--checkpoint", str(tmp_path / "none.ckpt")]) == 2
    assert capsys.readouterr().err.strip() == f"error: checkpoint {tmp_path / 'none.ckpt'} does not exist"
