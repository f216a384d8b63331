"""tests.helpers.markdown: the pipe tables of a report, read back as frames of their cells."""

import pytest

from tests.helpers.markdown import markdown_table, markdown_tables

REPORT = """# A report

**Speed — CPU: test**

| # points | toy | OMNet† |
|---:|---:|---:|
| 32 | 1.5 | 12 |
| 64 | 3.0 | - |

- a note

| Method | OS |
|---|---|
| ICP | **2.000** |
"""


def test_each_table_is_a_frame_of_its_cells_under_its_title():
    (title, speed), (note, methods) = markdown_tables(REPORT)
    assert title == "Speed — CPU: test" and note == "- a note"
    assert speed.columns.tolist() == ["# points", "toy", "OMNet†"]
    assert speed.values.tolist() == [["32", "1.5", "12"], ["64", "3.0", "-"]]
    assert methods.to_dict("records") == [{"Method": "ICP", "OS": "**2.000**"}]


def test_one_table_by_its_title():
    assert markdown_table(REPORT, "Speed")[1].shape == (2, 3)
    with pytest.raises(AssertionError, match="0 tables titled 'Throughput'"):
        markdown_table(REPORT, "Throughput")
