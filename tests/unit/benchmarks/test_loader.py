"""benchmarks.speed.loader: pairs of an experiment's train loader per CPU-second, in this process or in workers."""

from __future__ import annotations

import pytest

from benchmarks.speed.loader import describe, main, measure
from src.utils.errors import ConfigError
from tests.helpers.registration_helpers import TINY


def _tiny(tmp_path) -> list[str]:
    return [o for o in TINY if not o.startswith(("model_scale", "trainer."))] + [f"data.cache_root={tmp_path / 'cache'}",
                                                                               "+exp=unseen_shapes"]


@pytest.mark.parametrize("workers", [0, 1])
def test_it_counts_the_pairs_of_every_batch_over_epochs_and_the_cpu_that_made_them(tmp_path, workers):
    rate = measure(_tiny(tmp_path), batches=9, workers=workers)  # 14 training shapes: 7 batches of 2 an epoch
    assert (rate.pairs, rate.workers) == (18, workers)
    assert rate.cpu_s > 0 and rate.wall_s > 0 and rate.pairs_per_cpu_s == rate.pairs / rate.cpu_s
    assert describe(rate).startswith("| 18 | ")


def test_bad_input_is_one_line(tmp_path, capsys):
    with pytest.raises(ConfigError, match="--batches must be at least 1"):
        measure(_tiny(tmp_path), batches=0)
    assert main([*_tiny(tmp_path), "data.batch_size=64", "--batches", "1"]) == 2
    assert capsys.readouterr().err.strip() == \
        "error: the train loader gives no batch (a training set smaller than data.batch_size)"
