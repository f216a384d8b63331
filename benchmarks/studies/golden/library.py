"""The classical methods' library calls on the golden pairs, written here from the libraries' documented APIs
with the settings each wrapper's docstring gives (``baselines/classical/``): ``(pairs) -> (P, 4, 4)``.

Every call is the library's own (Open3D's; small_gicp's; probreg's; the authors' Go-ICP as py-goicp wraps it), in
float64 (Go-ICP's C++ code computes in float), started from the identity, with the pair conditioning the wrapper
documents; nothing of the wrappers runs here. Normals,
where a method uses them, are Open3D's PCA normals over a hybrid neighbourhood (radius 0.1, at most 30
neighbours), flipped to point away from the cloud's centroid (the wrappers' documented ``centroid`` orientation).
Open3D runs on one thread (:func:`one_thread`): with more, its point-to-plane ICP is not reproducible from run
to run on some pairs (its reductions are summed in the threads' order; see the study's README).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: ICP's documented defaults (``baselines/classical/icp.py``): correspondence distance 0.5, 30 iterations,
#: relative fitness / RMSE 1e-6.
ICP_DISTANCE, ICP_ITERATIONS, ICP_RELATIVE = 0.5, 30, 1e-6
GICP_DISTANCE, GICP_EPSILON = 1.0, 1e-3  # baselines/classical/open3d_icp.py
NORMAL_RADIUS, NORMAL_MAX_NN, FEATURE_RADIUS, FEATURE_MAX_NN = 0.1, 30, 0.25, 100  # baselines/classical/fgr.py
SEED = 0  # Open3D's sampler, seeded before the features of a pair (FGR's tuples)


def _o3d():
    import open3d

    return open3d


def one_thread() -> None:
    """Open3D's parallel loops on one thread (a process-wide setting), so that its results are reproducible."""
    _o3d().utility.set_max_threads(1)


def library_version(method: str) -> str:
    """The library (and version) of ``method``'s call."""
    from importlib.metadata import version

    if method not in LIBRARIES:
        return f"open3d {_o3d().__version__}"
    distribution = PACKAGES[LIBRARIES[method]][0]
    return f"{distribution} {version(distribution)}"


def _cloud(points: np.ndarray, normals: bool = False):
    o3d = _o3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    if normals:
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS, max_nn=NORMAL_MAX_NN))
        raw = np.asarray(pcd.normals)
        away = np.sign(np.einsum("ij,ij->i", raw, points - points.mean(axis=0)))
        pcd.normals = o3d.utility.Vector3dVector(raw * np.where(away == 0, -1.0, away)[:, None])
    return pcd


def _criteria():
    return _o3d().pipelines.registration.ICPConvergenceCriteria(
        relative_fitness=ICP_RELATIVE, relative_rmse=ICP_RELATIVE, max_iteration=ICP_ITERATIONS)


