"""Registries kept as data: a YAML list of records read into frozen dataclasses (lists become tuples).

The method registry (``baselines/methods.yaml``) and the published weights (``baselines/learned/published.yaml``)
are read this way; a record with an unknown or missing field is one :class:`~src.utils.errors.ConfigError` line naming
the file and the record.
"""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import yaml

from src.utils.errors import ConfigError

T = TypeVar("T")


def load_records(path: Path, cls: type[T]) -> tuple[T, ...]:
    """The records of the YAML list at ``path`` as ``cls`` instances, in the file's order."""
    records = []
    for index, fields in enumerate(yaml.safe_load(path.read_text(encoding="utf-8")) or []):
        try:
            records.append(cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()}))
        except (TypeError, ValueError) as err:
            raise ConfigError(f"{path.name}, record {index + 1} ({next(iter(fields.values()), '?')}): {err}") from None
    return tuple(records)
