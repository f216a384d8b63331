"""One schema check of a composed config: types, ranges and choices of the data and model fields.

:func:`validate_config` runs before a job touches anything (``src.train`` and ``src.eval`` through
:func:`src.run.failures.record_failures`, ``benchmarks.grid`` for each experiment it composes), so a
value such as ``data.pair.noise_sigma=-1`` or ``data.batch_size=abc`` stops with one
:class:`~src.utils.errors.ConfigError` line naming the key, the rule and the value, instead of running
with a silently different setting or failing deep inside with a traceback.

:data:`RULES` is the one table: dotted key -> :class:`Rule`. A rule applies when its key is in the
config (the network keys only for the networks that have them). A key without a rule, of a node that builds an
object, must have the type the constructor's annotation names (``trainer.devices=1.5``, ``trainer.precision=abc``:
:func:`_check_options`); other keys (per-model ``recipe`` blocks), interpolations and values computed at
instantiation (a node with a ``_target_``) are not this module's business and pass. A top-level key that no config file of the
application has (``+trainer_max_steps=5``, ``+foo=1``) is refused (:func:`check_top_level_keys`): nothing
reads it. (A ``data.pair.num_points`` that a cache layout cannot honour is refused once the cache is open:
:func:`src.data.datamodule.check_pair_layout`.)
"""

from __future__ import annotations

import collections.abc
import difflib
import functools
import inspect
import math
import os
import types
import typing
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from src.data.transforms import NORMALS, PARTIAL_MANNERS, PERTURBATIONS, SAMPLINGS
from src.utils.config_values import plain
from src.utils.errors import ConfigError, user_error_behind
from src.geometry.clouds import MIN_POINTS
from src.utils.paths import REPO_ROOT

CONF_DIR = REPO_ROOT / "conf"


@dataclass(frozen=True)
class Rule:
    """What a value must be: an ``int``/``float``/``bool`` within optional bounds (``low_open`` /
    ``high_open``: strict), one of ``choices``, a non-empty path (``str``), or a list of such values (``each``)."""

    kind: type = float
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[str, ...] = ()
    nullable: bool = False
    each: bool = False
    sentinel: int | None = None
    """A value accepted besides the bounds, e.g. ``-1`` (no limit) for ``trainer.max_steps``."""

    def describe(self) -> str:
        if self.choices:
            text = f"one of {', '.join(self.choices)}"
        elif self.kind is str:
            text = "a non-empty path"
        elif self.kind is bool:
            text = "true or false"
        else:
            text = "an integer" if self.kind is int else "a number"
            show = (lambda x: str(int(x))) if self.kind is int else (lambda x: f"{x:g}")
            if self.low is not None and self.high is not None:
                text += f" in {'(' if self.low_open else '['}{show(self.low)}, {show(self.high)}{')' if self.high_open else ']'}"
            elif self.low is not None:
                text += f" {'>' if self.low_open else '>='} {show(self.low)}"
        if self.each:
            text = f"a list of {text.replace('an integer', 'integers').replace('a number', 'numbers')}"
        if self.sentinel is not None:
            text += f" (or {self.sentinel}: no limit)"
        return text + (" (or null)" if self.nullable else "")

    def accepts(self, value: Any) -> bool:
        if value is None:
            return self.nullable
        if self.each:
            return isinstance(value, (list, tuple)) and all(self._accepts_one(v) for v in value)
        return self._accepts_one(value)

    def _accepts_one(self, value: Any) -> bool:
        if self.sentinel is not None and value == self.sentinel and not isinstance(value, bool):
            return True
        if self.choices:
            return isinstance(value, str) and value in self.choices
        if self.kind is str:
            return isinstance(value, str) and bool(value.strip())
        if self.kind is bool or isinstance(value, bool):
            return self.kind is bool and isinstance(value, bool)
        if not isinstance(value, (int, float)) or (self.kind is int and not isinstance(value, int)):
            return False
        if not math.isfinite(value):
            return False
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or (value < self.high if self.high_open else value <= self.high)


