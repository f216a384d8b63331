"""Registration methods behind one interface, and a parallel runner for evaluating them.

>>> from baselines import get_registrator, run_pairs
>>> icp = get_registrator("icp", max_iterations=30)
>>> T = icp.register(src, ref)                     # (4, 4), ref ≈ T[:3, :3] @ src + T[:3, 3]
>>> result = icp.register_result(src, ref)         # T, seconds, failed/timed_out/reason, fitness, inlier_rmse
>>> results = run_pairs(icp, pairs, workers=2, timeout_s=60)    # one RegistrationResult per pair

The methods and their facts: :mod:`baselines.methods`.
"""

from baselines.base import Registrator, RegistratorConfig
from baselines.methods import METHODS, Method
from baselines.registry import available_registrators, get_registrator, register_registrator, resolve_registrator
from baselines.result import RegistrationResult, transform_problem
from baselines.runner import run_pairs
from src.geometry.clouds import check_batch, check_cloud

__all__ = [
    "METHODS", "Method", "RegistrationResult", "Registrator", "RegistratorConfig", "available_registrators",
    "check_batch", "check_cloud", "get_registrator", "register_registrator", "resolve_registrator", "run_pairs",
    "transform_problem",
]
