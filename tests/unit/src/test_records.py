"""src.utils.records: registries kept as YAML lists of dataclass records."""

from dataclasses import dataclass
from pathlib import Path

import pytest

from src.utils.errors import ConfigError
from src.utils.records import load_records


@dataclass(frozen=True)
class Item:
    name: str
    sizes: tuple[int, ...] = ()


def test_records_keep_order_and_turn_lists_into_tuples(tmp_path: Path) -> None:
    path = tmp_path / "items.yaml"
    path.write_text("- name: b\n  sizes: [1, 2]\n- name: a\n")
    assert load_records(path, Item) == (Item("b", (1, 2)), Item("a"))


@pytest.mark.parametrize("text, said", [("- name: a\n  colour: red\n", "colour"), ("- sizes: [1]\n", "name")])
def test_a_bad_record_is_one_line_naming_file_and_record(tmp_path: Path, text: str, said: str) -> None:
    path = tmp_path / "items.yaml"
    path.write_text("- name: ok\n" + text)
    with pytest.raises(ConfigError, match=rf"items\.yaml, record 2 .*{said}"):
        load_records(path, Item)