def integer(low: int | None = None, nullable: bool = False, sentinel: int | None = None) -> Rule:
    return Rule(int, low, nullable=nullable, sentinel=sentinel)


def number(low: float | None = None, high: float | None = None, low_open: bool = False, high_open: bool = False,
           nullable: bool = False) -> Rule:
    return Rule(float, low, high, low_open, high_open, nullable=nullable)


POSITIVE = number(0.0, low_open=True)
SEED = Rule(int, 0, 2**32 - 1)  # what NumPy and Lightning accept
NON_NEGATIVE = number(0.0)
FRACTION = number(0.0, 1.0, low_open=True)  # (0, 1]
FLAG = Rule(bool)
PATH = Rule(str, nullable=True)  # a file; empty (``ckpt_path=``) is no path: null is "none"

_NETWORK_COUNTS = ("num_iters", "num_train_iters", "num_sk_iter", "max_iter", "n_blocks", "n_heads", "k", "emb_dims",
                   "ff_dims", "d_model", "n_clusters", "dim_k", "feat_dim", "num_neighbors", "normals_k",
                   "num_keypoints", "topk", "decoder_points", "keep_divisor", "eval_max_iter",
                   "num_random_points")
_NETWORK_SCALES = ("width", "overlap_dist", "radius", "match_dist", "delta", "xtol", "temp_factor")
_NETWORK_WEIGHTS = ("rot_loss_weight", "trans_loss_weight", "cycle_weight", "feature_alignment_weight", "chamfer_weight",
                    "transform_weight", "feature_loss_weight", "inlier_weight")
_NETWORK_FLAGS = ("share_weights", "mask_module", "mask_loss", "fusion", "connection", "cycle", "pointer", "learn_delta",
                  "deterministic_eval", "use_rri", "exact_procrustes", "slack")

