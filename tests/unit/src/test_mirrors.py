"""A dataset's hosts tried in order (src/data/mirrors.py), against a real HTTP server on 127.0.0.1, and
the records' hosts themselves: a bad host is one logged line and the next one is tried; the archive that
arrives is verified (checksum, structure) and unpacked; nothing corrupt stays in the downloads folder."""

import hashlib
import json
import logging
import re
import tarfile

import pytest

from src.data.cache import open_cache
from src.data.datasets import DATASETS, get_dataset
from src.data.download import HF_ADDRESS
from src.data.mirrors import MIRRORS_ENV, download_archive
from src.data.prepare import main
from src.utils.errors import DatasetError
from tests.helpers.http_server import File, HubFile, Redirect, dead_url, serve

RESAMPLED = get_dataset("modelnet40_resampled")
HUB_PATH = "/datasets/someone/modelnet/resolve/main/resampled.tar.gz"


@pytest.fixture
def archives(resampled_dir, make_zip, h5_dir, tmp_path):
    """The resampled fixture as .zip and .tar.gz bytes, and the h5 fixture (another layout) as .zip."""
    tar = tmp_path / "resampled.tar.gz"
    with tarfile.open(tar, "w:gz") as f:
        f.add(resampled_dir, arcname=resampled_dir.name)
    return {"zip": make_zip(resampled_dir).read_bytes(), "tar": tar.read_bytes(), "h5": make_zip(h5_dir).read_bytes()}


@pytest.fixture
def mirrors_file(tmp_path, monkeypatch):
    """``write({layout: [entries]})`` -> the file, named by $OMNET_DATA_MIRRORS."""

    def write(listing: dict) -> None:
        path = tmp_path / "mirrors.json"
        path.write_text(json.dumps(listing))
        monkeypatch.setenv(MIRRORS_ENV, str(path))

    return write


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _host_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    """The warnings logged per host tried (``<address>: <what happened>``); the info lines (what was downloaded or
    kept) are not among them."""
    text = "\n".join(r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING)
    return [m[0] for m in re.finditer(r"http://127\.0\.0\.1:\d+/\S+: [^\n]+", text)]


