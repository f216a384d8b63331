"""The markers of pyproject.toml and their one place of skipping (tests/conftest.py, tests/helpers/markers.py):
``slow`` without ``--run-slow``, ``shared_data`` where a named shared file is absent, ``goicp`` without Go-ICP."""

from __future__ import annotations

import pytest

from tests.helpers.markers import GOICP_MISSING, skip_reason


class Marked:
    """Just enough of a pytest item for :func:`skip_reason`: its markers."""

    def __init__(self, *decorators: pytest.MarkDecorator):
        self.marks = [d.mark for d in decorators]

    def iter_markers(self, name: str):
        return (m for m in self.marks if m.name == name)

    def get_closest_marker(self, name: str):
        return next(self.iter_markers(name), None)


@pytest.fixture
def shared(tmp_path, monkeypatch):
    """An empty shared folder ($OMNET_SHARED_DIR) holding only data/here.zip."""
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "here.zip").write_bytes(b"")
    monkeypatch.setenv("OMNET_SHARED_DIR", str(tmp_path))
    return tmp_path


def test_slow_runs_only_with_run_slow():
    item = Marked(pytest.mark.slow)
    assert skip_reason(item, run_slow=False, has_goicp=True) == "slow: run with --run-slow"
    assert skip_reason(item, run_slow=True, has_goicp=True) is None


def test_shared_data_names_each_absent_file(shared):
    assert skip_reason(Marked(pytest.mark.shared_data("data/here.zip")), run_slow=False, has_goicp=False) is None
    item = Marked(pytest.mark.shared_data("data/here.zip", "data/gone.zip"), pytest.mark.shared_data("weights/w.t7"))
    reason = skip_reason(item, run_slow=False, has_goicp=True)
    assert reason == f"shared data absent: data/gone.zip, weights/w.t7 not in {shared} (../shared or $OMNET_SHARED_DIR)"


def test_shared_data_needs_the_files_it_reads():
    with pytest.raises(pytest.UsageError, match="needs the shared file"):
        skip_reason(Marked(pytest.mark.shared_data), run_slow=False, has_goicp=True)


def test_goicp_skips_without_the_extension():
    assert skip_reason(Marked(pytest.mark.goicp), run_slow=False, has_goicp=False) == GOICP_MISSING
    assert skip_reason(Marked(pytest.mark.goicp), run_slow=False, has_goicp=True) is None
    assert skip_reason(Marked(), run_slow=False, has_goicp=False) is None


def test_run_slow_is_an_option(pytestconfig):
    assert pytestconfig.getoption("--run-slow") in (False, True)


@pytest.mark.shared_data("no/such/file.zip")
def test_the_conftest_skips_a_marked_test_before_it_runs():
    pytest.fail("a shared_data test whose file is absent ran: tests/conftest.py did not skip it")
