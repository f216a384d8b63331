import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest

from src.data import cache as cache_module
from src.data.cache import REQUIRED_FIELDS, CacheWriter, open_cache
from src.data.mesh import MeshShape
from src.data.prepare import build_synthetic_cache, ensure_cache, main, prepare
from src.utils.errors import ConfigError, DatasetError
from src.utils.paths import shared_path
from tests.helpers.paths import ROOT

AIRPLANE_ZIP = shared_path("data", "modelnet40_normal_resampled_airplane.zip")


@pytest.fixture(autouse=True)
def info_logs(caplog):
    caplog.set_level(logging.INFO, logger="src.data.prepare")
    return caplog


def _points(cache, split="train"):
    return np.array(cache.split(split).points)


def test_princeton_folder_and_zip_with_workers_agree(princeton_dir, make_zip, tmp_path):
    kwargs = {"num_samplings": 3, "num_points": 64, "seed": 1}
    cache = prepare("modelnet40", source=princeton_dir, cache_root=tmp_path / "a", workers=1, **kwargs)
    pooled = prepare("modelnet40", source=make_zip(princeton_dir), cache_root=tmp_path / "b", workers=2, **kwargs)
    assert (cache.pair_sampling, cache.categories) == ("independent_samplings", ["airplane", "chair"])
    assert cache.halves == {"1": ["airplane", "chair"], "2": []}
    assert cache.manifest["sampling"] == {
        "num_samplings": 3, "num_points": 64, "seed": 1, "method": "area_weighted_uniform",
        "normalization": "bbox_center_unit_sphere", "limit": None,
    }
    train = cache.split("train")
    assert train.points.shape == (3, 3, 64, 3) and train.normals is None and train.labels.tolist() == [0, 0, 1]
    assert cache.split("test").shape_names == ["airplane_0003", "chair_0002"]
    assert np.linalg.norm(train.points, axis=-1).max() <= 1 + 1e-6
    for split in ("train", "test"):
        assert np.array_equal(_points(cache, split), _points(pooled, split))


def test_pointnet_h5_is_single_sampling(h5_dir, tmp_path):
    cache = prepare("modelnet40", source=h5_dir, cache_root=tmp_path)
    assert (cache.pair_sampling, cache.manifest["source_layout"]) == ("single_sampling", "pointnet_h5")
    assert cache.split("train").points.shape == cache.split("train").normals.shape == (3, 1, 32, 3)
    assert cache.split("train").shape_names == ["airplane_0001", "chair_0001", "airplane_0002"]
    assert cache.manifest["sampling"]["num_points"] == 32
    with pytest.raises(DatasetError, match="--num-points: not applicable to the pointnet_h5 layout"):
        prepare("modelnet40", source=h5_dir, cache_root=tmp_path, num_points=1024)


def test_resampled_split_with_missing_files(resampled_dir, tmp_path, info_logs):
    (resampled_dir / "chair" / "chair_0002.txt").unlink()
    cache = prepare("modelnet40_resampled", source=resampled_dir, cache_root=tmp_path)
    message = cache.manifest["missing_splits"]["test"]["message"]
    assert message == (
        f"split 'test' is not built: 1 of 2 shapes listed in its split list are missing from {resampled_dir} "
        "(chair: 1 of 1, first: chair_0002)"
    )
    assert message in info_logs.messages
    assert cache.pair_sampling == "disjoint_subsets" and cache.available_splits == ["train"]
    assert cache.split("train").points.shape == (3, 1, 20, 3)
    with pytest.raises(DatasetError) as error:
        open_cache(tmp_path / "modelnet40_resampled").split("test")
    assert str(error.value) == message


def test_malformed_file_in_a_worker_aborts_the_build(resampled_dir, tmp_path):
    (resampled_dir / "chair" / "chair_0001.txt").write_text("1,2,3,4,5,6\n1,2,3\n")
    with pytest.raises(DatasetError, match="chair/chair_0001.txt: line 2 is malformed"):
        prepare("modelnet40_resampled", source=resampled_dir, cache_root=tmp_path / "c", workers=2)
    assert [p.name for p in (tmp_path / "c").iterdir()] == [".modelnet40_resampled.lock"]


def _flip(path):
    data = bytearray(path.read_bytes())
    data[200] ^= 0xFF
    path.write_bytes(bytes(data))


