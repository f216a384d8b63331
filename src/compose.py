"""``conf/config.yaml`` composed outside a Hydra app (in Hydra's running context when there is one): the
whole config (:func:`compose_conf`), a model's group (:func:`compose_model_config`), or an experiment checked
as the entry points check it (:func:`compose_experiment`).

Hydra and :mod:`src.validation` (torch) are imported in the functions: importing this module stays light for
the modules that import it at start-up (:mod:`baselines.learned.adapter`, the grid's worker processes).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from src.config import register_resolvers
from src.utils.errors import ConfigError
from src.utils.paths import CONF_DIR


def compose_conf(overrides: Sequence[str]) -> Any:
    """``conf/config.yaml`` composed with ``overrides`` (in Hydra's running context if there is one)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    register_resolvers()
    if GlobalHydra.instance().is_initialized():
        return compose("config", overrides=list(overrides))
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def compose_model_config(model: str, model_scale: float, overrides: Sequence[str] = ()) -> Any:
    """The ``model`` group of ``conf/`` for ``conf/model/<model>.yaml`` (a RegistrationModule config)."""
    return compose_conf([f"model={model}", f"model_scale={model_scale}", *overrides]).model


def compose_experiment(overrides: Sequence[str]) -> Any:
    """:func:`compose_conf` checked by :func:`src.validation.validate_config`; a bad override (an unknown
    experiment named with the available ones) as one :class:`~src.utils.errors.ConfigError` line."""
    from hydra.errors import HydraException

    from src.validation import validate_config

    try:
        cfg = compose_conf(overrides)
    except HydraException as err:
        experiment = next((o.split("=", 1)[1] for o in overrides if o.startswith("+exp=")), None)
        available = sorted(p.stem for p in (CONF_DIR / "exp").glob("*.yaml"))
        if experiment and "exp/" in str(err) and experiment not in available:
            raise ConfigError(f"unknown experiment '{experiment}'; available: {', '.join(available)}") from None
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"cannot compose the test set with overrides {list(overrides)}: {first}") from None
    validate_config(cfg)
    return cfg
