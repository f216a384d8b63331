"""The repository's folders for the tests, wherever a test file lies under tests/."""

from pathlib import Path

#: The repository root (tests/helpers/paths.py → two levels up).
ROOT = Path(__file__).resolve().parents[2]
#: The Hydra configs.
CONF = ROOT / "conf"
#: Data files the tests compare against (tests/fixtures/).
FIXTURES = ROOT / "tests" / "fixtures"