def _incomplete(path):
    manifest = json.loads((path.parent / "manifest.json").read_text())
    del manifest["complete"]
    (path.parent / "manifest.json").write_text(json.dumps(manifest))


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        (_flip, "sha256 mismatch"),
        (lambda p: p.write_bytes(p.read_bytes()[:-8]), "truncated or corrupt"),
        (_incomplete, "incomplete"),
    ],
)
def test_rerun_is_a_noop_and_damage_is_rebuilt(princeton_dir, tmp_path, info_logs, monkeypatch, damage, reason):
    args = {"source": princeton_dir, "cache_root": tmp_path, "num_samplings": 2, "num_points": 16}
    original = _points(prepare("modelnet40", **args))
    points_file = tmp_path / "modelnet40" / "train_points.npy"
    stamp = points_file.stat().st_mtime_ns
    prepare("modelnet40", **args)
    assert "up to date" in info_logs.text and points_file.stat().st_mtime_ns == stamp
    damage(points_file)
    monkeypatch.setattr(cache_module, "_verified", set(), raising=False)  # as in a new process
    info_logs.clear()
    rebuilt = prepare("modelnet40", **args)
    assert "rebuilding:" in info_logs.text and reason in info_logs.text
    assert np.array_equal(_points(open_cache(rebuilt.root)), original)