#: The one table of rules (checked in this order: the choices that other values interpolate come first).
RULES: dict[str, Rule] = {
    "sampling": Rule(str, choices=SAMPLINGS),
    "partial": Rule(str, choices=PARTIAL_MANNERS),
    "seed": SEED,
    "model_scale": POSITIVE,
    "test_after_fit": FLAG,
    "force_precision": FLAG,
    "ckpt_path": PATH,
    "init_weights": PATH,
    "weights": PATH,
    # data (conf/data/base.yaml)
    "data.pair.sampling": Rule(str, choices=SAMPLINGS),
    "data.pair.partial": Rule(str, choices=PARTIAL_MANNERS),
    "data.pair.num_points": integer(MIN_POINTS),
    "data.pair.rot_mag": number(0.0, 180.0),
    "data.pair.trans_mag": NON_NEGATIVE,
    "data.pair.noise_sigma": NON_NEGATIVE,
    "data.pair.noise_clip": POSITIVE,
    "data.pair.prnet_num_keep": integer(MIN_POINTS),
    "data.pair.rpmnet_p_keep": FRACTION,
    "data.pair.rpmnet_num_points": integer(MIN_POINTS),
    "data.pair.rpmnet_resample_points": integer(MIN_POINTS, nullable=True),
    "data.pair.overlap_ratio": number(0.0, 1.0, low_open=True, nullable=True),
    "data.pair.perturbation": Rule(str, choices=PERTURBATIONS),
    "data.pair.twist_mag": NON_NEGATIVE,
    "data.pair.twist_random_mag": FLAG,
    "data.pair.unit_cube": FLAG,
    "data.normals": Rule(str, choices=NORMALS),
    "data.remove_axisymmetric": FLAG,
    "data.batch_size": integer(1, nullable=True),  # null: a test-only data config (src.train refuses it)
    "data.eval_batch_size": integer(1),
    "data.num_workers": integer(0),
    "data.pin_memory": FLAG,
    "data.persistent_workers": FLAG,
    "data.seed": SEED,
    "data.build.num_train_per_category": integer(1),
    "data.build.num_test_per_category": integer(1),
    "data.build.num_samplings": integer(1),
    "data.build.num_points": integer(MIN_POINTS),
    "data.build.seed": SEED,
    "data.build.normals": FLAG,
    # trainer and callbacks (conf/trainer/*.yaml, conf/callbacks/default.yaml): zero or negative budgets and
    # intervals train nothing, never validate or checkpoint, or fail deep inside Lightning
    "trainer.max_steps": integer(1, sentinel=-1),
    "trainer.max_epochs": integer(1, nullable=True, sentinel=-1),
    "trainer.val_check_interval": number(0.0, low_open=True, nullable=True),
    "trainer.check_val_every_n_epoch": integer(1, nullable=True),
    "trainer.log_every_n_steps": integer(1),
    "trainer.accumulate_grad_batches": integer(1),
    "trainer.limit_train_batches": number(0.0, low_open=True, nullable=True),  # null: every batch (Lightning's default)
    "trainer.limit_val_batches": number(0.0, nullable=True),
    "trainer.limit_test_batches": number(0.0, low_open=True, nullable=True),
    "trainer.gradient_clip_val": number(0.0, nullable=True),
    "trainer.num_sanity_val_steps": integer(-1),
    **{f"callbacks.periodic_checkpoint.train_time_interval.{unit}": POSITIVE for unit in ("seconds", "minutes", "hours")},
    "callbacks.periodic_checkpoint.every_n_train_steps": integer(1, nullable=True),
    "callbacks.checkpoint.every_n_train_steps": integer(1, nullable=True),
    "callbacks.checkpoint.save_top_k": integer(-1),
    "callbacks.checkpoint.mode": Rule(str, choices=("min", "max")),
    # model (conf/model/*.yaml, conf/recipe/*.yaml): the RegistrationModule, then network fields by name
    "model.lr": POSITIVE,
    "model.weight_decay": NON_NEGATIVE,
    "model.lr_milestones": Rule(int, 0, each=True),
    "model.lr_gamma": POSITIVE,
    "model.scheduler.milestones": Rule(int, 0, each=True),
    "model.scheduler.gamma": POSITIVE,
    "model.scheduler.factor": number(0.0, 1.0, low_open=True, high_open=True),
    "model.scheduler.patience": integer(0),
    "model.scheduler.min_lr": NON_NEGATIVE,
    "model.scheduler.warmup_steps": integer(0),
    "model.scheduler.pct_start": number(0.0, 1.0, low_open=True, high_open=True),
    "model.scheduler.div_factor": POSITIVE,
    "model.scheduler.final_div_factor": POSITIVE,
    "model.compile": FLAG,
    **{f"model.network.{name}": integer(1) for name in _NETWORK_COUNTS},
    "model.network.mask_start_iter": integer(0),
    **{f"model.network.{name}": POSITIVE for name in _NETWORK_SCALES},
    **{f"model.network.{name}": NON_NEGATIVE for name in _NETWORK_WEIGHTS},
    **{f"model.network.{name}": FLAG for name in _NETWORK_FLAGS},
    "model.network.mask_class_weights": Rule(float, 0.0, each=True),
    "model.network.dropout": number(0.0, 1.0, high_open=True),
    "model.network.discount": FRACTION,
}

_ABSENT = object()


def _value(cfg: DictConfig, key: str) -> Any:
    """The resolved value at ``key`` (``_ABSENT`` if there is none); a value whose interpolation fails
    raises the UserError behind it, or a ConfigError naming the key."""
    try:
        value = OmegaConf.select(cfg, key, default=_ABSENT, throw_on_missing=False)
    except Exception as err:  # noqa: BLE001 - OmegaConf wraps resolver errors in its own types
        user_error = user_error_behind(err)
        if user_error is not None:
            raise user_error from None
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise ConfigError(f"{key} cannot be resolved: {first}") from None
    return plain(value)