def icp(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    reg = _o3d().pipelines.registration
    return reg.registration_icp(_cloud(src), _cloud(ref), ICP_DISTANCE, np.eye(4),
                                reg.TransformationEstimationPointToPoint(False), _criteria()).transformation


def point_to_plane_icp(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    reg = _o3d().pipelines.registration
    return reg.registration_icp(_cloud(src), _cloud(ref, normals=True), ICP_DISTANCE, np.eye(4),
                                reg.TransformationEstimationPointToPlane(), _criteria()).transformation


def gicp(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    reg = _o3d().pipelines.registration
    return reg.registration_generalized_icp(
        _cloud(src, normals=True), _cloud(ref, normals=True), GICP_DISTANCE, np.eye(4),
        reg.TransformationEstimationForGeneralizedICP(GICP_EPSILON), _criteria()).transformation


def _seeded_features(src: np.ndarray, ref: np.ndarray) -> tuple[list, list]:
    """Open3D's sampler seeded with :data:`SEED`, then both clouds with normals and their FPFH features (FGR's)."""
    o3d = _o3d()
    o3d.utility.random.seed(SEED)
    clouds = [_cloud(points, normals=True) for points in (src, ref)]
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=FEATURE_RADIUS, max_nn=FEATURE_MAX_NN)
    return clouds, [o3d.pipelines.registration.compute_fpfh_feature(c, search) for c in clouds]


def fgr(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    reg = _o3d().pipelines.registration
    clouds, features = _seeded_features(src, ref)
    option = reg.FastGlobalRegistrationOption(  # Open3D's defaults, named (fgr.py)
        division_factor=1.4, use_absolute_scale=False, decrease_mu=True, maximum_correspondence_distance=0.025,
        iteration_number=64, tuple_scale=0.95, maximum_tuple_count=1000)
    return reg.registration_fgr_based_on_feature_matching(*clouds, *features, option).transformation


#: RANSAC's documented defaults (``baselines/classical/ransac.py``): inlier distance 0.05 (0.075 refined by ICP),
#: 3 matches a sample, no mutual filter, edge-length ratio 0.9, 100,000 iterations, confidence 0.999; the ICP
#: refinement at correspondence distance 0.05 (``refine_distance``).
RANSAC_DISTANCE, RANSAC_ICP_DISTANCE, RANSAC_N, EDGE_RATIO, RANSAC_ITERATIONS, CONFIDENCE = 0.05, 0.075, 3, 0.9, 100_000, 0.999
REFINE_DISTANCE = 0.05


def _ransac(src: np.ndarray, ref: np.ndarray, distance: float) -> np.ndarray:
    """Open3D's RANSAC on FPFH matches (FGR's features), its sampler seeded with :data:`SEED` before the features."""
    reg = _o3d().pipelines.registration
    clouds, features = _seeded_features(src, ref)
    return reg.registration_ransac_based_on_feature_matching(
        *clouds, *features, False, distance, reg.TransformationEstimationPointToPoint(False), RANSAC_N,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(EDGE_RATIO), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(RANSAC_ITERATIONS, CONFIDENCE)).transformation


def ransac(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return _ransac(src, ref, RANSAC_DISTANCE)


def ransac_icp(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """RANSAC at the refined row's inlier distance, then Open3D's point-to-point ICP from its pose."""
    reg = _o3d().pipelines.registration
    start = _ransac(src, ref, RANSAC_ICP_DISTANCE)
    return reg.registration_icp(_cloud(src), _cloud(ref), REFINE_DISTANCE, start,
                                reg.TransformationEstimationPointToPoint(False), _criteria()).transformation


def small_gicp(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """small_gicp's GICP with the wrapper's documented defaults (``baselines/classical/smallgicp.py``):
    down-sampling 0.01, 20 neighbours, correspondence distance 1.0, 30 iterations, one thread."""
    import small_gicp as sg

    (ref_pc, ref_tree), (src_pc, _) = (sg.preprocess_points(c.astype(np.float64), 0.01, 20, num_threads=1) for c in (ref, src))
    return sg.align(ref_pc, src_pc, ref_tree, registration_type="GICP", max_correspondence_distance=1.0,
                    max_iterations=30, num_threads=1).T_target_source


def filterreg(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """probreg's rigid point-to-point FilterReg with the wrapper's documented defaults
    (``baselines/classical/filterreg.py``): probreg's (σ² from the data, ``w`` 0, 50 iterations, tolerance 1e-3,
    minimum σ² 1e-4) but ``update_sigma2=True``; its rotation (composed of float32 Kabsch steps, off SO(3) by up
    to 4e-5) projected onto the nearest rotation, as the wrapper documents; on one OpenMP thread."""
    from probreg import filterreg as probreg_filterreg
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, user_api="openmp"):
        result = probreg_filterreg.registration_filterreg(
            src.astype(np.float64), ref.astype(np.float64), sigma2=None, update_sigma2=True, w=0.0,
            objective_type="pt2pt", maxiter=50, tol=1e-3, min_sigma2=1e-4)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = _nearest_rotation(result.transformation.rot), result.transformation.t
    return out


def _nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest ``matrix`` (Frobenius): U diag(1, 1, det UVᵀ) Vᵀ of its SVD."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


#: Go-ICP's documented settings (``baselines/classical/goicp.py``, ``docs/methods/goicp.md``): MSE threshold 0.002,
#: trim fraction 0.3, distance transform of 100 cells over twice the model's box, rotations in [-π, π]³ and
#: translations in [-0.5, 0.5]³ of the normalised frame.
GOICP_MSE, GOICP_TRIM, GOICP_DT_SIZE, GOICP_DT_FACTOR, GOICP_TRANSLATION = 0.002, 0.3, 100, 2.0, 0.5


def goicp(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The authors' Go-ICP (py-goicp's ``GoICP``) with the wrapper's documented settings and conditioning: each
    cloud centred on its centroid, both scaled by one factor into [-1, 1]³, data = ``src``, model = ``ref``; its
    optimum (R, t') mapped back, t = c_ref − R c_src + s t', R (float) projected onto the nearest rotation."""
    import py_goicp

    src, ref = src.astype(np.float64), ref.astype(np.float64)
    c_src, c_ref = src.mean(axis=0), ref.mean(axis=0)
    scale = max(np.abs(src - c_src).max(), np.abs(ref - c_ref).max())
    solver = py_goicp.GoICP()
    model, data = ([py_goicp.POINT3D(*map(float, p)) for p in (c - centre) / scale] for c, centre in ((ref, c_ref), (src, c_src)))
    solver.loadModelAndData(len(model), model, len(data), data)
    solver.setDTSizeAndFactor(GOICP_DT_SIZE, GOICP_DT_FACTOR)
    rotations, translations = py_goicp.ROTNODE(), py_goicp.TRANSNODE()
    rotations.a = rotations.b = rotations.c = -np.pi
    rotations.w = 2 * np.pi
    translations.x = translations.y = translations.z = -GOICP_TRANSLATION
    translations.w = 2 * GOICP_TRANSLATION
    solver.setInitNodeRot(rotations)
    solver.setInitNodeTrans(translations)
    solver.MSEThresh, solver.trimFraction, solver.doTrim = GOICP_MSE, GOICP_TRIM, True
    solver.BuildDT()
    solver.Register()
    rotation = _nearest_rotation(np.array(solver.optimalRotation()))
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation, c_ref - rotation @ c_src + scale * np.array(solver.optimalTranslation())
    return out


CALLS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "icp": icp, "point_to_plane_icp": point_to_plane_icp, "gicp": gicp, "fgr": fgr, "small_gicp": small_gicp,
    "filterreg": filterreg, "goicp": goicp, "ransac": ransac, "ransac_icp": ransac_icp}
#: The module each call needs, beside Open3D (an optional package of the framework).
LIBRARIES = {"small_gicp": "small_gicp", "filterreg": "probreg", "goicp": "py_goicp"}
#: Each module's distribution (its version is recorded) and repository.
PACKAGES = {"small_gicp": ("small_gicp", "koide3/small_gicp"), "probreg": ("probreg", "neka-nat/probreg"),
            "py_goicp": ("py-goicp", "aalavandhaann/go-icp_cython")}


def run(method: str, pairs: dict[str, np.ndarray]) -> np.ndarray:
    """(P, 4, 4) estimates of the library call of ``method`` on every pair (Open3D on one thread)."""
    one_thread()
    return np.stack([np.asarray(CALLS[method](s, r), dtype=np.float64) for s, r in zip(pairs["src"], pairs["ref"])])
