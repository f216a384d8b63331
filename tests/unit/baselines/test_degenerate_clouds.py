"""A method that cannot determine a rotation says so: every registered method either refuses a degenerate pair with
one line or gives an answer, and repeating points changes neither; a solver that found nothing raises
RegistrationError instead of returning the identity as if it were an estimate."""

from __future__ import annotations

import numpy as np
import pytest

from baselines import get_registrator
from baselines.conditioning import deduplicated
from baselines.methods import METHODS
from baselines.testing import euler_transform, l_shape_surface, make_pair
from src.geometry.numpy_rigid import apply_transform
from src.utils.errors import ConfigError, RegistrationError, UserError

TRUTH = euler_transform((20.0, 10.0, 30.0), (0.1, -0.2, 0.15))
FOUR = np.array([[0.0, 0.0, 0.0], [0.6, 0.0, 0.0], [0.1, 0.4, 0.2], [-0.2, 0.3, 0.5]])
FLAT = l_shape_surface(300, seed=0) * [1.0, 1.0, 0.0]  # the asymmetric L pressed onto the plane z = 0
#: case -> (cloud, how many times its points repeat in the reported input).
CASES = {"three points": (FOUR[:3], 256), "four points repeated 256 times": (FOUR, 256), "a flat shape": (FLAT, 2)}


def _registrator(key: str, **options):
    try:
        return get_registrator(key, **options)
    except ConfigError as err:  # an optional package that is not installed
        pytest.skip(str(err))


def _outcome(registrator, src: np.ndarray, ref: np.ndarray) -> np.ndarray | str:
    """The estimate, or the one-line message of the refusal."""
    try:
        return registrator.register(src, ref)
    except UserError as err:
        assert str(err) and "\n" not in str(err), repr(err)
        return str(err)


@pytest.mark.parametrize("key", [method.key for method in METHODS])
def test_a_degenerate_pair_is_refused_in_one_line_or_answered_as_without_its_repeated_points(key):
    registrator = _registrator(key)
    for case, (cloud, repeats) in CASES.items():
        ref = apply_transform(TRUTH, cloud)
        once = _outcome(registrator, cloud, ref)
        repeated = _outcome(registrator, np.tile(cloud, (repeats, 1)), np.tile(ref, (repeats, 1)))
        if isinstance(once, str):
            assert repeated == once, case
        else:
            assert not isinstance(repeated, str), (case, repeated)
            # to the last bits, which Open3D's multi-threaded sums (GICP) vary from run to run
            np.testing.assert_allclose(repeated, once, rtol=0, atol=1e-12, err_msg=case)
            # no rotation is no estimate of a 36 deg one (only the identity method answers it, by definition)
            assert key == "identity" or not np.allclose(once[:3, :3], np.eye(3), atol=1e-6), case


def test_repeated_points_are_registered_once_and_a_duplicate_free_cloud_is_left_as_it_is():
    cloud = np.tile(FOUR, (256, 1))
    assert np.array_equal(deduplicated(cloud), FOUR)
    assert deduplicated(FLAT) is FLAT
    assert np.array_equal(deduplicated(FOUR[[2, 0, 2, 1, 0]]), FOUR[[2, 0, 1]])  # first appearances, in order


@pytest.mark.parametrize("key, option", [
    ("icp", {"max_correspondence_distance": 1e-6}),
    ("point_to_plane_icp", {"max_correspondence_distance": 1e-6}),
    ("gicp", {"max_correspondence_distance": 1e-6}),
    ("small_gicp", {"max_correspondence_distance": 1e-6}),
    ("symmetric_icp", {"max_correspondence_distance": 1e-6}),
    ("ransac", {"distance_threshold": 1e-9}),
])
def test_a_solver_that_found_nothing_raises_instead_of_returning_the_identity(key, option):
    """Nothing within reach of the start (the ICP family), or no sample whose matches agree (RANSAC): the libraries
    return the identity, which is no estimate."""
    registrator = _registrator(key, **option)
    pair = make_pair(TRUTH, 300, seed=1, twice_sampled=True, noise=0.01)
    with pytest.raises(RegistrationError, match=rf"^{key}: found no transform: "):
        registrator.register(*pair)
    result = registrator.register_result(*pair)
    assert result.failed and result.reason.startswith(f"RegistrationError: {key}: found no transform")
    get_registrator(key).register(*pair)  # with its defaults it finds one