def validate_config(cfg: DictConfig) -> None:
    """Raise ConfigError for a top-level key of ``cfg`` (``conf/config.yaml``) that no config file has,
    then for the first value that breaks its rule in :data:`RULES`, then for the first key of an
    object's node (``_target_``) that its class or function does not take."""
    check_top_level_keys(cfg, "config")
    _check_rules(cfg, RULES)
    for path, node in _object_nodes(cfg):
        _check_options(cfg, path, node)
    _check_precision(cfg)


def _check_rules(cfg: DictConfig, rules: Mapping[str, Rule]) -> None:
    """ConfigError for the first value of ``cfg`` that breaks its rule in ``rules``."""
    for key, rule in rules.items():
        value = _value(cfg, key)
        if value is _ABSENT or (isinstance(value, dict) and "_target_" in value):
            continue
        if not rule.accepts(value):
            raise ConfigError(f"{key}={_show(value)} is invalid: it must be {rule.describe()}")


#: The grid's own keys (``conf/benchmark/*.yaml``).
GRID_RULES: dict[str, Rule] = {
    "workers": integer(0, nullable=True),
    "timeout_s": number(0.0, low_open=True, nullable=True),
    "pairs_per_call": integer(1),
    "save_every_s": number(0.0, low_open=True, nullable=True),
    "benchmark.max_pairs": integer(1, nullable=True),
    "progress": FLAG,
    "paper": FLAG,
}


def validate_grid_config(cfg: DictConfig) -> None:
    """ConfigError for a top-level key no grid config has, a value of the grid's own keys that breaks its rule in
    :data:`GRID_RULES`, or a per-method pair limit (``benchmark.max_pairs_by_method``) that is no count >= 1."""
    check_top_level_keys(cfg, "benchmark_grid")
    _check_rules(cfg, GRID_RULES)
    limits = _value(cfg, "benchmark.max_pairs_by_method")
    for method, limit in (limits.items() if isinstance(limits, dict) else ()):
        if not integer(1).accepts(limit):
            raise ConfigError(f"benchmark.max_pairs_by_method.{method}={_show(limit)} is invalid: it must be "
                              f"{integer(1).describe()}")


#: The config groups of each application's primary config that are not its top-level keys themselves.
_OTHER_APPS_GROUPS = {"config": ("benchmark", "hydra"), "benchmark_grid": ()}


def _is_global(path: Path) -> bool:
    """Whether a config file's keys are top-level keys (``# @package _global_``, or a primary config)."""
    return path.parent == CONF_DIR or "@package _global_" in path.read_text().split("\n", 1)[0]


@functools.cache
def top_level_keys(app: str) -> tuple[str, ...]:
    """Every top-level key that a config of ``app`` can have, read from ``conf/``: ``config`` (``src.train``,
    ``src.eval``: ``conf/config.yaml``, its groups and the ``@package _global_`` files of experiments,
    sweeps and recipes) or ``benchmark_grid`` (``benchmarks.grid``: ``conf/benchmark/*.yaml``)."""
    if app == "benchmark_grid":  # its grid files, and the data configs it composes (a `_global_` one sets sampling)
        files = sorted((CONF_DIR / "benchmark").glob("*.yaml")) + sorted((CONF_DIR / "data").glob("*.yaml"))
        keys = {"benchmark", "method_options", "data", "hydra"}
    else:
        files = [CONF_DIR / "config.yaml"] + sorted(
            p for p in CONF_DIR.glob("*/**/*.yaml") if p.relative_to(CONF_DIR).parts[0] not in _OTHER_APPS_GROUPS[app])
        keys = {"hydra"}
    for path in files:
        if _is_global(path):
            keys |= {str(k) for k in OmegaConf.load(path).keys() if k != "defaults"}
        else:
            keys.add(path.relative_to(CONF_DIR).parts[0])  # a group's package: its folder's name
    return tuple(sorted(keys))


