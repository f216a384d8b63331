"""baselines.learned.adapter: a src.train checkpoint behind the Registrator interface, and in the grid."""

import json
import pickle
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from torch.utils.data import DataLoader

from baselines import get_registrator
from baselines.learned.adapter import LEARNED_METHODS, LearnedRegistrator, run_batches
from baselines.testing import euler_transform, l_shape_surface
from src.utils.errors import CheckpointError
from src.models.module import RegistrationModule
from src.utils.paths import SHIPPED_DIR
from tests.helpers.paths import CONF

TINY_OMNET = {"_target_": "src.models.omnet.OMNet", "width": 0.0625, "num_iters": 2}


def _pair(seed: int, n: int = 64) -> dict[str, torch.Tensor]:
    gt = euler_transform((10.0 * seed, 20.0, 5.0), (0.1, -0.2, 0.05))
    src = l_shape_surface(n, seed)
    ref = src @ gt[:3, :3].T + gt[:3, 3]
    return {"points_src": torch.tensor(src, dtype=torch.float32), "points_ref": torch.tensor(ref, dtype=torch.float32),
            "transform_gt": torch.tensor(gt, dtype=torch.float32)}


@pytest.fixture(scope="module")
def omnet_ckpt(tmp_path_factory) -> Path:
    """A tiny OMNet trained for one step and saved with Lightning's Trainer.save_checkpoint."""
    torch.manual_seed(0)
    module = RegistrationModule(network=TINY_OMNET, lr=1e-3)
    trainer = L.Trainer(accelerator="cpu", max_steps=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
    trainer.fit(module, train_dataloaders=DataLoader([_pair(i) for i in range(4)], batch_size=2))
    path = tmp_path_factory.mktemp("ckpt") / "omnet.ckpt"
    trainer.save_checkpoint(path)
    return path


def test_checkpoint_round_trip(omnet_ckpt):
    registrator = get_registrator("omnet", checkpoint=str(omnet_ckpt), device="cpu")
    assert registrator.needs_training and registrator.label == "OMNet"
    batch = [_pair(i) for i in (5, 6, 7)]
    src = torch.stack([b["points_src"] for b in batch])
    ref = torch.stack([b["points_ref"] for b in batch])
    module = RegistrationModule.load_from_checkpoint(omnet_ckpt, map_location="cpu").eval()
    with torch.no_grad():
        expected = module(src, ref).double().numpy()
    got = registrator.register_batch(src.numpy(), ref.numpy())
    assert got.shape == (3, 4, 4) and np.allclose(got, expected, atol=1e-5)
    assert np.allclose(registrator.register(src[1].numpy(), ref[1].numpy()), expected[1], atol=1e-5)
    # picklable without its weights (reloaded lazily), same estimates afterwards
    clone = pickle.loads(pickle.dumps(registrator))
    assert clone._module is None
    assert np.allclose(clone.register_batch(src.numpy(), ref.numpy()), expected, atol=1e-5)
    # run_batches: one result per pair, in order, batched
    results = run_batches(registrator, [(s.numpy(), r.numpy()) for s, r in zip(src, ref)], batch_size=2, progress=False)
    assert len(results) == 3 and not any(r.failed for r in results) and all(0 <= r.fitness <= 1 for r in results)
    assert np.allclose(np.stack([r.transform for r in results]), expected, atol=1e-5)


def test_checkpoint_errors(omnet_ckpt, tmp_path, monkeypatch):
    shipped_networks = {json.loads(card.read_text())["network"]["_target_"] for card in SHIPPED_DIR.glob("*.json")}
    dcp_card = json.loads(next(SHIPPED_DIR.glob("dcp_*.json")).read_text())
    (tmp_path / "shipped").mkdir()
    (tmp_path / "shipped" / "dcp_card_without_weights.json").write_text(json.dumps(dcp_card))
    with monkeypatch.context() as patch:  # every learned method ships one: a folder with a card and no weights
        patch.setattr("baselines.learned.adapter.SHIPPED_DIR", tmp_path / "shipped")
        with pytest.raises(CheckpointError, match="method 'dcp' needs a checkpoint and none is shipped for it in .*checkpoint=PATH"):
            get_registrator("dcp")
    assert set(LEARNED_METHODS.values()) <= shipped_networks  # and each finds its own
    shipped = get_registrator("omnet")  # no checkpoint: the shipped one, named in its label
    assert shipped.label == f"OMNet (shipped: {Path(shipped.config.checkpoint).stem})"
    assert Path(shipped.config.checkpoint).with_suffix(".json").is_file()
    with pytest.raises(CheckpointError, match="does not exist"):
        get_registrator("omnet", checkpoint=str(tmp_path / "missing.ckpt"))
    with pytest.raises(CheckpointError, match=r"holds a src\.models\.omnet\.OMNet network, not baselines\.learned\.dcp\.DCP .*method 'omnet'"):
        get_registrator("dcp", checkpoint=str(omnet_ckpt))
    junk = tmp_path / "junk.ckpt"
    junk.write_text("not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable PyTorch checkpoint"):
        get_registrator("prnet", checkpoint=str(junk))
    with pytest.raises(CheckpointError) as info:
        get_registrator("rpmnet", checkpoint=str(omnet_ckpt))
    assert "\n" not in str(info.value)  # one line


def test_failures_are_flagged_not_raised(omnet_ckpt, monkeypatch):
    registrator = get_registrator("omnet", checkpoint=str(omnet_ckpt), device="cpu")
    pairs = [(_pair(i)["points_src"].numpy(), _pair(i)["points_ref"].numpy()) for i in range(3)]
    real = LearnedRegistrator._register

    def flaky_batch(self, src, ref):
        raise RuntimeError("out of memory")

    def flaky_one(self, src, ref):
        if abs(float(src[0, 0]) - float(pairs[1][0][0, 0])) < 1e-12:
            raise RuntimeError("bad pair\nsecond line")
        out = real(self, src, ref)
        if abs(float(src[0, 0]) - float(pairs[2][0][0, 0])) < 1e-12:
            out[0, 0] = np.nan
        return out

    monkeypatch.setattr(LearnedRegistrator, "_register_batch", flaky_batch)
    monkeypatch.setattr(LearnedRegistrator, "_register", flaky_one)
    results = run_batches(registrator, pairs, progress=False)
    assert [r.failed for r in results] == [False, True, True]
    assert results[1].reason == "RuntimeError: bad pair" and "non-rigid" in results[2].reason
    assert np.allclose(results[1].transform, np.eye(4)) and np.allclose(results[2].transform, np.eye(4))


def test_fresh_weights_for_timing():
    registrator = get_registrator("omnet", fresh_weights=True, model_scale=0.0625,
                                  model_overrides=["model.network.num_iters=1"], device="cpu")
    assert registrator.label == "OMNet (untrained)"
    pair = _pair(1)
    transform = registrator.register(pair["points_src"].numpy(), pair["points_ref"].numpy())
    assert transform.shape == (4, 4) and np.isfinite(transform).all()


def test_learned_method_in_the_grid(omnet_ckpt, tmp_path):
    from benchmarks.grid.run import run_grid

    tiny = ["data.build.num_train_per_category=2", "data.build.num_test_per_category=1", "data.build.num_samplings=3",
            f"data.cache_root={tmp_path / 'cache'}"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("benchmark_grid", overrides=[
            "benchmark.methods=[omnet]", "benchmark.reference=null", "benchmark.experiments=[unseen_shapes]",
            "benchmark.samplings=[ts]",
            "benchmark.partials=[prnet,rpmnet]", "benchmark.max_pairs=3", "progress=false", "paper=false",
            "benchmark.overrides=[" + ",".join(f'"{o}"' for o in tiny) + "]",
            # a checkpoint per cell pattern; none matches the RPMNet-manner cell
            f'method_options.omnet.checkpoint={{*/ts/prnet:"{omnet_ckpt}"}}',
            f"output_dir={tmp_path / 'out'}",
        ])
    result = run_grid(cfg)
    assert result.skipped == ["omnet/unseen_shapes/ts/rpmnet: skipped (no checkpoint of omnet matches unseen_shapes/ts/rpmnet)"]
    tidy = result.tidy
    assert set(tidy["method"]) == {"OMNet"} and set(tidy["partial"]) == {"prnet"} and (tidy["n_pairs"] == 3).all()
    definition = result.cells[0]["definition"]["method"]["config"]
    assert len(definition["checkpoint_sha256"]) == 64


def _tiny_prnet(*overrides: str, **options) -> LearnedRegistrator:
    return get_registrator("prnet", fresh_weights=True, model_scale=0.0625, device="cpu", model_overrides=[
        "model.network.num_iters=1", "model.network.num_keypoints=16", *overrides], **options)


def test_a_network_that_samples_at_test_repeats_whatever_ran_before():
    """PRNet's Gumbel draws are seeded per forward pass: the same batch gives the same estimates after any other
    use of the RNG, the caller's RNG is left as it was, and the seed is what the draws depend on."""
    src = np.stack([l_shape_surface(64, seed) for seed in range(3)])
    ref = src[:, ::-1].copy()
    registrator = _tiny_prnet()
    assert registrator.samples_at_test
    torch.manual_seed(1)
    before = torch.random.get_rng_state()
    first = registrator.register_batch(src, ref)
    assert torch.equal(torch.random.get_rng_state(), before)
    torch.rand(100)
    assert np.array_equal(first, registrator.register_batch(src, ref))
    other_seed = _tiny_prnet(seed=1)
    other_seed._module = registrator.module  # the same weights, other draws
    assert not np.array_equal(first, other_seed.register_batch(src, ref))


def test_the_seed_defines_a_grid_cell_only_for_a_network_that_samples(omnet_ckpt):
    from omegaconf import OmegaConf

    from benchmarks.grid.plan import MethodFactory

    factory = MethodFactory(OmegaConf.create({}))
    assert factory.identity(_tiny_prnet())["config"]["seed"] == 0
    assert "seed" not in factory.identity(get_registrator("omnet", checkpoint=str(omnet_ckpt)))["config"]
    assert not _tiny_prnet("model.network.deterministic_eval=true").samples_at_test
    assert factory.identity(get_registrator("fgr"))["config"]["seed"] == 0  # a classical method's seed stays


def test_the_shipped_checkpoint_says_once_what_it_was_trained_on(caplog, monkeypatch):
    """get_registrator("omnet") took the shipped real-airplane model for any clouds without a word."""
    from baselines.learned import adapter

    monkeypatch.setattr(adapter, "_ANNOUNCED", set())
    with caplog.at_level("WARNING", logger=adapter.__name__):
        first = get_registrator("omnet")
        get_registrator("omnet")
    said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    card = json.loads(Path(first.config.checkpoint).with_suffix(".json").read_text())
    experiment = card["experiment"]
    assert len(said) == 1 and Path(first.config.checkpoint).name in said[0]
    assert all(str(v) in said[0] for v in (experiment["task"], experiment["dataset"], experiment["sampling"].upper()))
    assert "checkpoint=PATH" in said[0]
