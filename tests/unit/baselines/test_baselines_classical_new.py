"""The newer classical baselines (RANSAC, point-to-plane ICP, GICP, small_gicp, CPD, FilterReg): known
transforms, the runner's per-pair timeout, bad input and bad options; an optional package missing → skipped."""

from __future__ import annotations

import importlib.util
import re
import tomllib

import numpy as np
import pytest

from baselines import get_registrator, run_pairs, transform_problem
from baselines.registry import resolve_registrator
from baselines.classical import _optional
from baselines.classical.cpd import expectation
from baselines.testing import euler_transform, make_pair, rotation_error_deg, translation_error
from src.utils.errors import ConfigError, PointCloudError
from tests.helpers.paths import ROOT

SMALL = euler_transform((10.0, -8.0, 6.0), (0.1, -0.05, 0.08))  # ~14° in total: within a local method's basin
LARGE = euler_transform((40.0, -35.0, 30.0), (0.3, -0.2, 0.25))  # ~60° in total: for the global method

#: method -> the PyPI package it needs (None: Open3D only, always installed)
PACKAGES = {"ransac": None, "ransac_icp": None, "point_to_plane_icp": None, "gicp": None, "small_gicp": "small-gicp", "cpd": None,
            "filterreg": "probreg"}
LOCAL = ["point_to_plane_icp", "gicp", "small_gicp", "cpd", "filterreg"]


def _needs(method: str) -> None:
    """Skip, with the product's own install hint, when the method's optional package is missing."""
    cls = resolve_registrator(method)
    if issubclass(cls, _optional.NeedsPackage) and importlib.util.find_spec(cls.module) is None:
        pytest.skip(f"optional package {cls.package} not installed: {_optional.install_hint(cls.package, cls.extra)}")


def _errors(estimate, truth) -> tuple[float, float]:
    assert transform_problem(estimate) is None, transform_problem(estimate)
    return rotation_error_deg(estimate, truth), translation_error(estimate, truth)


@pytest.mark.parametrize("method", LOCAL)
def test_local_methods_recover_a_small_transform(method):
    _needs(method)
    reg = get_registrator(method)
    rot, trans = _errors(reg.register(*make_pair(SMALL, 500, seed=1)), SMALL)
    assert rot < 0.5 and trans < 0.01  # the same points: near exact
    rot, trans = _errors(reg.register(*make_pair(SMALL, 500, seed=2, twice_sampled=True)), SMALL)
    assert rot < 3.0 and trans < 0.05  # independent samples of the surface


@pytest.mark.parametrize("method, limit", [("ransac", 3.0), ("ransac_icp", 1.0)])
def test_ransac_recovers_a_large_transform_and_icp_refines_it(method, limit):
    pair = make_pair(LARGE, 500, seed=0, noise=0.005)
    rot, trans = _errors(get_registrator(method).register(*pair), LARGE)
    assert rot < limit and trans < 0.03


def test_ransac_is_deterministic_with_a_seed():
    reg = get_registrator("ransac", seed=3)
    pair = make_pair(LARGE, 300, seed=6, noise=0.01)
    np.testing.assert_array_equal(reg.register(*pair), reg.register(*pair))


def test_small_gicp_vgicp_recovers_a_small_transform():
    _needs("small_gicp")
    rot, trans = _errors(get_registrator("small_gicp", registration_type="VGICP").register(
        *make_pair(SMALL, 500, seed=2, twice_sampled=True)), SMALL)
    assert rot < 3.0 and trans < 0.05


def test_cpd_keeps_the_scale_at_one():
    """CPD's scale is fixed: on a source half the size of the reference the estimate stays a rotation."""
    src, ref = make_pair(SMALL, 300, seed=1)
    estimate = get_registrator("cpd").register(0.5 * src, ref)
    np.testing.assert_allclose(np.linalg.det(estimate[:3, :3]), 1.0, atol=1e-9)
    np.testing.assert_allclose(estimate[:3, :3] @ estimate[:3, :3].T, np.eye(3), atol=1e-9)


def test_cpd_leaves_out_a_reference_point_that_no_centroid_reaches():
    """With no outlier term (w = 0) and a small σ², every kernel of a far reference point underflows to 0 (the
    authors' cpd_P.c divides 0 by 0 there): that point gets no responsibility; the others keep theirs."""
    ref = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [10.0, 0.0, 0.0]])
    step = expectation(ref, centroids=ref[:2] + 0.01, sigma2=1e-3, w=0.0)
    assert np.isfinite(step.nll) and np.isfinite(step.px).all()
    np.testing.assert_allclose(step.pt1, [1.0, 1.0, 0.0])
    np.testing.assert_allclose(step.p1.sum(), 2.0)


def test_cpd_stops_with_one_line_when_the_outlier_term_explains_every_point():
    """Found by the property suite: two 3-point clouds ~1.5e5 apart; the uniform term's weight grows with σ³, so no
    reference point was left to any centroid (N_P = 0), and the M-step divided by zero into an SVD error."""
    src = np.array([[100000.126, 99999.868, 100000.640], [100000.105, 99999.464, 100000.362],
                    [100001.304, 100000.947, 99999.296]])
    ref = np.array([[68126.120, 155943.719, -32257.015], [68126.108, 155943.337, -32256.707],
                    [68128.048, 155943.319, -32257.709]])
    with pytest.raises(PointCloudError, match=r"^CPD: every reference point is explained by the outlier term alone"):
        get_registrator("cpd").register(src, ref)