def check_top_level_keys(cfg: DictConfig, app: str) -> None:
    """ConfigError for a top-level key of ``cfg`` that no config file of ``app`` has (added with ``+``:
    nothing reads it, e.g. ``+trainer_max_steps=5``), naming the close matches and the valid keys."""
    known = top_level_keys(app)
    unknown = [str(k) for k in cfg.keys() if str(k) not in known]
    if not unknown:
        return
    key = unknown[0]
    dotted = [f"{k}.{key[len(k) + 1:]}" for k in known if key.startswith(f"{k}_")]  # trainer_max_steps
    close = dotted or difflib.get_close_matches(key, known, n=3, cutoff=0.5)
    hint = f"did you mean {', '.join(close)}? " if close else ""
    raise ConfigError(f"{key} is not a top-level config key (nothing reads it): {hint}the top-level keys are "
                      f"{', '.join(known)}")


#: Precisions Lightning silently replaces on the CPU (by bf16-mixed: there is no fp16 autocast there).
_FP16 = ("16", "16-mixed")


def _check_precision(cfg: DictConfig) -> None:
    """ConfigError for an fp16 precision on the CPU, which Lightning would replace by bf16-mixed."""
    precision, accelerator = str(_value(cfg, "trainer.precision")), _value(cfg, "trainer.accelerator")
    on_cpu = accelerator == "cpu" or (accelerator in ("auto", _ABSENT) and not torch.cuda.is_available())
    if precision in _FP16 and on_cpu:
        raise ConfigError(f"trainer.precision={precision} on the CPU: Lightning would run bf16-mixed instead (no fp16 "
                          "autocast on the CPU): use 32-true or bf16-mixed, or a GPU")


def _object_nodes(node: Any, path: str = "") -> Iterator[tuple[str, DictConfig]]:
    """Every node below ``node`` that builds an object (has a ``_target_``), with its dotted path."""
    if not isinstance(node, DictConfig):
        return
    if "_target_" in node:
        yield path, node
    for key in node.keys():
        child = node._get_node(key)
        if isinstance(child, DictConfig) and not child._is_missing() and not child._is_interpolation():
            yield from _object_nodes(child, f"{path}.{key}" if path else str(key))


#: The keys Hydra's instantiation reads itself (any other key, ``_foo`` included, goes to the constructor).
_HYDRA_KEYS = ("_target_", "_recursive_", "_convert_", "_partial_", "_args_")


#: Values settled before their object is built, taken besides its type: ``trainer.precision=auto`` (:mod:`src.run.precision`).
_SETTLED_BEFORE_BUILD: dict[str, Any] = {"trainer.precision": typing.Literal["auto"]}


def _check_options(cfg: DictConfig, path: str, node: DictConfig) -> None:
    """ConfigError for a key of ``node`` that its ``_target_`` does not take (e.g. ``+trainer.max_step=5``,
    or ``+data.foo=1``, which would fail deep inside the constructor or be silently dropped), then for a value
    whose type the parameter's annotation rules out (``trainer.devices=1.5``, ``trainer.enable_progress_bar=abc``,
    ``+trainer.min_steps=2.5``: a traceback, or run as something else); a key of :data:`RULES` is its rule's."""
    try:
        target = hydra.utils.get_object(str(node._get_node("_target_")._value()))
        parameters = inspect.signature(target).parameters.values()
    except Exception:  # noqa: BLE001 - an unknown target or a builtin: instantiation reports it
        return
    if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters):
        takes = [p.name for p in parameters if p.kind is not inspect.Parameter.VAR_POSITIONAL]
        unknown = [str(k) for k in node.keys() if str(k) not in _HYDRA_KEYS and str(k) not in takes]
        if unknown:
            key = unknown[0]
            close = difflib.get_close_matches(key, takes, n=3)
            hint = f"did you mean {', '.join(close)}?" if close else f"it takes {', '.join(takes)}"
            where = f"{path}.{key}" if path else key
            raise ConfigError(f"{where} is not an option of {node._get_node('_target_')._value()}: {hint}")
    hints = _parameter_types(target)
    for key in map(str, node.keys()):
        where = f"{path}.{key}" if path else key
        if key not in hints or where in RULES or node._get_node(key)._is_interpolation():
            continue  # (an interpolation, e.g. ${output_dir}/checkpoints: what it names is checked where it is set)
        hint = typing.Union[hints[key], _SETTLED_BEFORE_BUILD[where]] if where in _SETTLED_BEFORE_BUILD else hints[key]
        value = _value(cfg, where)
        if not (isinstance(value, dict) and "_target_" in value) and not _fits(value, hint):
            raise ConfigError(f"{where}={_show(value)} is invalid: it must be {_describe_type(hint)}")