def test_bad_hosts_are_skipped_one_line_each(archives, mirrors_file, tmp_path, caplog):
    good = archives["zip"]
    routes = {"/404.zip": None, "/short.zip": File(good, truncate_to=len(good) // 2), "/wrong.zip": File(good[::-1]),
              "/h5.zip": File(archives["h5"]), "/moved.zip": Redirect("/good.zip"), "/good.zip": File(good)}
    with serve(routes) as (url, requests):
        mirrors_file({"pointnet2_resampled": [
            {"url": dead_url("/a.zip")},                                   # connection refused
            {"url": f"{url}/404.zip"},                                    # HTTP 404
            {"url": f"{url}/short.zip"},                                  # truncated, no checksum: structure
            {"url": f"{url}/wrong.zip", "sha256": _sha(good)},            # another file: checksum
            {"url": f"{url}/h5.zip"},                                     # another layout
            {"url": f"{url}/moved.zip", "md5": hashlib.md5(good).hexdigest()},  # redirected to the archive
            {"url": f"{url}/never.zip"},                                  # not tried
        ]})
        with caplog.at_level(logging.WARNING, logger="src.data.mirrors"):
            path = download_archive(RESAMPLED, tmp_path / "downloads")
    assert path == tmp_path / "downloads" / "moved.zip" and path.read_bytes() == good
    assert download_archive(RESAMPLED, tmp_path / "downloads") == path  # the hosts are gone: verified, not fetched
    assert sorted(p.name for p in (tmp_path / "downloads").iterdir()) == ["moved.zip"]
    assert [r[1] for r in requests] == ["/404.zip", "/short.zip", "/wrong.zip", "/h5.zip", "/moved.zip", "/good.zip"]
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(lines) == 5 and all(line.startswith("http://127.0.0.1:") for line in lines)
    for line, what in zip(lines, ["cannot connect", "HTTP 404 Not Found", "not a readable archive of the dataset",
                                  "checksum mismatch", "it holds the pointnet_h5 layout, not pointnet2_resampled"]):
        assert what in line, (line, what)


def test_tar_archive_from_the_hub_is_unpacked(archives, mirrors_file, tmp_path, monkeypatch):
    data = archives["tar"]
    with serve({HUB_PATH: HubFile(data)}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        mirrors_file({"pointnet2_resampled": [
            {"url": f"https://huggingface.co{HUB_PATH}", "md5": hashlib.md5(data).hexdigest(), "size": len(data)}]})
        path = download_archive(RESAMPLED, tmp_path / "downloads")
    assert path == tmp_path / "downloads" / "resampled" and path.is_dir()
    assert (path / "modelnet40_normal_resampled" / "modelnet40_shape_names.txt").is_file()
    assert download_archive(RESAMPLED, tmp_path / "downloads") == path  # the host is gone: verified, not fetched


def test_kept_file_that_fails_its_checksum_is_replaced(archives, mirrors_file, tmp_path, caplog):
    good = archives["zip"]
    (tmp_path / "downloads").mkdir()
    (tmp_path / "downloads" / "r.zip").write_bytes(archives["h5"])
    with serve({"/r.zip": File(good)}) as (url, requests):
        mirrors_file({"pointnet2_resampled": [{"url": f"{url}/r.zip", "sha256": _sha(good)}]})
        assert download_archive(RESAMPLED, tmp_path / "downloads").read_bytes() == good
    assert len(requests) == 1 and "r.zip: checksum mismatch: expected sha256:" in caplog.text


def test_wrong_size_and_damaged_tar_leave_nothing(archives, mirrors_file, tmp_path):
    tar = archives["tar"]
    with serve({"/a.tar.gz": File(tar), "/b.tar.gz": File(tar, truncate_to=len(tar) // 2)}) as (url, _):
        mirrors_file({"pointnet2_resampled": [{"url": f"{url}/a.tar.gz", "size": len(tar) + 1},
                                              {"url": f"{url}/b.tar.gz"}]})
        with pytest.raises(DatasetError) as error:
            download_archive(RESAMPLED, tmp_path / "downloads")
    assert sorted(p.name for p in (tmp_path / "downloads").iterdir()) == []
    message = str(error.value)
    assert "\n" not in message and message.startswith("no host served a.tar.gz intact (2 tried, one line each above)")
    assert "`python -m src.data.prepare modelnet40_resampled --source PATH`" in message


def test_download_through_the_mirror_list_end_to_end(archives, mirrors_file, tmp_path, caplog):
    good = archives["zip"]
    with serve({"/mirror/resampled.zip": File(good, drop_after=1000)}) as (url, requests):
        mirrors_file({"pointnet2_resampled": [{"url": f"{url}/gone/resampled.zip"},
                                              {"url": f"{url}/mirror/resampled.zip", "sha256": _sha(good)}]})
        assert main(["modelnet40_resampled", "--download", "--cache-root", str(tmp_path / "c")]) == 0
    assert requests[-1] == ("GET", "/mirror/resampled.zip", "bytes=1000-")  # interrupted, then resumed
    assert open_cache(tmp_path / "c" / "modelnet40_resampled").available_splits == ["train", "test"]
    assert [line.split(": ", 1)[1] for line in _host_lines(caplog)] == ["HTTP 404 Not Found"]


def test_no_host_answers_end_to_end(mirrors_file, tmp_path, capsys, caplog):
    with serve({}) as (url, _):
        mirrors_file({"pointnet2_resampled": [{"url": dead_url("/r.zip")}, {"url": f"{url}/r.zip"}]})
        assert main(["modelnet40_resampled", "--download", "--cache-root", str(tmp_path / "c")]) == 2
    assert len(_host_lines(caplog)) == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and captured.err.startswith("error: no host served r.zip intact (2 tried")


@pytest.mark.parametrize(("argv", "message"), [
    (["stanford", "--download"], "stanford has no archive to download: pass --source PATH"),
    (["modelnet40_resampled", "--download", "pointnet_h5"], "modelnet40_resampled downloads no pointnet_h5 archive"),
    (["modelnet40", "--download", "pointnet_h5", "--url", "http://x/y.zip"], "--url: the layout of an archive given"),
])
def test_what_cannot_be_downloaded_is_one_line(tmp_path, capsys, argv, message):
    assert main([*argv, "--cache-root", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err


def test_unreadable_mirrors_file_is_one_line(tmp_path, monkeypatch):
    (tmp_path / "m.json").write_text('{"pointnet2_resampled": [{"adress": "x"}]}')
    monkeypatch.setenv(MIRRORS_ENV, str(tmp_path / "m.json"))
    with pytest.raises(DatasetError, match=r"^OMNET_DATA_MIRRORS=.*m\.json: expected a JSON file mapping layouts"):
        download_archive(RESAMPLED, tmp_path / "downloads")


@pytest.mark.parametrize("mirror", [m for d in DATASETS for s in d.sources for m in s.mirrors], ids=lambda m: m.url)
def test_every_recorded_host_says_where_it_comes_from(mirror):
    assert mirror.url.startswith("https://") or mirror.url.startswith("http://modelnet.cs.princeton.edu/")
    assert re.fullmatch(r"[0-9a-f]{64}|", mirror.sha256) and re.fullmatch(r"[0-9a-f]{32}|", mirror.md5)
    assert mirror.evidence and mirror.file_name.endswith((".zip", ".tar.gz"))
    if "huggingface.co" in mirror.url:
        assert HF_ADDRESS.match(mirror.url)


def test_records_list_the_original_host_last():
    for dataset in DATASETS:
        for source in dataset.downloads:
            assert source.mirrors[-1].evidence.startswith("original host"), source.layout
            assert len({m.file_name.split(".")[0] for m in source.mirrors}) == 1, source.layout


def test_the_records_huggingface_mirror_through_its_endpoint(h5_dir, make_zip, tmp_path, monkeypatch):
    """prepare modelnet40 --download pointnet_h5 with the record's own hosts: its first, the HuggingFace
    mirror, answered by the loopback server through HF_ENDPOINT (huggingface_hub's endpoint setting)."""
    data = make_zip(h5_dir).read_bytes()
    with serve({"/datasets/Msun/modelnet40/resolve/main/modelnet40_ply_hdf5_2048.zip": HubFile(data)}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        assert main(["modelnet40", "--download", "pointnet_h5", "--cache-root", str(tmp_path / "c")]) == 0
    assert (tmp_path / "c" / "downloads" / "modelnet40_ply_hdf5_2048.zip").read_bytes() == data
    assert open_cache(tmp_path / "c" / "modelnet40").manifest["source_layout"] == "pointnet_h5"


def test_an_archive_without_a_published_checksum_is_verified_against_its_first_download(
        archives, resampled_dir, make_zip, mirrors_file, tmp_path, caplog):
    """No host publishes a checksum of PointNet's h5 archive: the first good download's sha256 is recorded, said in
    one line; the archive kept is then verified against it (a partial one is downloaded again), and so are later
    downloads (another version of the archive is refused)."""
    good, downloads = archives["zip"], tmp_path / "downloads"
    routes = {"/r.zip": File(good)}
    with serve(routes) as (url, requests), caplog.at_level(logging.INFO, logger="src.data.mirrors"):
        mirrors_file({"pointnet2_resampled": [{"url": f"{url}/r.zip"}]})
        assert download_archive(RESAMPLED, downloads) == downloads / "r.zip"
        record = downloads / "r.zip.sha256"
        assert record.read_text() == f"{_sha(good)}  r.zip\n"  # as sha256sum writes it: `sha256sum -c` checks it
        assert caplog.messages[-2:] == [
            f"{url}/r.zip: no checksum of r.zip is published; the sha256 of this download, {_sha(good)}, is recorded "
            f"in {record}, and later downloads of it are verified against it",
            f"downloaded {downloads / 'r.zip'} from {url}/r.zip: 5 shapes (train 3, test 2)"]

        caplog.clear()
        assert download_archive(RESAMPLED, downloads) == downloads / "r.zip" and len(requests) == 1  # kept
        assert caplog.messages == [f"using {downloads / 'r.zip'}, kept from an earlier download (sha256 as recorded "
                                   f"at its first download, in {record}): 5 shapes (train 3, test 2)"]

        (downloads / "r.zip").write_bytes(good[: len(good) // 2])  # a partial copy in its place
        caplog.clear()
        assert download_archive(RESAMPLED, downloads).read_bytes() == good and len(requests) == 2
        assert caplog.messages[0] == (f"{downloads / 'r.zip'}: checksum mismatch: expected sha256:{_sha(good)}; "
                                      "deleted: downloading it again")

        (resampled_dir / "airplane" / "airplane_0001.txt").write_text("0,0,0,0,0,1\n1,0,0,0,0,1\n0,1,0,0,0,1\n")
        routes["/r.zip"] = File(make_zip(resampled_dir).read_bytes())  # the host's file changed
        (downloads / "r.zip").unlink()
        caplog.clear()
        with pytest.raises(DatasetError, match=r"^no host served r\.zip intact"):
            download_archive(RESAMPLED, downloads)
    assert caplog.messages[0] == (f"{url}/r.zip: checksum mismatch: expected sha256:{_sha(good)}; the transfer is "
                                  f"deleted (the sha256 recorded at its first download, in {record}: delete that file "
                                  "to accept another version of the archive)")
    assert sorted(p.name for p in downloads.iterdir()) == ["r.zip.sha256"]


def test_an_archive_kept_that_nothing_can_verify_is_refused_in_one_line(archives, mirrors_file, tmp_path, capsys):
    """A file in downloads/ of which no checksum is published and none was recorded (copied there by hand, or
    downloaded by an earlier version): refused, left as it is, and the hosts are not asked."""
    kept = tmp_path / "c" / "downloads" / "r.zip"
    kept.parent.mkdir(parents=True)
    kept.write_bytes(archives["zip"])
    with serve({"/r.zip": File(archives["zip"])}) as (url, requests):
        mirrors_file({"pointnet2_resampled": [{"url": f"{url}/r.zip"}]})
        assert main(["modelnet40_resampled", "--download", "--cache-root", str(tmp_path / "c")]) == 2
    assert requests == [] and kept.read_bytes() == archives["zip"]
    err = capsys.readouterr().err
    assert err == (f"error: {kept} is in the downloads folder, but no checksum of it is published and none was recorded "
                   "when it was downloaded, so it cannot be verified (it may be partial or another file): delete it to "
                   f"download it again, or pass it as --source {kept} to use it as it is\n")


def test_an_archive_kept_with_a_published_checksum_says_what_it_gives(archives, mirrors_file, tmp_path, caplog):
    good = archives["zip"]
    (tmp_path / "downloads").mkdir()
    (tmp_path / "downloads" / "r.zip").write_bytes(good)
    mirrors_file({"pointnet2_resampled": [{"url": dead_url("/r.zip"), "md5": hashlib.md5(good).hexdigest()}]})
    with caplog.at_level(logging.INFO, logger="src.data.mirrors"):
        assert download_archive(RESAMPLED, tmp_path / "downloads") == tmp_path / "downloads" / "r.zip"
    assert caplog.messages == [f"using {tmp_path / 'downloads' / 'r.zip'}, kept from an earlier download (md5 as "
                               "published): 5 shapes (train 3, test 2)"]
