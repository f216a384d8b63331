"""The precision a shipped checkpoint was trained in, as its card records it (docs/results.md: Shipped checkpoints)."""

import json

from src.models.pretrained import UNRECORDED, trained_precision
from src.utils.paths import SHIPPED_DIR


def test_every_shipped_card_records_float32_training():
    """docs/results.md says every shipped checkpoint was trained in float32; a new card must say what it was."""
    cards = {path.name: json.loads(path.read_text()) for path in SHIPPED_DIR.glob("*.json")}
    assert cards and {name: trained_precision(card) for name, card in cards.items()} == dict.fromkeys(cards, "32-true")


def test_a_card_without_its_training_precision_reads_unrecorded():
    assert trained_precision({"training": {"steps_run": 10}}) == trained_precision({}) == UNRECORDED
    assert trained_precision({"training": {"precision": "bf16-mixed"}}) == "bf16-mixed"