@functools.cache
def _parameter_types(target: Any) -> dict[str, Any]:
    """The annotated types of the parameters of ``target`` (a class: its ``__init__``); none if they cannot be read."""
    try:
        return typing.get_type_hints(target.__init__ if inspect.isclass(target) else target)
    except Exception:  # noqa: BLE001 - an annotation naming what its module does not import: nothing to check
        return {}


_LISTS = (list, tuple, collections.abc.Sequence, collections.abc.Iterable, collections.abc.Collection)
_MAPPINGS = (dict, collections.abc.Mapping)
_PATHS = (Path, PurePath, os.PathLike)
_WORDS = {bool: ("true or false", "true/false values"), int: ("an integer", "integers"), float: ("a number", "numbers"),
          str: ("a string", "strings")}


def _fits(value: Any, hint: Any) -> bool:
    """Whether a config value (plain: None, bool, int, float, str, list, dict) can be of type ``hint``; True for a
    type no config value is written as (a class, ``Any``, a callable): its constructor judges it."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, arg) for arg in args)
    if origin is typing.Literal:
        return any(type(value) is type(choice) and value == choice for choice in args)
    if hint is type(None):
        return value is None
    if hint in _WORDS:  # (bool is an int in Python, an integer in a config is no float and no flag)
        exact = isinstance(value, hint) and (hint is bool or not isinstance(value, bool))
        return exact or (hint is float and isinstance(value, int) and not isinstance(value, bool))
    if hint in _PATHS:
        return isinstance(value, str)
    container = origin or hint
    if container in _LISTS:
        if not isinstance(value, list):
            return False
        each = [a for a in args if a is not Ellipsis]
        kinds = each if container is tuple and len(each) > 1 else each[:1] * len(value)
        return all(_fits(v, t) for v, t in zip(value, kinds))
    if container in _MAPPINGS:
        return isinstance(value, dict)
    return True


def _describe_type(hint: Any) -> str:
    """``hint`` in words: ``a list of integers, a string or an integer``, ``true or false (or null)``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        choices = list(dict.fromkeys(str(c) for a in args if typing.get_origin(a) is typing.Literal
                                     for c in typing.get_args(a)))  # (32 and '32' alike)
        parts = [_describe_type(a) for a in args if a is not type(None) and typing.get_origin(a) is not typing.Literal]
        parts += [_describe_type(typing.Literal[tuple(choices)])] if choices else []
        text = ", ".join(parts[:-1]) + f" or {parts[-1]}" if len(parts) > 1 else parts[0]
        return text + (" (or null)" if type(None) in args else "")
    if origin is typing.Literal:
        return f"one of {', '.join(map(str, args))}" if len(args) > 1 else str(args[0])
    if hint in _WORDS:
        return _WORDS[hint][0]
    if hint in _PATHS:
        return "a path"
    if (origin or hint) in _MAPPINGS:
        return "a mapping"
    if (origin or hint) in _LISTS:
        each = [a for a in args if a is not Ellipsis]
        return f"a list of {_WORDS[each[0]][1]}" if len(set(each)) == 1 and each[0] in _WORDS else "a list"
    return f"a {getattr(hint, '__name__', hint)}"


def _show(value: Any) -> str:
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, Sequence):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    return str(value).lower() if isinstance(value, bool) or value is None else str(value)
