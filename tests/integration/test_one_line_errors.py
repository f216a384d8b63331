"""One line saying what to do, for user errors that gave a traceback or a misleading message (docs/bad_input.md).

Checklist (each case: a test below that failed before its fix):

1. a zip member that is encrypted, or compressed with a method zipfile cannot read, is named (``Archive.read``);
2. a split list or shape-name list that is not UTF-8 is named (``readers._lines``);
3. an empty ``ckpt_path=`` (``init_weights=``, ``weights=``) is refused by src.train and src.eval (it ran as if not
   given: a fresh training, the shipped checkpoint's scores);
4. a results-table cell that is not a number names its row and column (``python -m benchmarks.tables``);
5. an output folder under a file, a folder where an output file goes (the tables' ``--out``, a run folder's files);
6. an option of a type its constructor does not take names the type it takes (``trainer.devices=1.5``; a float
   where an integer goes is refused, not truncated), and ``+trainer.max_time={seconds: 1}`` is taken as a mapping;
7. clouds a learned method cannot hold in memory are refused before training, with its point budget;
8. a test result names the weights it tested (the checkpoint and its step, or the last weights and why), and a
   training stopped by ``trainer.max_time`` or the CPU budget says at which step.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

import src.eval
import src.train
from benchmarks.tables.render import main as tables_main
from src.data.readers import open_reader
from src.models.omnet import OMNet
from src.run import memory
from src.run.checkpoint_io import read_checkpoint
from src.run.evaluated import checkpoint_weights
from src.train import train
from src.utils.errors import ConfigError, exit_code_of
from src.validation import validate_config
from tests.helpers.registration_helpers import CONF, TINY, compose_config

SHIPPED = CONF.parent / "checkpoints" / "omnet_unseen_categories_synthetic_ts_prnet.ckpt"
NO_LOGGING = ["hydra/job_logging=none", "hydra/hydra_logging=none"]


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> str:
    return f"data.cache_root={tmp_path_factory.mktemp('cache')}"


def _tiny(cache: str, tmp_path: Path, *overrides: str):
    return compose_config(*TINY, cache, f"output_dir={tmp_path / 'run'}", "+exp=unseen_shapes", *overrides)


def _error_lines(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


# --- 1, 2: archives -----------------------------------------------------------------------------

#: (general-purpose flag, compression method, name length, name) offsets of a local header and a central entry.
_ZIP_ENTRIES = {b"PK\x03\x04": (6, 8, 26, 30), b"PK\x01\x02": (8, 10, 28, 46)}


def _mark_member(archive: Path, member: str, flag_bits: int | None = None, method: int | None = None) -> None:
    """Rewrite ``member``'s local header and central directory entry as an encrypting or another zip tool writes
    them (Python's zipfile writes neither)."""
    data = bytearray(archive.read_bytes())
    for signature, (flag_at, method_at, length_at, name_at) in _ZIP_ENTRIES.items():
        start = data.find(signature)
        while start != -1:
            length = int.from_bytes(data[start + length_at:start + length_at + 2], "little")
            if data[start + name_at:start + name_at + length] == member.encode():
                for value, at in ((flag_bits, flag_at), (method, method_at)):
                    if value is not None:
                        data[start + at:start + at + 2] = value.to_bytes(2, "little")
            start = data.find(signature, start + 4)
    archive.write_bytes(bytes(data))


@pytest.mark.parametrize("flag_bits, method, problem", [  # were: RuntimeError / NotImplementedError tracebacks
    (0x1, None, "is encrypted: unpack the archive with its password and pass the folder, or zip it again without one"),
    (None, 9, "is compressed with method 9 (deflate64), which Python's zipfile cannot read: unpack the archive with a "
              "tool that can (7z x) and pass the folder, or zip it again with deflate"),
])
def test_a_zip_member_zipfile_cannot_read_is_named(resampled_dir, make_zip, flag_bits, method, problem, capsys):
    archive = make_zip(resampled_dir)
    member = "modelnet40_normal_resampled/modelnet40_train.txt"
    _mark_member(archive, member, flag_bits, method)
    assert exit_code_of(lambda: open_reader(archive)) == 2
    assert _error_lines(capsys) == [f"error: {member} in {archive} {problem}"]


@pytest.mark.parametrize("name", ["modelnet40_shape_names.txt", "modelnet40_train.txt"])
def test_a_list_file_that_is_not_utf8_is_named(resampled_dir, name, capsys):
    path = resampled_dir / name  # saved in Latin-1 by a Windows editor: was a UnicodeDecodeError traceback
    path.write_bytes(path.read_bytes().replace(b"airplane", "avi\u00f3n".encode("latin-1"), 1))
    assert exit_code_of(lambda: open_reader(resampled_dir)) == 2
    assert _error_lines(capsys) == [f"error: {name} is not UTF-8 text (byte 0xf3 at offset 3): save it as UTF-8"]


# --- 3: an empty checkpoint path -------------------------------------------------------------------


@pytest.mark.parametrize("module", ["src.train", "src.eval"])  # trained from scratch / scored the shipped checkpoint
def test_an_empty_ckpt_path_on_the_command_line_is_refused(module, tmp_path, monkeypatch, capsys):
    main = {"src.train": src.train.main, "src.eval": src.eval.main}[module]
    monkeypatch.setattr(sys, "argv", [module, "ckpt_path=", f"hydra.run.dir={tmp_path}", *NO_LOGGING])
    with pytest.raises(SystemExit) as info:
        main()
    assert info.value.code == 2
    assert _error_lines(capsys) == ["error: ckpt_path='' is invalid: it must be a non-empty path (or null)"]


def test_empty_weight_paths_are_refused_and_null_and_paths_pass():
    for key in ("init_weights", "weights"):
        with pytest.raises(ConfigError, match=rf"^{key}='' is invalid: it must be a non-empty path \(or null\)$"):
            validate_config(compose_config(f"{key}="))
    for fine in ("ckpt_path=null", "ckpt_path=last", f"ckpt_path={SHIPPED}", "weights=official:dcp_v1"):
        validate_config(compose_config(fine))


# --- 4, 5: results tables and output paths --------------------------------------------------------------

HEADER = "method,experiment,sampling,partial,metric,value\n"


def _results(folder: Path, icp_value: str) -> Path:
    path = folder / "results.csv"
    path.write_text(HEADER + "fgr,unseen_shapes,ts,prnet,Error(R),3.0\n" f"icp,unseen_shapes,ts,prnet,Error(R),{icp_value}\n")
    return path


def test_a_table_cell_that_is_no_number_names_its_row_and_column(tmp_path, capsys):
    results = _results(tmp_path, "1.2 deg")
    assert tables_main([str(results), "--metrics", "Error(R)"]) == 2  # was: TypeError traceback from the mean
    assert _error_lines(capsys) == [
        f"error: {results}: row 2 (method icp, experiment unseen_shapes, sampling ts, metric Error(R)), column value: "
        "'1.2 deg' is not a number; write the number, or NaN for a run that gave none"]
    assert [p.name for p in tmp_path.iterdir()] == ["results.csv"]
    _results(tmp_path, "NaN")  # a run without a number: shown as NaN
    assert tables_main([str(results), "--metrics", "Error(R)"]) == 0
    assert "| icp | NaN |" in capsys.readouterr().out  # TS data only: the TS column alone


@pytest.mark.parametrize("out, problem", [  # were: FileExistsError, NotADirectoryError, IsADirectoryError tracebacks
    ("notes.txt", "{tmp}/notes.txt is a file, not a folder: move the file, or give another --out"),
    ("notes.txt/tables", "{tmp}/notes.txt is a file, not a folder: move the file, or give another --out"),
    ("tables", "{tmp}/tables/table1.md is a folder, where a file goes: move the folder, or give another --out"),
])
def test_a_table_output_in_the_way_is_one_line(out, problem, tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    (tmp_path / "tables" / "table1.md").mkdir(parents=True)
    assert tables_main([str(_results(tmp_path, "1.0")), "--metrics", "Error(R)", "--out", str(tmp_path / out)]) == 2
    assert _error_lines(capsys) == [f"error: --out {tmp_path / out}: {problem.format(tmp=tmp_path)}"]
    assert not (tmp_path / "tables" / "table1.tex").exists()


def test_a_run_folder_under_a_file_is_one_line(tmp_path, cache, capsys, caplog):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(SystemExit) as info:
        src.train.main.__wrapped__(compose_config(*TINY, cache, f"output_dir={tmp_path / 'notes.txt' / 'run'}"))
    assert info.value.code == 2
    assert _error_lines(capsys) == [
        f"error: writing the run folder: {tmp_path}/notes.txt/run or a folder above it is a file, not a folder: move the "
        "file, or write elsewhere (OMNET_CACHE_DIR / --cache-root for caches, hydra.run.dir or output_dir for runs)"]
    assert "failure.json not written" not in caplog.text  # was a second line, logged before it, of the same cause


def test_a_folder_where_a_run_file_goes_is_one_line(tmp_path, cache, capsys):
    (tmp_path / "config_resolved.yaml").mkdir()  # was: IsADirectoryError traceback (after a whole test for metrics.json)
    with pytest.raises(SystemExit) as info:
        src.train.main.__wrapped__(compose_config(*TINY, cache, f"output_dir={tmp_path}"))
    assert info.value.code == 2
    assert _error_lines(capsys) == [
        f"error: writing config_resolved.yaml: {tmp_path}/config_resolved.yaml is a folder, where a file goes: move the "
        "folder, or write elsewhere (hydra.run.dir or output_dir for runs)"]


# --- 6: option types -------------------------------------------------------------------------------


@pytest.mark.parametrize("override, message", [
    ("trainer.devices=1.5", "trainer.devices=1.5 is invalid: it must be a list of integers, a string or an integer"),
    ("trainer.enable_progress_bar=abc", "trainer.enable_progress_bar='abc' is invalid: it must be true or false (or null)"),
    ("+trainer.min_steps=2.5", "trainer.min_steps=2.5 is invalid: it must be an integer (or null)"),  # ran, truncated
    ("trainer.deterministic=abc", "trainer.deterministic='abc' is invalid: it must be true or false or warn (or null)"),
    ("callbacks.lr_monitor.logging_interval=hour",
     "callbacks.lr_monitor.logging_interval='hour' is invalid: it must be one of step, epoch (or null)"),
    ("logger.csv.version=1.5", "logger.csv.version=1.5 is invalid: it must be an integer or a string (or null)"),
    ("trainer.precision=abc", "trainer.precision='abc' is invalid: it must be one of 64, 32, 16, transformer-engine, "
                              "transformer-engine-float16, 16-true, 16-mixed, bf16-true, bf16-mixed, 32-true, 64-true, "
                              "bf16, auto (or null)"),  # a ValueError traceback from Lightning
    ("trainer.max_steps=10.5", "trainer.max_steps=10.5 is invalid: it must be an integer >= 1 (or -1: no limit)"),
    ("data.batch_size=2.5", "data.batch_size=2.5 is invalid: it must be an integer >= 1 (or null)"),
])
def test_an_option_of_the_wrong_type_names_the_type_it_takes(override, message):
    with pytest.raises(ConfigError) as info:
        validate_config(compose_config(override))
    assert str(info.value) == message


def test_options_of_the_types_their_constructors_take_pass():
    for fine in ("trainer.precision=auto", "trainer.precision=32", "trainer.devices=auto", "trainer.devices=[0]", "trainer.deterministic=warn", "trainer.fast_dev_run=2",
                 "+trainer.max_time={minutes: 5}", "+trainer.max_time=00:01:00:00", "callbacks.checkpoint.save_last=link",
                 "callbacks.clock.budget_cpu_hours=1"):
        validate_config(compose_config(fine))


# --- 7: clouds beyond the memory --------------------------------------------------------------------


def test_clouds_beyond_the_memory_are_refused_before_training_with_the_point_budget(tmp_path, cache, monkeypatch):
    available = 48 * 2**20
    monkeypatch.setattr(memory, "available_bytes", lambda device: available)  # (was: "can't allocate memory" traceback)
    with pytest.raises(ConfigError) as info:
        train(_tiny(cache, tmp_path, "partial=none", "trainer.max_steps=1"))  # whole clouds of 2,048 points
    assert str(info.value) == (
        "OMNet cannot hold a training batch in memory: 2 pairs of 2048 and 2048 points need at least 68 MiB ((B, N, "
        "M) pairwise matrices and per-point activations), more than the 48 MiB available on cpu; its point budget "
        "there is at most 1617 points per cloud at data.batch_size=2: use fewer points per cloud "
        "(data.pair.num_points), or a smaller data.batch_size")
    assert not (tmp_path / "run" / "checkpoints").exists()
    network = OMNet(width=0.0625)  # the budget is the most points that fit
    assert memory.step_bytes(network, "train", 2, 1617, 1617) <= available < memory.step_bytes(network, "train", 2, 1618, 1618)


# --- 8: which weights a result comes from ------------------------------------------------------------

SELECTED = r"{run}/checkpoints/best-(\d+)\.ckpt \(step \1\), selected on val/score \(min\), of (\d+) steps trained"


@pytest.mark.parametrize("override, weights", [
    ("trainer.max_steps=2", r"the last weights, step 2 \(no validation ran, so val/score selected no checkpoint\)"),
    ("+trainer.max_time={seconds: 1}", SELECTED + r"; training stopped at step \2 of trainer.max_steps=260000 "
                                                  r"\(trainer.max_time reached after \d+ s of training\)"),
    ("callbacks.clock.budget_cpu_hours=0.0001", SELECTED + r"; training stopped at step \2 of trainer.max_steps=260000 "
                                                           r"\(callbacks.clock.budget_cpu_hours=0.0001 reached\)"),
])
def test_a_result_names_its_weights_and_where_training_stopped(override, weights, tmp_path, cache, capsys):
    train(_tiny(cache, tmp_path, override, "trainer.limit_val_batches=1", "trainer.limit_test_batches=1"))
    run = tmp_path / "run"
    printed = [line.removeprefix("weights: ") for line in capsys.readouterr().out.splitlines() if line.startswith("weights: ")]
    recorded = json.loads((run / "metrics.json").read_text())["tested_weights"]
    assert printed == [recorded] and re.fullmatch(weights.format(run=re.escape(str(run))), recorded), recorded


def test_an_evaluated_checkpoint_is_named_with_its_step():
    assert checkpoint_weights(str(SHIPPED), read_checkpoint(SHIPPED)) == f"{SHIPPED} (step 2200)"  # from its card
    assert checkpoint_weights("run/last.ckpt", {"global_step": 16}) == "run/last.ckpt (step 16)"
    assert checkpoint_weights("elsewhere.ckpt", {}) == "elsewhere.ckpt (its training step is not recorded)"
