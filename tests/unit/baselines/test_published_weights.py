"""Published weights: strict converters, the registry, numerical equivalence with the authors' code,
the three entries (src.eval, the Python API), their one-line errors, and PointNetLK's pair protocol.

The equivalence fixtures (tests/fixtures/published_*.npz) were computed once with the authors' own
code and the same weights by tests/helpers/make_published_fixtures.py. Tests that need ../shared/weights
are marked ``shared_data`` and skip (with the reason) only where their file is absent.
"""

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from baselines import get_registrator
from baselines.learned.common.encoders import PointNetEncoder
from baselines.learned.common.global_feature import eval_mode, lk_jacobian
from baselines.learned.pointnetlk import learning3d_reported_transform
from baselines.learned.published import PUBLISHED, published_module, resolve
from baselines.learned.weight_converters import convert
from src.config import register_resolvers
from src.data.perturbations import TwistPerturbation, UnitCube, build_twist_transforms, twist_matrix
from src.utils.errors import CheckpointError, ConfigError
from src.utils.paths import shared_path
from tests.helpers.paths import CONF as CONF_DIR, FIXTURES

CONF = str(CONF_DIR)
register_resolvers()


def needs(name: str) -> pytest.MarkDecorator:
    """The published weights ``name`` (``../shared/weights/<file>``): skipped where absent."""
    return pytest.mark.shared_data(f"weights/{PUBLISHED[name].file}")


def fixture(name: str) -> dict[str, torch.Tensor]:
    with np.load(FIXTURES / f"published_{name}.npz") as data:
        return {k: torch.from_numpy(data[k]) for k in data.files}


def translation(t: torch.Tensor) -> torch.Tensor:
    out = torch.eye(4, dtype=t.dtype).repeat(t.shape[0], 1, 1)
    out[:, :3, 3] = t
    return out


# --- converters (no published file needed) ----------------------------------------------------------


def _learning3d_pointnet(seed: int = 0) -> tuple[dict[str, torch.Tensor], torch.nn.Module]:
    """A random learning3d-layout PointNet (Conv1d with bias + BatchNorm1d with running statistics)."""
    torch.manual_seed(seed)
    channels = (3, 64, 64, 64, 128, 1024)
    layers, state = [], {}
    for i, (c_in, c_out) in enumerate(zip(channels[:-1], channels[1:]), start=1):
        conv, bn = torch.nn.Conv1d(c_in, c_out, 1), torch.nn.BatchNorm1d(c_out)
        bn.running_mean.uniform_(-1, 1), bn.running_var.uniform_(0.5, 2), bn.weight.data.uniform_(0.5, 1.5)
        bn.bias.data.uniform_(-0.2, 0.2)
        layers += [conv, bn, torch.nn.ReLU()]
        state.update({f"conv{i}.{k}": v for k, v in conv.state_dict().items()})
        state.update({f"bn{i}.{k}": v for k, v in bn.state_dict().items()})
    return state, torch.nn.Sequential(*layers).eval()


def test_bias_before_batchnorm_is_folded_exactly_and_every_tensor_is_used():
    state, reference = _learning3d_pointnet()
    encoder = PointNetEncoder((3, 64, 64, 64, 128, 1024)).eval()
    encoder.load_state_dict(convert(state, "learning3d_pointnet"), strict=True)
    points = torch.randn(2, 100, 3)
    with torch.no_grad():
        expected = reference(points.transpose(1, 2)).amax(dim=2)
        torch.testing.assert_close(encoder(points)[1], expected, atol=1e-5, rtol=1e-5)
    with pytest.raises(CheckpointError, match="bn3.running_var is missing"):
        convert({k: v for k, v in state.items() if k != "bn3.running_var"}, "learning3d_pointnet")
    with pytest.raises(CheckpointError, match="does not use, e.g. fc.weight"):
        convert({**state, "fc.weight": torch.zeros(1)}, "learning3d_pointnet")


