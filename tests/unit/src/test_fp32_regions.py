"""model.fp32_modules: the named parts run in float32 under bf16 autocast, the rest as before."""

import copy
import pickle

import pytest
import torch
from torch import nn

from src.models.fp32_regions import fp32_module_names, keep_fp32


def _net() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Sequential(nn.Linear(8, 8), nn.Linear(8, 2)))


def test_a_kept_part_computes_in_float32_under_autocast_and_the_rest_in_bf16():
    net, x = _net(), torch.randn(5, 3)
    assert keep_fp32(net, ["2"]) == ["2"]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        hidden = net[1](net[0](x))
        out = net(x)
    assert hidden.dtype == torch.bfloat16 and out.dtype == torch.float32
    assert torch.equal(out, net[2](hidden.float()))  # the head on the bf16 features, in float32
    out.sum().backward()  # gradients flow through the region
    assert net[0].weight.grad is not None and torch.isfinite(net[0].weight.grad).all()


def test_without_autocast_nothing_changes():
    plain, kept, x = _net(), _net(), torch.randn(5, 3)
    keep_fp32(kept, ["*"])
    assert torch.equal(plain(x), kept(x))


def test_patterns_select_the_outermost_matches_and_a_pattern_matching_nothing_is_refused():
    assert fp32_module_names(_net(), ["2*"]) == ["2"]  # 2.0 and 2.1 are inside 2
    assert fp32_module_names(_net(), ["2.1", "0"]) == ["2.1", "0"]
    with pytest.raises(ValueError, match=r"'head' matches no submodule of Sequential \(its top-level modules: 0, 1, 2\)"):
        keep_fp32(_net(), ["head"])


def test_the_regions_survive_a_copy_and_pickling():
    net, x = _net(), torch.randn(5, 3)
    keep_fp32(net, ["2"])
    for other in (copy.deepcopy(net), pickle.loads(pickle.dumps(net))):
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert other(x).dtype == torch.float32
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert net[0](x).dtype == torch.bfloat16  # autocast is back on after the region


def test_model_fp32_modules_keeps_omnets_pose_head_in_float32_and_is_checked():
    import hydra

    from src.compose import compose_model_config
    from src.utils.errors import ConfigError
    from src.models.module import RegistrationModule

    cfg = compose_model_config("omnet", 0.0625, ["+model.fp32_modules=[iterations.*.regressor]"])
    module = hydra.utils.instantiate(cfg)
    assert module.hparams["fp32_modules"] == ["iterations.*.regressor"]
    pooled = torch.randn(4, module.network.iterations[0].regressor[0][0].in_features)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert module.network.iterations[0].regressor(pooled).dtype == torch.float32
        assert module.network.iterations[0].encoder[0](torch.randn(4, 8, 3)).dtype == torch.bfloat16
    rebuilt = RegistrationModule(**module.hparams)  # what load_from_checkpoint does with the stored hyperparameters
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert rebuilt.network.iterations[0].regressor(pooled).dtype == torch.float32
    with pytest.raises(ConfigError, match=r"^model.fp32_modules: 'head' matches no submodule of OMNet"):
        RegistrationModule(network=dict(module.hparams["network"]), fp32_modules=["head"])
