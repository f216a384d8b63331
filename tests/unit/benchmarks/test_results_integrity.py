"""Results tables are written with a checksum in every parquet page and read verified against them: a damaged
file is one line naming it, never a table of wrong numbers (src/utils/files.py, benchmarks.tables)."""

import numpy as np
import pandas as pd
import pytest

from benchmarks.tables.render import main as tables_main
from src.utils.errors import UserError
from src.utils.files import read_parquet, write_parquet

VALUE = 12.345678901234567  # Error(R) of one cell, a value whose 8 bytes appear once in the file


@pytest.fixture
def damaged(tmp_path):
    """A tidy results table with one bit of one stored value flipped, as a failing disk or copy does."""
    frame = pd.DataFrame({"method": ["ICP", "FGR"], "experiment": ["unseen_shapes"] * 2, "sampling": ["TS"] * 2,
                          "partial": ["prnet"] * 2, "metric": ["Error(R)"] * 2, "value": [VALUE, 3.5]})
    path = tmp_path / "results.parquet"
    write_parquet(frame, path)
    data = bytearray(path.read_bytes())
    where = bytes(data).index(np.float64(VALUE).tobytes())
    data[where] ^= 1
    path.write_bytes(bytes(data))
    return path


def test_a_flipped_bit_reads_as_another_number_unless_verified(damaged):
    assert pd.read_parquet(damaged)["value"][0] != VALUE  # what the tables showed: a wrong number, silently
    with pytest.raises(UserError) as error:
        read_parquet(damaged)
    assert str(error.value) == (f"{damaged} is damaged (could not verify page integrity, CRC checksum verification "
                                "failed for page_ordinal 0): write it again with the command that made it")


def test_the_tables_command_refuses_a_damaged_table_in_one_line(damaged, capsys):
    assert tables_main([str(damaged), "--out", str(damaged.parent / "tables")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {damaged} is damaged (")
    assert not (damaged.parent / "tables").exists()


def test_an_intact_table_and_one_written_without_checksums_read_back(tmp_path):
    frame = pd.DataFrame({"value": [VALUE, np.nan]})
    write_parquet(frame, tmp_path / "a.parquet")
    frame.to_parquet(tmp_path / "b.parquet", index=False)  # an earlier version's file: no checksums to verify
    for name in ("a.parquet", "b.parquet"):
        pd.testing.assert_frame_equal(read_parquet(tmp_path / name), frame)