def test_unreadable_foreign_and_unknown_weights_are_one_line_errors(tmp_path):
    junk = tmp_path / "junk.t7"
    junk.write_text("not weights")
    with pytest.raises(CheckpointError, match="not a readable PyTorch weights file"):
        resolve(str(junk))
    foreign = tmp_path / "foreign.pth"
    torch.save({"layer.weight": torch.zeros(2)}, foreign)
    with pytest.raises(CheckpointError, match="not a published state dict of a known layout"):
        resolve(str(foreign))
    with pytest.raises(CheckpointError, match="does not exist"):
        resolve(str(tmp_path / "missing.t7"))
    with pytest.raises(ConfigError, match="unknown published weights 'official:dcp_v9'; known: official:dcp_v1"):
        resolve("official:dcp_v9")
    with pytest.raises(ConfigError) as info:
        get_registrator("dcp", weights="official:dcp_v1", checkpoint="x.ckpt")
    assert "\n" not in str(info.value)


def test_the_shared_file_must_be_the_published_one(tmp_path, monkeypatch):
    monkeypatch.setenv("OMNET_SHARED_DIR", str(tmp_path))
    with pytest.raises(CheckpointError, match=r"official:dcp_v1: .*dcp_v1.t7 does not exist"):
        resolve("official:dcp_v1")
    (tmp_path / "weights").mkdir()
    torch.save({"emb_nn.conv1.weight": torch.zeros(1)}, tmp_path / "weights" / "dcp_v1.t7")
    with pytest.raises(CheckpointError, match="has sha256 .* not the published file's 797d34fa5ef9"):
        resolve("official:dcp_v1")
    # the same file given by its path (once loaded as the published weights, its sha256 never checked)
    with pytest.raises(CheckpointError, match="has sha256 .* not the published file's 797d34fa5ef9"):
        resolve(str(tmp_path / "weights" / "dcp_v1.t7"))


@needs("dcp_v1")
def test_a_path_of_another_name_is_loaded_but_marked_unverified(tmp_path):
    published = shared_path("weights", PUBLISHED["dcp_v1"].file)
    copy = tmp_path / "my_dcp.t7"
    copy.write_bytes(published.read_bytes())
    assert resolve(str(published)).verified and not resolve(str(copy)).verified
    assert published_module(str(copy)).hparams["weights"] == {"spec": str(copy), "file": str(copy), "verified": False}


def test_registry_entries_are_complete():
    for name, entry in PUBLISHED.items():
        assert entry.name == name and len(entry.sha256) == 64 and entry.license and entry.source and entry.trained_on
        if entry.method is not None:
            assert (Path(CONF) / "model" / f"{entry.model}.yaml").is_file()
            assert (Path(CONF) / "exp" / f"{entry.protocol}.yaml").is_file()


# --- numerical equivalence with the authors' code ----------------------------------------------------


@needs("dcp_v1")
def test_dcp_v1_matches_the_authors_code():
    data = fixture("dcp_v1")
    module = published_module("official:dcp_v1")
    assert module.hparams["network"]["pointer"] is False
    with torch.no_grad():
        transform = module(data["src"], data["ref"])
    torch.testing.assert_close(transform[:, :3, :3], data["rotation"], atol=5e-4, rtol=0)
    torch.testing.assert_close(transform[:, :3, 3], data["translation"], atol=5e-4, rtol=0)


def run_published_lk(name: str, linearize):
    """The published PointNetLK-style network ``name`` on its fixture: ``linearize(network, centred
    template) -> (features, jacobian)`` and the registration, in eval mode; the features must be the
    authors'. Returns (fixture, jacobian, output)."""
    data = fixture(name)
    network = published_module(f"official:{name}").network
    template, source = data["template"], data["source"]
    centred = template - template.mean(dim=1, keepdim=True)
    with torch.no_grad(), eval_mode(network.encoder):
        features, jacobian = linearize(network, centred)
        out = network(source, template)
    torch.testing.assert_close(features, data["features"], atol=1e-4, rtol=1e-5)
    return data, jacobian, out


def _learning3d_linearize(network, centred):
    features = network.features(centred)
    return features, lk_jacobian(network.features, centred, network.delta, features)