def test_different_parameters_or_source_rebuild(princeton_dir, tmp_path, info_logs):
    args = {"source": princeton_dir, "cache_root": tmp_path, "num_samplings": 2, "num_points": 16}
    prepare("modelnet40", **args)
    assert prepare("modelnet40", **{**args, "num_points": 8}).split("train").points.shape == (3, 2, 8, 3)
    assert "was built with different sampling" in info_logs.text
    (princeton_dir / "airplane" / "train" / "airplane_0001.off").unlink()
    assert prepare("modelnet40", **{**args, "num_points": 8}).split("train").points.shape[0] == 2
    assert "was built with different source" in info_logs.text


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["modelnet40"], "error: modelnet40 needs --source PATH (a princeton_off or pointnet_h5 folder or .zip)"),
        (["modelnet40", "--source", "{resampled}"], "prepared as `modelnet40_resampled`, not `modelnet40`"),
        (["modelnet40_resampled", "--source", "{tmp}/nowhere"], "nowhere does not exist"),
        (["modelnet40", "--url", "http://x/y.zip"], "--url is only used with --download"),
        (["synthetic", "--source", "{tmp}"], "error: --source: not applicable to synthetic"),
        (["modelnet40_resampled", "--source", "{truncated}"], "truncated.zip is a damaged .zip archive (its end-of"),
        (["modelnet40_resampled", "--source", "{overflow}"], "airplane_0002.txt: line 2 has the value 1e40, beyond"),
    ],
)
def test_main_reports_errors_in_one_line(resampled_dir, make_zip, tmp_path, capsys, argv, message):
    data = make_zip(resampled_dir).read_bytes()
    (tmp_path / "truncated.zip").write_bytes(data[: len(data) // 2])
    (resampled_dir / "airplane" / "airplane_0002.txt").write_text("0,0,0,0,0,1\n0.1,1e40,0,0,0,1\n")
    argv = [a.format(resampled=resampled_dir, tmp=tmp_path, truncated=tmp_path / "truncated.zip",
                     overflow=resampled_dir) for a in argv]
    assert main([*argv, "--cache-root", str(tmp_path / "cache")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err


def test_download_then_prepare(resampled_dir, make_zip, tmp_path):
    url = make_zip(resampled_dir).as_uri()
    assert main(["modelnet40_resampled", "--download", "--url", url, "--cache-root", str(tmp_path / "c")]) == 0
    assert (tmp_path / "c" / "downloads" / "modelnet40_normal_resampled_zip.zip").is_file()
    assert open_cache(tmp_path / "c" / "modelnet40_resampled").available_splits == ["train", "test"]


@pytest.fixture
def fake_synthetic(monkeypatch, tmp_path, meshes):
    """A stand-in for src.data.synthetic: 2 categories (box, tetra); its source file is a tmp file."""
    module = types.ModuleType("src.data.synthetic")
    module.__file__ = str(tmp_path / "synthetic.py")
    Path(module.__file__).write_text("v1")
    module.SYNTHETIC_CATEGORIES = ("box", "tetra")
    module.SYNTHETIC_HALVES = {"1": ["box"], "2": ["tetra"]}

    def generate_shapes(num_train_per_category, num_test_per_category, seed):
        rng = np.random.default_rng(seed)
        for split, count in (("train", num_train_per_category), ("test", num_test_per_category)):
            for category, mesh in (("box", meshes["cube"]), ("tetra", meshes["tetra"])):
                for i in range(count):
                    yield MeshShape(f"{category}_{split}_{i}", category, split, mesh[0] * rng.uniform(0.5, 2, 3), mesh[1])

    module.generate_shapes = generate_shapes
    monkeypatch.setitem(sys.modules, "src.data.synthetic", module)
    return module


def test_synthetic_builds_once_and_ensure_cache_reuses(fake_synthetic, tmp_path, info_logs):
    params = {"num_train_per_category": 2, "num_test_per_category": 1, "num_samplings": 2, "num_points": 16}
    cache = build_synthetic_cache(tmp_path, **params)
    assert (cache.dataset, cache.manifest["source_layout"]) == ("synthetic", "procedural")
    assert cache.pair_sampling == "independent_samplings"
    assert cache.categories == ["box", "tetra"] and cache.halves == {"1": ["box"], "2": ["tetra"]}
    assert cache.split("train").points.shape == (4, 2, 16, 3) and cache.split("test").labels.tolist() == [0, 1]
    assert cache.manifest["sampling"]["num_train_per_category"] == 2
    info_logs.clear()
    assert np.array_equal(_points(ensure_cache("synthetic", tmp_path, **params)), _points(cache))
    assert "up to date" in info_logs.text
    Path(fake_synthetic.__file__).write_text("v2")  # the generator changed
    ensure_cache("synthetic", tmp_path, **params)
    assert "was built with different source" in info_logs.text


def test_ensure_cache_for_real_datasets(resampled_dir, tmp_path):
    with pytest.raises(ConfigError, match="unknown dataset 'modelnet10'; expected one of modelnet40, "):
        ensure_cache("modelnet10", tmp_path)
    fix = r"run `python -m src.data.prepare modelnet40 --source PATH` \(or use data=synthetic"
    with pytest.raises(DatasetError, match=rf"no dataset cache at .*modelnet40; {fix}"):
        ensure_cache("modelnet40", tmp_path)
    prepare("modelnet40_resampled", source=resampled_dir, cache_root=tmp_path)
    assert ensure_cache("modelnet40_resampled", tmp_path, num_points=20).dataset == "modelnet40_resampled"
    with pytest.raises(DatasetError, match="has num_points=20, requested 10000"):
        ensure_cache("modelnet40_resampled", tmp_path, num_points=10000)


@pytest.mark.shared_data("data/modelnet40_normal_resampled_airplane.zip")
def test_real_airplane_archive(tmp_path, info_logs):
    cache = prepare("modelnet40_resampled", source=AIRPLANE_ZIP, cache_root=tmp_path, limit=5)
    train = cache.split("train")
    assert train.points.shape == (5, 1, 10000, 3) and train.shape_names[0] == "airplane_0001"
    assert np.linalg.norm(train.points, axis=-1).max() < 1.01
    assert np.allclose(np.linalg.norm(train.normals, axis=-1), 1, atol=1e-2)
    missing = cache.manifest["missing_splits"]["test"]
    assert missing["count"] == 100 and missing["examples"][:2] == ["airplane_0627", "airplane_0628"]
    assert missing["by_category"]["airplane"]["missing"] == 100
    assert missing["message"] in info_logs.messages
    with pytest.raises(DatasetError, match=r"'test' is not built: 100 of 100 shapes .* \(airplane: 100 of 100, first"):
        cache.split("test")


# --- content verified at use: train/eval open caches through ensure_cache ----------


@pytest.fixture
def resampled_cache(resampled_dir, make_zip, tmp_path, monkeypatch):
    """A modelnet40_resampled cache built from a zip of ``resampled_dir``; the memo of verified caches
    starts empty, as in a new process. Returns ``(zip, original train points)``."""
    source = make_zip(resampled_dir)
    cache = prepare("modelnet40_resampled", source=source, cache_root=tmp_path / "cache")
    monkeypatch.setattr(cache_module, "_verified", set(), raising=False)
    return source, _points(cache)


def _zero_shapes_in_place(root: Path) -> None:
    points = np.load(root / "modelnet40_resampled" / "train_points.npy", mmap_mode="r+")
    points[:2] = 0
    points.flush()


def _flip_manifest(field: str, value: object):
    def flip(root: Path) -> None:
        path = root / "modelnet40_resampled" / "manifest.json"
        manifest = json.loads(path.read_text())
        manifest[field] = value
        path.write_text(json.dumps(manifest, indent=1))
    return flip


EDITED_MANIFEST = r"manifest.json is corrupt \(its content_hash does not match its fields\)"
DAMAGES = [
    (_zero_shapes_in_place, r"train_points.npy is corrupt \(sha256 mismatch\)"),
    (_flip_manifest("halves", {"2": ["airplane"]}), EDITED_MANIFEST),
    (_flip_manifest("pair_sampling", "independent_samplings"), EDITED_MANIFEST),
]


@pytest.mark.parametrize(("damage", "cause"), DAMAGES)
def test_damage_is_rebuilt_at_use_from_the_known_source(resampled_cache, tmp_path, info_logs, damage, cause):
    source, original = resampled_cache
    damage(tmp_path / "cache")
    cache = ensure_cache("modelnet40_resampled", tmp_path / "cache")
    warning = rf".*/modelnet40_resampled/{cause}: rebuilding it from {re.escape(str(source))}"
    assert any(re.fullmatch(warning, message) for message in info_logs.messages)
    assert np.array_equal(_points(cache), original) and cache.halves == {"1": ["airplane", "chair"], "2": []}
    assert cache.pair_sampling == "disjoint_subsets"


@pytest.mark.parametrize(("damage", "cause"), DAMAGES)
def test_damage_without_its_source_is_refused_in_one_line(resampled_cache, tmp_path, damage, cause):
    resampled_cache[0].unlink()
    damage(tmp_path / "cache")
    with pytest.raises(DatasetError, match=rf"{cause}; run `python -m src.data.prepare modelnet40_resampled") as error:
        ensure_cache("modelnet40_resampled", tmp_path / "cache")
    assert "\n" not in str(error.value)


@pytest.mark.parametrize(("damage", "cause"), DAMAGES[1:])
def test_prepare_rebuilds_a_manifest_edited_in_place(resampled_cache, tmp_path, info_logs, damage, cause):
    damage(tmp_path / "cache")
    cache = prepare("modelnet40_resampled", source=resampled_cache[0], cache_root=tmp_path / "cache")
    assert re.search(rf"rebuilding: .*{cause}", info_logs.text) and "hashes verified" not in info_logs.text
    assert cache.halves == {"1": ["airplane", "chair"], "2": []} and cache.pair_sampling == "disjoint_subsets"


def test_the_datamodule_notices_same_size_damage(resampled_cache, tmp_path, info_logs):
    from src.data.datamodule import RegistrationDataModule

    _zero_shapes_in_place(tmp_path / "cache")
    datamodule = RegistrationDataModule(
        "modelnet40_resampled", str(tmp_path / "cache"), splits={"train": {"split": "train"}}, num_workers=0,
        remove_axisymmetric=False, pair={"sampling": "os", "partial": "prnet", "num_points": 16, "prnet_num_keep": 8},
    )
    datamodule.setup("fit")
    assert "train_points.npy is corrupt (sha256 mismatch)" in info_logs.text
    assert np.array_equal(np.asarray(datamodule.datasets["train"].points), resampled_cache[1])


def test_a_format_1_cache_is_rebuilt_at_use_from_its_recorded_source(resampled_cache, tmp_path, info_logs):
    path = tmp_path / "cache" / "modelnet40_resampled" / "manifest.json"
    manifest = json.loads(path.read_text())
    source = manifest["source"]
    manifest |= {"format_version": 1, "source": {"path": source["paths"][0], "fingerprint": source["fingerprints"][0]}}
    path.write_text(json.dumps(manifest))
    cache = ensure_cache("modelnet40_resampled", tmp_path / "cache")
    assert "has format_version 1, expected 2: rebuilding it from " in info_logs.text
    assert cache.manifest["format_version"] == 2 and np.array_equal(_points(cache), resampled_cache[1])


# --- shape identities across splits and files: a leak or a different dataset than the lists say --


def _append(path: Path, line: str) -> None:
    path.write_text(path.read_text() + line + "\n")


@pytest.mark.parametrize("edit, message", [
    # trained with a train/test leak: the index-based guard compares within one split only
    (lambda root: _append(root / "modelnet40_test.txt", "airplane_0001"),
     "1 shapes are listed in both modelnet40_train.txt of {root} and modelnet40_test.txt of {root} "
     "(first: airplane_0001): a shape in two splits leaks the test set into training; list each shape in one split"),
    (lambda root: _append(root / "modelnet40_train.txt", "chair_0001"),
     "modelnet40_train.txt of {root} lists 1 shape ids more than once (first: chair_0001): list each shape once"),
    (lambda root: (root / "airplanes").mkdir() or (root / "airplanes" / "airplanes_0001.txt").write_text("0,0,0,0,0,1\n"),
     "{root}: the folders airplanes hold shapes of categories that modelnet40_shape_names.txt does not name: add them "
     "to it, or remove the folders"),
    (lambda root: _append(root / "modelnet40_train.txt", "aeroplane_0001"),
     "{root}: modelnet40_train.txt lists shapes of categories that modelnet40_shape_names.txt does not name "
     "(aeroplane): a list of another dataset?"),
])
def test_shape_identities_are_checked_across_splits_and_files(resampled_dir, tmp_path, edit, message):
    edit(resampled_dir)
    with pytest.raises(DatasetError) as error:
        prepare("modelnet40_resampled", source=resampled_dir, cache_root=tmp_path)
    assert str(error.value) == message.format(root=resampled_dir)
    assert not (tmp_path / "modelnet40_resampled").exists()


def test_merged_sources_sharing_a_shape_across_splits_are_refused(resampled_dir, tmp_path):
    other = tmp_path / "other" / "modelnet40_normal_resampled"
    (other / "chair").mkdir(parents=True)
    (other / "chair" / "chair_0001.txt").write_text((resampled_dir / "chair" / "chair_0001.txt").read_text())
    (other / "modelnet40_shape_names.txt").write_text((resampled_dir / "modelnet40_shape_names.txt").read_text())
    (other / "modelnet40_test.txt").write_text("chair_0001\n")  # a training chair of the first source
    (resampled_dir / "modelnet40_test.txt").write_text("airplane_0003\n")
    with pytest.raises(DatasetError, match=r"^1 shapes are listed in both .*modelnet40_train.txt .* and .*other.*"
                                           r"modelnet40_test.txt .*\(first: chair_0001\)"):
        prepare("modelnet40_resampled", source=[resampled_dir, other], cache_root=tmp_path / "cache")


def test_training_refuses_a_cache_whose_splits_share_a_shape_id(tmp_path):
    """A cache written before these checks (or by hand): the same id in its train and test splits."""
    from src.data.cache import CacheSplit, write_cache
    from src.data.datamodule import RegistrationDataModule
    from src.utils.errors import ConfigError

    points = np.random.default_rng(0).normal(size=(2, 1, 64, 3)).astype(np.float32)
    fields = {"dataset": "modelnet40_resampled", "source_layout": "pointnet2_resampled",
              "pair_sampling": "disjoint_subsets", "categories": ["airplane"], "halves": {"1": ["airplane"], "2": []},
              "sampling": {"num_samplings": 1}, "source": {"paths": [], "fingerprints": []}}
    write_cache(tmp_path / "modelnet40_resampled", fields, {
        "train": CacheSplit("train", points, None, np.zeros(2, np.int64), ["airplane_0001", "airplane_0002"]),
        "test": CacheSplit("test", points[:1], None, np.zeros(1, np.int64), ["airplane_0002"]),
    })
    splits = {"train": {"split": "train", "categories": "all"}, "test": {"split": "test", "categories": "all"}}
    datamodule = RegistrationDataModule("modelnet40_resampled", str(tmp_path), splits, remove_axisymmetric=False,
                                        pair={"num_points": 32}, batch_size=1, num_workers=0)
    with pytest.raises(ConfigError, match=r"^1 shapes of the test set are also training shapes \(cache splits 'train' "
                                          r"and 'test' list the same shape ids\) \(first: airplane_0002\)"):
        datamodule.setup("fit")


def test_an_up_to_date_cache_is_said_once_per_process(princeton_dir, tmp_path, info_logs):
    """A grid of 12 cells printed the same "cache up to date" line 12 times."""
    args = {"source": princeton_dir, "cache_root": tmp_path, "num_samplings": 2, "num_points": 16}
    prepare("modelnet40", **args)
    info_logs.clear()
    for _ in range(3):
        prepare("modelnet40", **args)
    assert info_logs.text.count("cache up to date") == 1


# A build whose two pool workers each work on a shape that takes 10 minutes, as `prepare --workers 2` does.
_SLOW_BUILD = """
import sys
from pathlib import Path
from src.data.cache import REQUIRED_FIELDS, CacheWriter
from src.data.prepare import _shape_mapper
from src.utils.errors import exit_code_of
from tests.helpers.slow_shapes import SlowReader, as_loaded

folder = Path(sys.argv[1])

def build():
    with CacheWriter(folder / "cache" / "slow", dict.fromkeys(REQUIRED_FIELDS, "")), \\
            _shape_mapper(SlowReader(folder / "pids"), as_loaded, {}, workers=2) as map_tasks:
        list(map_tasks([(i, 600) for i in range(8)]))

sys.exit(exit_code_of(build))
"""


def _running(pid: int) -> bool:
    """Whether process ``pid`` still runs (a zombie, ended but not yet reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _default_signals() -> None:
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, signal.SIG_DFL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize(("signum", "status"), [(signal.SIGKILL, -signal.SIGKILL), (signal.SIGTERM, -signal.SIGTERM),
                                                (signal.SIGINT, 128 + signal.SIGINT)], ids=["kill", "term", "int"])
def test_a_stopped_build_leaves_no_worker_and_the_next_build_removes_its_folder(tmp_path, caplog, signum, status):
    """Its workers outlived a `prepare --workers 2` stopped by kill -9 or SIGTERM, for good, and so did its temporary
    folder (168 MB for the airplanes). Ctrl+C (SIGINT) cleans up at once; the others' folder goes at the next build."""
    caplog.set_level(logging.INFO, logger="src.data.cache")
    (tmp_path / "pids").mkdir()
    # the build starts as from a shell, with every signal's default action: a child inherits the signals its parent
    # ignores, and the test process may ignore SIGINT after another test's libraries
    process = subprocess.Popen([sys.executable, "-c", _SLOW_BUILD, str(tmp_path)], cwd=ROOT, stderr=subprocess.PIPE,
                               text=True, preexec_fn=_default_signals)
    deadline = time.monotonic() + 120
    while len(list((tmp_path / "pids").iterdir())) < 2 and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    workers = [int(p.name) for p in (tmp_path / "pids").iterdir()]
    assert len(workers) == 2 and all(map(_running, workers)), process.stderr.read() if process.poll() else workers
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == status, stderr
    deadline = time.monotonic() + 10
    while any(map(_running, workers)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(map(_running, workers))
    left = list((tmp_path / "cache").glob(".slow.tmp-*"))
    assert len(left) == (signum != signal.SIGINT)
    if signum == signal.SIGINT:
        assert stderr.strip().splitlines()[-1] == "error: interrupted by SIGINT"
    CacheWriter(tmp_path / "cache" / "slow", dict.fromkeys(REQUIRED_FIELDS, "")).abort()  # the next build
    assert list((tmp_path / "cache").iterdir()) == []
    removed = [m for m in caplog.messages if m.startswith("removed")]
    assert removed == ([f"removed 1 folder(s) left by an interrupted build of {tmp_path / 'cache' / 'slow'}: "
                        f"{left[0].name}"] if left else [])


def test_only_the_folders_of_writers_that_no_longer_run_are_removed(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    for owner in (int(dead.stdout), os.getpid()):
        (tmp_path / f".slow.tmp-{owner}-abc").mkdir()
        (tmp_path / f".slow.old-{owner}-abc").mkdir()
    (tmp_path / ".other.tmp-1-abc").mkdir()  # another cache's
    CacheWriter(tmp_path / "slow", dict.fromkeys(REQUIRED_FIELDS, "")).abort()
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        ".other.tmp-1-abc", f".slow.old-{os.getpid()}-abc", f".slow.tmp-{os.getpid()}-abc"]


@pytest.mark.parametrize("make", [os.mkfifo, lambda path: path.symlink_to(path.parent / "absent.txt")],
                         ids=["fifo", "dangling_link"])
def test_a_shape_file_that_is_no_regular_file_is_refused(resampled_dir, tmp_path, capsys, make):
    """A FIFO among the shape files blocked `prepare` for good (reading it waits for a writer)."""
    shape = resampled_dir / "chair" / "chair_0001.txt"
    shape.unlink()
    make(shape)
    kind = "a FIFO" if shape.is_fifo() else "a link to nothing"
    assert main(["modelnet40_resampled", "--source", str(resampled_dir), "--cache-root", str(tmp_path / "c")]) == 2
    assert capsys.readouterr().err == (f"error: source {resampled_dir}: chair/chair_0001.txt is {kind}, not a regular "
                                       "file: remove it from the folder\n")
