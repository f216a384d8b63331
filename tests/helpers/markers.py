"""Why a test is skipped by the markers of pyproject.toml (applied by tests/conftest.py at collection).

- ``slow``: skipped unless pytest runs with ``--run-slow``;
- ``shared_data("data/<file>", ...)``: skipped when one of the named files or folders of the shared
  folder (:func:`src.utils.paths.shared_path`: ``../shared``, or ``$OMNET_SHARED_DIR``) is absent;
- ``goicp``: skipped when the optional Go-ICP extension cannot be imported.
"""

from pathlib import Path

import pytest

from src.utils.paths import shared_dir, shared_path

GOICP_MISSING = "optional Go-ICP extension not installed: run baselines/classical/install_goicp.sh"


def missing_shared_files(marker: pytest.Mark) -> list[str]:
    """The files a ``shared_data`` marker names (relative to the shared folder) that are absent."""
    if not marker.args:
        raise pytest.UsageError("@pytest.mark.shared_data needs the shared file(s) it reads, e.g. 'data/<file>.zip'")
    return [name for name in marker.args if not shared_path(*Path(name).parts).exists()]


def skip_reason(item: pytest.Item, run_slow: bool, has_goicp: bool) -> str | None:
    """Why ``item`` is skipped by its markers, or None."""
    if item.get_closest_marker("slow") is not None and not run_slow:
        return "slow: run with --run-slow"
    missing = [name for marker in item.iter_markers("shared_data") for name in missing_shared_files(marker)]
    if missing:
        return f"shared data absent: {', '.join(missing)} not in {shared_dir()} (../shared or $OMNET_SHARED_DIR)"
    if item.get_closest_marker("goicp") is not None and not has_goicp:
        return GOICP_MISSING
    return None
