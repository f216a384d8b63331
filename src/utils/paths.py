"""Where the repository and the read-only shared folder are, for every module and test.

The shared folder (the paper, its tables, real data, published weights) lies at ``../shared`` beside
the repository root, on every machine and in CI; ``$OMNET_SHARED_DIR`` points elsewhere.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
#: The Hydra configs (``conf/config.yaml`` and its groups).
CONF_DIR = REPO_ROOT / "conf"
#: Shipped checkpoints (``<name>.ckpt``) and their cards (``<name>.json``).
SHIPPED_DIR = REPO_ROOT / "checkpoints"


def shipped_checkpoint_path(name: str) -> str:
    """``${shipped:<name>}``: the path of ``checkpoints/<name>.ckpt``, wherever the command runs."""
    return str(SHIPPED_DIR / f"{name}.ckpt")


def shared_dir() -> Path:
    """``$OMNET_SHARED_DIR``, else ``<repository root>/../shared``."""
    env = os.environ.get("OMNET_SHARED_DIR")
    return Path(env).expanduser() if env else REPO_ROOT.parent / "shared"


def shared_path(*parts: str) -> Path:
    """A path inside the shared folder, e.g. ``shared_path("data", "stanford")``."""
    return shared_dir().joinpath(*parts)


def without_folder(text: str, folder: Path, placeholder: str) -> str:
    """``text`` with ``folder``'s absolute path (resolved or not, longest first; the whole folder name, not the
    start of a longer one) written as ``placeholder``: a record committed to the repository names no path of the
    machine it was made on."""
    for spelling in sorted({str(folder.resolve()), str(folder.absolute())}, key=len, reverse=True):
        text = re.sub(re.escape(spelling) + r"(?![\w.-])", lambda _: placeholder, text)
    return text


def with_folder(text: str, folder: Path, placeholder: str) -> str:
    """The inverse of :func:`without_folder`: each ``placeholder`` that starts a path (alone, or before a ``/``)
    written as ``folder``'s absolute path."""
    return re.sub(r"(?<![\w./-])" + re.escape(placeholder) + r"(?![\w.-])", lambda _: str(folder.absolute()), text)