@needs("learning3d_pointnetlk")
def test_learning3d_pointnetlk_matches_the_authors_code_and_fixes_its_translation():
    data, jacobian, out = run_published_lk("learning3d_pointnetlk", _learning3d_linearize)
    template, source = data["template"], data["source"]
    torch.testing.assert_close(jacobian, data["jacobian"], atol=2e-3, rtol=1e-4)  # finite differences, δ = 0.01
    assert len(out["transforms"]) == 10 and out["iterations"] == int(data["iterations"])
    torch.testing.assert_close(out["residual"], data["residual"], atol=1e-3, rtol=1e-4)
    ours = out["transforms"][-1]
    mean_t, mean_s = template.mean(dim=1), source.mean(dim=1)
    torch.testing.assert_close(ours, translation(mean_t) @ data["g_centred"] @ translation(-mean_s), atol=1e-4, rtol=0)
    # learning3d reports T(m_t)·g·T(−m_t); ours is right, theirs off by about the translation
    torch.testing.assert_close(learning3d_reported_transform(ours, source, template), data["est_T"], atol=1e-4, rtol=0)
    eye = torch.eye(4).expand(2, 4, 4)
    torch.testing.assert_close(ours @ data["igt"], eye, atol=1e-4, rtol=0)
    assert (data["est_T"] @ data["igt"] - eye)[:, :3, 3].norm(dim=1).min() > 0.1


@needs("pointnetlk_revisited")
def test_pointnetlk_revisited_matches_the_authors_code():
    data, jacobian, out = run_published_lk("pointnetlk_revisited", lambda network, centred: network.linearize(centred))
    torch.testing.assert_close(jacobian, -data["jacobian"], atol=1e-4, rtol=1e-5)  # theirs: ∂φ(exp(−ξ)P)/∂ξ
    assert len(out["transforms"]) == 20 and out["iterations"] == int(data["iterations"]) - 1  # theirs counts the stop test
    torch.testing.assert_close(out["transforms"][-1], data["transform"], atol=1e-4, rtol=0)


# --- the three entries ---------------------------------------------------------------------------------


@needs("dcp_v1")
@needs("learning3d_pointnet_classifier_features")  # its wrong-method refusal
def test_python_api_and_wrong_method():
    data = fixture("dcp_v1")
    registrator = get_registrator("dcp", weights="official:dcp_v1", device="cpu")
    assert registrator.label == "DCP (official:dcp_v1)"
    estimate = registrator.register(data["src"][0].numpy(), data["ref"][0].numpy())
    np.testing.assert_allclose(estimate[:3, :3], data["rotation"][0].numpy(), atol=5e-4)
    with pytest.raises(CheckpointError, match=r"holds a baselines\.learned\.dcp\.DCP network, not .*use it as method 'dcp'"):
        get_registrator("pointnetlk", weights="official:dcp_v1")
    with pytest.raises(CheckpointError, match="holds PointNet features, not a registration network"):
        get_registrator("pointnetlk", weights="official:learning3d_pointnet_classifier_features")


@needs("dcp_v1")
def test_src_eval_evaluates_published_weights(tmp_path):
    from src.eval import evaluate

    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("config", overrides=[
            "model=dcp", "+exp=dcp_protocol", "weights=official:dcp_v1", "data=synthetic", "model_scale=0.0625",
            "data.build.num_points=1024",  # the protocol's 1,024-point clouds (synthetic clouds are whole samplings)
            "data.build.num_train_per_category=2", "data.build.num_test_per_category=1", "data.build.num_samplings=3",
            "data.eval_batch_size=2", "data.num_workers=0", "data.pin_memory=false", "trainer.accelerator=cpu",
            "trainer.limit_test_batches=1", "trainer.enable_progress_bar=false",
            f"data.cache_root={tmp_path / 'cache'}", f"output_dir={tmp_path / 'run'}",
        ])
    metrics = evaluate(cfg)  # the network comes from the registry (full width), not model_scale
    assert metrics["Error(R)"] < 20 and (tmp_path / "run" / "metrics.json").is_file()
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        wrong = compose("config", overrides=["model=omnet", "weights=official:dcp_v1", f"output_dir={tmp_path}"])
    with pytest.raises(CheckpointError, match="holds a baselines.learned.dcp.DCP network, not src.models.omnet.OMNet"):
        evaluate(wrong)


# --- the authors' protocols and the grid file ----------------------------------------------------------


