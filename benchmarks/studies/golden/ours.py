"""The framework on the golden pairs: each golden method's registrator, ``(pairs, dtype) -> (P, 4, 4)``.

A learned method in float32 takes the product's own path (:meth:`Registrator.register_batch`); in float64 the
registrator's loaded network runs in double precision (the same weights and code, another dtype), each batch
after the registrator's seed as ``register_batch`` (the draws of a network that samples at test). A classical
method registers pair by pair (:meth:`Registrator.register`, float64 whatever ``dtype``), Open3D on one thread
(:func:`benchmarks.studies.golden.library.one_thread`).
"""

from __future__ import annotations

import numpy as np
import torch

from baselines import get_registrator
from benchmarks.studies.golden.authors_prnet import NOISE_SEED
from benchmarks.studies.golden.library import CALLS, one_thread

#: The classical golden methods (the library calls and CPD): computed in float64 throughout, no float32 path to compare.
CLASSICAL = (*CALLS, "cpd")
#: golden method → (method key, registrator options).
METHODS: dict[str, tuple[str, dict[str, str | int]]] = {
    "learning3d_pointnetlk": ("pointnetlk", {"weights": "official:learning3d_pointnetlk"}),
    "pointnetlk_revisited": ("pointnetlk_revisited", {"weights": "official:pointnetlk_revisited"}),
    "dcp_v1": ("dcp", {"weights": "official:dcp_v1"}),
    "omnet": ("omnet", {}),  # the shipped checkpoints
    "idam": ("idam", {}),
    "rpmnet": ("rpmnet", {}),
    "fmr": ("fmr", {}),
    "prnet": ("prnet", {"seed": NOISE_SEED}),  # the seed of its Gumbel noise, as the golden file's
    "deepgmr": ("deepgmr", {}),
    **{key: (key, {}) for key in CLASSICAL},  # their defaults
}
#: Settings whose code default (the authors' computation) differs from what a shipped checkpoint records (how it was
#: trained): its golden file holds the code's, so its weights run here with these.
CODE_SETTINGS = {"prnet": {"layer_norm": "authors"}, "deepgmr": {"rri": "authors"}}
BATCH = 8


def estimates(method: str, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """The framework's (P, 4, 4) float64 estimates of golden ``method`` on ``pairs`` in ``dtype``."""
    key, options = METHODS[method]
    registrator = get_registrator(key, **options)
    if registrator.needs_training is False:  # a classical method: float64 throughout, one pair at a time
        one_thread()
        return np.stack([registrator.register(src, ref) for src, ref in zip(pairs["src"], pairs["ref"])])
    registrator = get_registrator(key, device="cpu", batch_size=BATCH, **options)
    if method in CODE_SETTINGS:
        _with_code_settings(registrator.module, CODE_SETTINGS[method])
    if dtype == torch.float32:
        return np.concatenate([registrator.register_batch(pairs["src"][i:i + BATCH], pairs["ref"][i:i + BATCH])
                               for i in range(0, len(pairs["src"]), BATCH)])
    module = registrator.module.to(dtype)
    out = []
    with torch.no_grad():
        for i in range(0, len(pairs["src"]), BATCH):
            src, ref = (torch.from_numpy(pairs[k][i:i + BATCH]).to(dtype) for k in ("src", "ref"))
            with torch.random.fork_rng():
                torch.manual_seed(registrator.config.seed)  # as register_batch: PRNet's noise at test
                out.append(module(src, ref).double().numpy())
    return np.concatenate(out)


def _with_code_settings(module: torch.nn.Module, settings: dict[str, str]) -> None:
    """``module``'s network rebuilt from its recorded config with ``settings`` over it, its weights kept."""
    import hydra

    network = hydra.utils.instantiate({**module.hparams["network"], **settings})
    network.load_state_dict(module.network.state_dict())
    module.network = network.to(next(module.network.parameters()).device).train(module.network.training)
