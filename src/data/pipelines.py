"""The pair pipelines of the protocols: which transforms, in which order, for each partial manner and
perturbation (the Euler-angle transforms of :mod:`src.data.transforms`, the twist of :mod:`src.data.perturbations`)."""

from __future__ import annotations

from src.data.perturbations import build_twist_transforms
from src.data.transforms import (
    PARTIAL_MANNERS,
    PERTURBATIONS,
    Compose,
    GaussianNoise,
    OverlapRatioCrop,
    PickPair,
    PRNetCrop,
    RandomRigidTransform,
    Resample,
    RPMNetCrop,
    Shuffle,
    Transform,
)
from src.utils.errors import ConfigError


def build_pair_transforms(
    pair_sampling: str,
    sampling: str = "ts",
    partial: str = "prnet",
    num_points: int = 2048,
    rot_mag: float = 45.0,
    trans_mag: float = 0.5,
    noise_sigma: float = 0.0,
    noise_clip: float = 0.05,
    prnet_num_keep: int = 768,
    rpmnet_p_keep: float = 0.7,
    rpmnet_num_points: int = 1024,
    rpmnet_resample_points: int | None = None,
    overlap_ratio: float | None = None,
    perturbation: str = "euler",
    twist_mag: float = 0.8,
    twist_random_mag: bool = True,
    unit_cube: bool = False,
) -> Compose:
    """The official OMNet code's pipelines (``dataset/transformations.py``, ``fetch_transform``).

    PRNet manner (class ``PRNet``): pick pair → the drawn transform moves the reference
    (``ref = R·src + t``, ground truth = that transform) → 768-NN crop of one far point, the same
    point for both clouds in their own frames → noise → shuffle. RPMNet manner
    (``RandomCrop``, ``RandomTransformSE3_euler``, ``Resampler``): pick pair → independent half-space
    crops (p_keep) → the drawn transform moves the source (ground truth = its inverse) → resample
    to ⌈p_keep·1024⌉ = 717 (or ``rpmnet_resample_points`` each) → noise → shuffle. ``none`` (full
    clouds, DCP's protocol): the transform moves the reference, as DCP's ``data.py`` does.

    The paper's text words the two manners the other way round (supplementary Sec. 2: "transform
    applied to Y giving X" for PRNet's); the code, which produced the published numbers and for whose
    direction the metric Euler conventions (zyx / xyz) were chosen, is followed here.

    ``perturbation="twist"`` (full clouds only): PointNetLK's protocol instead of the Euler-angle
    transform, :func:`~src.data.perturbations.build_twist_transforms` (``twist_mag``,
    ``twist_random_mag``, ``unit_cube``).

    ``overlap_ratio`` (test-time study, PRNet manner only): the crop becomes
    :class:`~src.data.transforms.OverlapRatioCrop` — partial X, then Y = two adjacent parts of the overlapping and
    non-overlapping regions in the requested proportion.
    """
    if partial not in PARTIAL_MANNERS:
        raise ConfigError(f"data.partial must be one of {PARTIAL_MANNERS}, got {partial!r}")
    if perturbation not in PERTURBATIONS:
        raise ConfigError(f"data.pair.perturbation must be one of {PERTURBATIONS}, got {perturbation!r}")
    if perturbation == "twist":
        if partial != "none" or overlap_ratio is not None:
            raise ConfigError("data.pair.perturbation=twist is PointNetLK's protocol on full clouds: use partial=none")
        return build_twist_transforms(pair_sampling, sampling, num_points, twist_mag, twist_random_mag, unit_cube,
                                      noise_sigma, noise_clip)
    pick = PickPair(sampling, pair_sampling, num_points)
    noise = GaussianNoise(noise_sigma, noise_clip)
    if overlap_ratio is not None:
        if partial != "prnet":
            raise ConfigError(
                f"data.pair.overlap_ratio is the paper's test protocol for the PRNet manner; got partial={partial!r}"
            )
        move = RandomRigidTransform(rot_mag, trans_mag, apply_to="ref")
        crop = OverlapRatioCrop(overlap_ratio, prnet_num_keep)
        return Compose([pick, move, crop, noise, Shuffle()])
    if partial == "prnet":
        move = RandomRigidTransform(rot_mag, trans_mag, apply_to="ref")
        steps: list[Transform] = [pick, move, PRNetCrop(prnet_num_keep), noise, Shuffle()]
    elif partial == "rpmnet":
        move = RandomRigidTransform(rot_mag, trans_mag, apply_to="src")
        resample = Resample(rpmnet_num_points, rpmnet_p_keep, rpmnet_resample_points)
        steps = [pick, RPMNetCrop(rpmnet_p_keep), move, resample, noise, Shuffle()]
    else:
        steps = [pick, RandomRigidTransform(rot_mag, trans_mag, apply_to="ref"), noise, Shuffle()]
    return Compose(steps)