@pytest.mark.parametrize("exp,points,perturbation", [
    ("dcp_protocol", 1024, "euler"), ("pointnetlk_protocol", 1024, "twist"), ("pointnetlk_revisited_protocol", 1000, "twist"),
])
def test_protocol_experiments_compose(exp, points, perturbation):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("config", overrides=[f"+exp={exp}", "data=modelnet40_resampled"])
    assert cfg.task_name == exp and cfg.sampling == "os" and cfg.partial == "none" and cfg.model.euler_seq == "zyx"
    assert cfg.data.pair.num_points == points and cfg.data.pair.noise_sigma == 0 and not cfg.data.remove_axisymmetric
    assert cfg.data.pair.perturbation == perturbation
    assert cfg.data.pair.unit_cube is (exp == "pointnetlk_revisited_protocol")


def test_grid_file_runs_each_model_under_its_protocol_and_omnets():
    import fnmatch

    import benchmarks.grid.plan  # noqa: F401 - registers the grid's primary config

    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose("benchmark_grid", overrides=["+benchmark=published_weights"])
    bench = cfg.benchmark
    excluded = lambda key: any(fnmatch.fnmatchcase(key, p) for p in bench.exclude)  # noqa: E731
    protocols = {e.method: e.protocol for e in PUBLISHED.values() if e.method}
    assert sorted(bench.methods) == sorted(protocols)
    for method, protocol in protocols.items():
        entry = next(e for e in PUBLISHED.values() if e.method == method)
        assert cfg.method_options[method].weights == f"official:{entry.name}"
        assert not excluded(f"{method}/{protocol}/os/none") and excluded(f"{method}/{protocol}/ts/none")
        assert all(not excluded(f"{method}/real_airplane/{s}/{p}") for s in ("os", "ts") for p in ("prnet", "rpmnet"))
        assert excluded(f"{method}/real_airplane/os/none")
        assert all(excluded(f"{method}/{other}/os/none") for other in protocols.values() if other != protocol)


# --- PointNetLK's pair protocol (src/data/perturbations.py) ---------------------------------------------


def test_twist_matrix_is_the_se3_exponential():
    from baselines.learned.common.global_feature import se3_exp

    twist = np.array([0.3, -0.5, 0.2, 0.4, -0.1, 0.7])
    np.testing.assert_allclose(twist_matrix(twist), se3_exp(torch.tensor(twist)).numpy(), atol=1e-12)


def test_twist_perturbation_moves_the_source_within_the_magnitude():
    rng = np.random.default_rng(0)
    points = rng.standard_normal((50, 3)).astype(np.float32)
    norms = []
    for _ in range(200):
        sample = TwistPerturbation(0.8)({"points_src": points.copy(), "points_ref": points.copy(),
                                         "transform_gt": np.eye(4)}, rng)
        gt = sample["transform_gt"]
        np.testing.assert_allclose(sample["points_src"] @ gt[:3, :3].T + gt[:3, 3], points, atol=1e-5)
        angle = np.arccos(np.clip((np.trace(gt[:3, :3]) - 1) / 2, -1, 1))
        norms.append(angle)
    assert max(norms) <= 0.8 and np.mean(norms) < 0.4  # |ω| ≤ |x| = U[0, 0.8]
    fixed = TwistPerturbation(0.8, random_magnitude=False)
    assert fixed.random_magnitude is False


def test_unit_cube_and_the_pipeline_keep_the_pair_rigid():
    rng = np.random.default_rng(1)
    shape = (rng.standard_normal((1, 3000, 3)) * [1.0, 0.5, 0.2] + [0.3, 0, 0]).astype(np.float32)
    sample = build_twist_transforms("disjoint_subsets", "os", 1000, unit_cube=True)({"shape_points": shape}, rng)
    ref, src, gt = sample["points_ref"], sample["points_src"], sample["transform_gt"]
    assert ref.shape == src.shape == (1000, 3)
    np.testing.assert_allclose(np.max(ref.max(0) - ref.min(0)), 1.0, atol=1e-6)
    np.testing.assert_allclose(ref.mean(0), 0.0, atol=1e-6)
    moved = src @ gt[:3, :3].T + gt[:3, 3]
    assert np.abs(np.sort(moved, axis=0) - np.sort(ref, axis=0)).max() < 1e-5  # the same points, shuffled
    cube = UnitCube()({"points_src": shape[0] * 2, "points_ref": shape[0] * 2, "transform_gt": np.eye(4)}, rng)
    np.testing.assert_allclose(cube["transform_gt"], np.eye(4), atol=1e-12)