def test_filterreg_refuses_a_pair_beyond_its_lattice_with_one_line():
    """Found by the property suite: probreg's lattice takes positions in units of σ, and two clouds 1e7 apart aborted
    the whole process (``free(): invalid size``); 9e6 registered. Now refused before probreg is called."""
    _needs("filterreg")
    src = np.random.default_rng(0).normal(size=(200, 3))
    with pytest.raises(PointCloudError, match=r"^FilterReg: the pair reaches 1.25e\+08 σ from its centre"):
        get_registrator("filterreg").register(src, src + [1e7, 0.0, 0.0])


def test_filterreg_returns_a_rotation_after_many_iterations():
    """probreg composes float32 Kabsch steps unrenormalised: after 200 steps its rotation was off SO(3) by more
    than the 1e-4 at which an estimate counts as non-rigid, and the pair failed."""
    _needs("filterreg")
    result = get_registrator("filterreg", max_iterations=200, tolerance=1e-12).register_result(
        *make_pair(SMALL, 300, seed=2, twice_sampled=True))
    assert not result.failed, result.reason
    rotation = result.transform[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)


def test_filterreg_does_not_depend_on_the_openmp_thread_count():
    """probreg's Kabsch and kernel sums are OpenMP reductions: with 2 threads the golden pairs moved by up to 0.15°."""
    _needs("filterreg")
    from threadpoolctl import threadpool_limits

    reg, pair = get_registrator("filterreg"), make_pair(SMALL, 300, seed=2, twice_sampled=True)
    with threadpool_limits(1, user_api="openmp"):
        one = reg.register(*pair)
    with threadpool_limits(2, user_api="openmp"):
        np.testing.assert_array_equal(reg.register(*pair), one)


@pytest.mark.parametrize("method", sorted(PACKAGES))
def test_every_new_method_runs_under_the_runner_with_a_timeout(method):
    _needs(method)
    pairs = [make_pair(SMALL, 300, seed=1)]
    ok = run_pairs(get_registrator(method), pairs, workers=1, timeout_s=120, progress=False)[0]
    assert not ok.failed, ok.reason
    late = run_pairs(get_registrator(method), pairs, workers=1, timeout_s=1e-9, progress=False)[0]
    assert late.failed and "timed out" in late.reason and np.array_equal(late.transform, np.eye(4))


@pytest.mark.parametrize("method", sorted(PACKAGES))
def test_bad_clouds_are_refused(method):
    _needs(method)
    reg = get_registrator(method)
    with pytest.raises(PointCloudError, match="src: degenerate cloud"):
        reg.register(np.ones((3, 3)), np.ones((3, 3)))
    src, ref = make_pair(SMALL, 100, seed=1)
    ref[5] = np.nan
    with pytest.raises(PointCloudError, match="ref"):
        reg.register(src, ref)
    with pytest.raises(PointCloudError, match="src"):
        reg.register(src[:, :2], ref)


@pytest.mark.parametrize("method, options, message", [
    ("ransac", {"ransac_n": 2}, "ransac_n must be >= 3"),
    ("ransac", {"confidence": 1.5}, r"confidence must be in \(0, 1\]"),
    ("ransac", {"feature_radius": 0}, "feature_radius must be > 0"),
    ("point_to_plane_icp", {"normal_orientation": "up"}, "normal_orientation must be one of"),
    ("gicp", {"epsilon": -1.0}, "epsilon must be > 0"),
    ("small_gicp", {"registration_type": "NDT"}, "registration_type must be one of GICP, VGICP"),
    ("cpd", {"w": 1.0}, r"w must be in \[0, 1\)"),
    ("filterreg", {"max_iterations": 0}, "max_iterations must be > 0"),
    ("gicp", {"colour": 1}, "unknown option"),
])
def test_bad_options_are_one_config_error(method, options, message):
    _needs(method)
    with pytest.raises(ConfigError, match=message):
        get_registrator(method, **options)


@pytest.mark.parametrize("method", ["small_gicp", "filterreg"])
def test_a_missing_optional_package_names_the_extra_that_installs_it(method, monkeypatch):
    """FilterReg's hint named the classical extra, which does not hold probreg."""
    monkeypatch.setattr(_optional.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ConfigError, match="needs the optional package") as info:
        get_registrator(method)
    extra = re.search(r'pip install -e "\.\[(\w+)\]"', str(info.value)).group(1)
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert f"pip install {PACKAGES[method]} (or" in str(info.value)
    assert any(requirement.startswith(PACKAGES[method]) for requirement in extras[extra]), (extra, extras[extra])


@pytest.mark.parametrize("method, call", [("point_to_plane_icp", "registration_icp"),
                                          ("ransac", "registration_ransac_based_on_feature_matching")])
def test_open3d_calls_whose_result_depends_on_the_thread_count_run_on_one_thread(method, call, monkeypatch):
    """Point-to-plane ICP depends on its threads' order on a pair near a tie, RANSAC's draws vary from run to run on more than one thread: both
    run on one Open3D thread, and the previous limit is restored."""
    from baselines.classical import _open3d

    utility = _open3d.open3d().utility
    before, seen = utility.get_max_threads(), []
    estimation = getattr(_open3d.open3d().pipelines.registration, call)

    def recording(*args, **kwargs):
        seen.append(utility.get_max_threads())
        return estimation(*args, **kwargs)

    monkeypatch.setattr(_open3d.open3d().pipelines.registration, call, recording)
    src = np.random.default_rng(0).normal(size=(200, 3))
    get_registrator(method).register(src, src + 0.01)
    assert seen == [1] and utility.get_max_threads() == before
