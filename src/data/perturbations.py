"""PointNetLK's pair protocol: a random twist moves the source (the protocol of PointNetLK,
learning3d's PointNetLK and PointNetLK-Revisited), optionally on unit-cube shapes (Revisited's).

Same interface as :mod:`src.data.transforms` (``transform(sample, rng) -> sample``, per-sample generator).

* :class:`TwistPerturbation` — ``x = a·u/‖u‖`` with ``u ~ N(0, I₆)`` and ``a ~ U[0, magnitude)`` (or ``a =
  magnitude``), twist order (ω, v) as their ``se3.exp`` (:func:`~src.geometry.numpy_rigid.twist_matrix`); the
  source becomes ``exp(x)·template`` and the ground truth (source → reference) is ``exp(−x)`` (PointNetLK
  ``ptlk/data/transforms.py`` 145–173 ``RandomTransformSE3`` with ``experiments/train_pointlk.py`` 300–304
  ``(args.mag = 0.8, True)``; learning3d ``ops/transform_functions.py`` ``PNLKTransform`` 119–138 with
  ``PNLKTransform(0.8, True)``, ``data_utils/dataloaders.py`` 267–269; PointNetLK-Revisited ``data_utils.py``
  ``RandomTransformSE3`` 249–280 with ``--mag 0.8``).
* :class:`UnitCube` — PointNetLK-Revisited's ``OnUnitCube`` (``data_utils.py`` 787–806, ``method2``): the
  shape is divided by the longest side of its bounding box, then centred on its mean; here the
  reference's scale and mean are applied to both clouds (the same shape, so the pair stays rigid).
* :func:`build_twist_transforms` — pick pair → (unit cube) → twist → noise → shuffle.

Selected by :func:`src.data.pipelines.build_pair_transforms` with ``data.pair.perturbation: twist``
(``twist_mag``, ``twist_random_mag``, ``unit_cube``; full clouds, ``partial=none``):
``conf/exp/pointnetlk_protocol.yaml``, ``conf/exp/pointnetlk_revisited_protocol.yaml``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from src.data.transforms import Compose, GaussianNoise, PickPair, Sample, Shuffle, Transform, move_cloud
from src.utils.errors import ConfigError
from src.geometry.numpy_rigid import twist_matrix


@dataclass
class TwistPerturbation:
    """Move the source by ``exp(x)``, a twist of random direction and magnitude (see the module docstring)."""

    magnitude: float = 0.8
    random_magnitude: bool = True

    def __post_init__(self) -> None:
        if not self.magnitude >= 0:
            raise ConfigError(f"twist_mag must be >= 0, got {self.magnitude}")

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        amplitude = rng.uniform(0.0, self.magnitude) if self.random_magnitude else self.magnitude
        direction = rng.standard_normal(6)
        move_cloud(sample, "src", twist_matrix(direction / np.linalg.norm(direction) * amplitude))
        return sample


@dataclass
class UnitCube:
    """Scale both clouds (and ``points_raw``) by 1 / (the reference's longest bounding-box side) and centre them on the
    reference's mean (PointNetLK-Revisited's ``OnUnitCube``); the ground truth's translation scales too."""

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        ref = sample["points_ref"]
        scale = float(np.max(ref.max(axis=0) - ref.min(axis=0)))
        centre = ref.mean(axis=0) / scale
        for key in ("points_src", "points_ref", "points_raw"):
            if key in sample:
                sample[key] = (sample[key] / scale - centre).astype(np.float32)
        gt = np.array(sample["transform_gt"], dtype=np.float64)
        gt[:3, 3] = gt[:3, 3] / scale + (gt[:3, :3] - np.eye(3)) @ centre
        sample["transform_gt"] = gt
        return sample


def build_twist_transforms(
    pair_sampling: str,
    sampling: str = "os",
    num_points: int = 1024,
    twist_mag: float = 0.8,
    twist_random_mag: bool = True,
    unit_cube: bool = False,
    noise_sigma: float = 0.0,
    noise_clip: float = 0.05,
) -> Compose:
    """PointNetLK's pipeline on full clouds: pick pair → (unit cube) → the twist moves the source →
    noise → shuffle (both clouds independently, as every other manner)."""
    steps: list[Transform] = [PickPair(sampling, pair_sampling, num_points)]
    if unit_cube:
        steps.append(UnitCube())
    steps += [TwistPerturbation(twist_mag, twist_random_mag), GaussianNoise(noise_sigma, noise_clip), Shuffle()]
    return Compose(steps)
