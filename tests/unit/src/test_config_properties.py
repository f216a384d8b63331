"""The config path's contract over generated overrides (hypothesis): an override of any key that
:data:`src.validation.RULES` checks (every group's: data, model, trainer, callbacks), given a generated value of
any type, or an unknown nested key, either composes into a config that validates and builds (the data module, and
the network on the ``meta`` device) or stops with one line (a :class:`~src.utils.errors.UserError`, or Hydra's error as
:func:`src.run.cli.describe_hydra_error` renders it); never another exception. No training, no data read.
"""

from __future__ import annotations

import functools

import hydra
import pytest
import torch
from hydra.errors import ConfigCompositionException, OverrideParseException
from hypothesis import example, given, settings
from hypothesis import strategies as st

from src.run.cli import describe_hydra_error
from src.utils.errors import user_error_behind
from src.utils.paths import CONF_DIR
from src.train import build_module
from src.validation import GRID_RULES, RULES, validate_config, validate_grid_config
from tests.helpers.registration_helpers import compose_config

#: Keys of the primary config's groups (the grid's own apart) and a few keys no rule names.
KEYS = sorted(RULES) + ["data.pair", "model.network", "trainer.precision", "callbacks.checkpoint.monitor"]
NAMES = st.text("abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=8)


def _literal(value: object) -> str:
    """``value`` as Hydra's override grammar writes it."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return {float("inf"): "inf", float("-inf"): "-inf"}.get(value, "nan" if value != value else repr(value))
    if isinstance(value, str):
        return "'" + value.replace("\\", "").replace("'", "") + "'"
    if isinstance(value, list):
        return "[" + ",".join(_literal(v) for v in value) + "]"
    return str(value)


SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-10**12, 10**12), st.floats(allow_nan=True, allow_infinity=True),
                    st.sampled_from(["abc", "", "min", "max", "ts", "prnet", "topk", "1e-3", "-1"]))
VALUES = st.one_of(SCALARS, st.lists(SCALARS, max_size=3))


@functools.cache
def _default_model_target() -> str:
    return str(compose_config().model._target_)


def _holds_the_contract(overrides: list[str], config_name: str = "config") -> None:
    try:
        cfg = compose_config(*overrides, config_name=config_name)
    except (ConfigCompositionException, OverrideParseException) as err:
        line = describe_hydra_error(err, CONF_DIR)
        assert line and "\n" not in line, line
        return
    try:
        if config_name == "config":
            validate_config(cfg)
            hydra.utils.instantiate(cfg.data)  # the constructor only: no cache is opened
            with torch.device("meta"):
                build_module(cfg.model)
        else:
            validate_grid_config(cfg)
    except Exception as err:  # noqa: BLE001 - what the entry points turn into one line (src.utils.errors.exit_code_of)
        user_error = user_error_behind(err)
        assert user_error is not None, repr(err)
        assert str(user_error) and "\n" not in str(user_error), repr(user_error)


@given(key=st.sampled_from(KEYS), value=VALUES)
@example(key="model_scale", value=605398.0)  # a network no memory holds
def test_a_generated_value_of_any_key_validates_or_is_one_line(key, value):
    _holds_the_contract([f"{key}={_literal(value)}"])


@given(group=st.sampled_from(["data", "data.pair", "data.build", "data.splits.test", "model", "model.network",
                              "trainer", "callbacks.checkpoint"]),
       names=st.lists(NAMES, min_size=1, max_size=3), value=SCALARS)
def test_an_unknown_nested_key_is_one_line(group, names, value):
    _holds_the_contract([f"+{group}.{'.'.join(names)}={_literal(value)}"])


@pytest.mark.parametrize("model", ["omnet", "dcp", "rpmnet"])
@settings(max_examples=10)
@given(key=st.sampled_from([k for k in RULES if k.startswith("model.network.")]), value=SCALARS)
def test_a_network_value_of_another_model_validates_or_is_one_line(model, key, value):
    _holds_the_contract([f"model={model}", f"{key}={_literal(value)}"])


@given(key=st.sampled_from(sorted(GRID_RULES) + ["benchmark.max_pairs_by_method.icp"]), value=VALUES)
def test_a_generated_grid_value_validates_or_is_one_line(key, value):
    from benchmarks.grid.plan import GRID_CONFIG  # (stores the grid's primary config)

    _holds_the_contract([f"++{key}={_literal(value)}"], GRID_CONFIG)
