"""Compute tests/fixtures/published_*.npz with the authors' own code and the published weights.

Run once (CPU), from the repository root; tests/unit/baselines/test_published_weights.py compares our
networks against the arrays. The authors' code is read from checkouts outside the repository (never
copied into it), e.g. with ``AUTHORS`` a folder of your choice:

    for r in WangYueFt+dcp vinits5+learning3d Lilac-Lee+PointNetLK_Revisited; do mkdir -p $AUTHORS/$r; done
    git -C <a clone of WangYueFt/dcp> show HEAD:model.py > $AUTHORS/WangYueFt+dcp/model.py   # + util.py
    # learning3d: models/{pointnet,pointnetlk,pooling}.py, ops/{data_utils,se3,so3,sinc,invmat}.py
    # PointNetLK_Revisited: model.py, utils.py
    python -m tests.helpers.make_published_fixtures --dcp $AUTHORS/WangYueFt+dcp \\
        --learning3d $AUTHORS/vinits5+learning3d --revisited $AUTHORS/Lilac-Lee+PointNetLK_Revisited

Two CPU-only edits are made in memory, never in the files: DCP's ``get_graph_feature`` puts its index
on ``torch.device('cuda')`` (→ the points' device); PointNetLK-Revisited's ``do_forward`` writes into
``eye(4).expand(B, 4, 4).to(p0)``, a copy on the GPU they ran on but a shared view on the CPU (→
``.clone()``). Inputs: two real airplanes of the prepared cache
(``python -m src.data.prepare modelnet40_resampled --source ../shared/data/...airplane.zip``).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import types
from argparse import Namespace
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from src.utils.paths import shared_path
from tests.helpers.paths import FIXTURES
SHAPES = (3, 7)  # train ids airplane_0004 and airplane_0008 of the cache


def load_module(name: str, path: Path, edits: dict[str, str] | None = None) -> types.ModuleType:
    """Import ``path`` as module ``name``, applying textual ``edits`` (old → new) in memory."""
    source = path.read_text()
    for old, new in (edits or {}).items():
        if old not in source:
            raise SystemExit(f"{path}: expected text {old!r} not found (another version of the code?)")
        source = source.replace(old, new)
    spec = importlib.util.spec_from_loader(name, loader=None, origin=str(path))
    module = importlib.util.module_from_spec(spec)
    module.__file__ = str(path)
    sys.modules[name] = module
    exec(compile(source, str(path), "exec"), module.__dict__)  # noqa: S102 - the authors' code, run locally once
    return module


def package(name: str, path: Path) -> None:
    """An empty package ``name`` over ``path`` (skips learning3d's __init__, which imports every model)."""
    module = types.ModuleType(name)
    module.__path__ = [str(path)]
    sys.modules[name] = module


def clouds(points: np.ndarray, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    picked = [points[i, 0][np.sort(rng.choice(points.shape[2], n, replace=False))] for i in SHAPES]
    return np.stack(picked).astype(np.float32)


def dcp_fixture(code: Path, points: np.ndarray) -> dict[str, np.ndarray]:
    sys.path.insert(0, str(code))
    dcp = load_module("dcp_model", code / "model.py", {"torch.device('cuda')": "x.device"})
    net = dcp.DCP(Namespace(emb_nn="dgcnn", pointer="identity", head="svd", emb_dims=512, cycle=False,
                            n_blocks=1, n_heads=4, ff_dims=1024, dropout=0.0))
    net.load_state_dict(torch.load(shared_path("weights", "dcp_v1.t7"), map_location="cpu"))
    net.eval()
    src = clouds(points, 256, 0)
    rot = Rotation.from_euler("zyx", [[30, 20, 10], [40, 5, 25]], degrees=True).as_matrix()
    trans = np.array([[0.2, -0.1, 0.3], [-0.3, 0.25, 0.1]])
    perm = np.random.default_rng(1).permutation(src.shape[1])
    ref = (np.einsum("bij,bnj->bni", rot, src) + trans[:, None])[:, perm].astype(np.float32)
    with torch.no_grad():
        rotation, translation, _, _ = net(torch.from_numpy(src).transpose(2, 1), torch.from_numpy(ref).transpose(2, 1))
    return {"src": src, "ref": ref, "rotation": rotation.numpy(), "translation": translation.numpy()}


def twist_pair(points: np.ndarray, n: int, se3_exp) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    template = torch.from_numpy(clouds(points, n, 2))
    twist = torch.tensor([[0.3, -0.2, 0.25, 0.2, 0.1, -0.3], [-0.1, 0.35, 0.1, -0.25, 0.3, 0.15]])
    g = se3_exp(twist)
    perm = torch.from_numpy(np.random.default_rng(3).permutation(n))
    source = (template @ g[:, :3, :3].transpose(1, 2) + g[:, None, :3, 3])[:, perm]
    return template.numpy(), source.numpy().astype(np.float32), g


def learning3d_fixture(code: Path, points: np.ndarray) -> dict[str, np.ndarray]:
    package("learning3d", code)
    package("learning3d.models", code / "models")
    package("learning3d.ops", code / "ops")
    from learning3d.models.pointnet import PointNet
    from learning3d.models.pointnetlk import PointNetLK
    from learning3d.ops import se3

    net = PointNetLK(feature_model=PointNet(emb_dims=1024, use_bn=True))
    net.load_state_dict(torch.load(shared_path("weights", "learning3d_pointnetlk.t7"), map_location="cpu"))
    net.eval()
    template, source, g = twist_pair(points, 512, se3.exp)
    p0, p1 = torch.from_numpy(template), torch.from_numpy(source)
    with torch.no_grad():
        out = net(p0, p1, maxiter=10)  # examples/test_pnlk.py: model(template, source)
        centred = p0 - p0.mean(dim=1, keepdim=True)
        features = net.pooling(net.feature_model(centred))
        jacobian = net.approx_Jic(centred, features, net.dt.expand(2, 6))
    g_centred = torch.eye(4).repeat(2, 1, 1)
    g_centred[:, :3, :3], g_centred[:, :3, 3] = out["est_R"], out["est_t"]  # iclk's g, before postprocess_data
    return {"template": template, "source": source, "igt": g.numpy(), "features": features.numpy(),
            "jacobian": jacobian.numpy(), "g_centred": g_centred.numpy(), "est_T": out["est_T"].numpy(),
            "residual": out["r"].numpy(), "iterations": np.array(out["itr"])}


def revisited_fixture(code: Path, points: np.ndarray) -> dict[str, np.ndarray]:
    sys.path.insert(0, str(code))
    utils = load_module("utils", code / "utils.py")
    model = load_module("plkr_model", code / "model.py", {
        "p0.size(0), 4, 4).to(p0)  # [B, 4, 4]": "p0.size(0), 4, 4).to(p0).clone()  # [B, 4, 4]",
        "p1.size(0), 4, 4).to(p1)  # [B, 4, 4]": "p1.size(0), 4, 4).to(p1).clone()  # [B, 4, 4]",
    })
    net = model.AnalyticalPointNetLK(model.Pointnet_Features(1024), "cpu")
    net.load_state_dict(torch.load(shared_path("weights", "pointnetlk_revisited_modelnet40.pth"), map_location="cpu"))
    net.eval()
    template, source, g = twist_pair(points, 512, utils.exp)
    template, source = template * 0.5, source * 0.5  # about the unit cube (data_utils.OnUnitCube)
    p0, p1 = torch.from_numpy(template), torch.from_numpy(source)
    model.AnalyticalPointNetLK.do_forward(net, p0, None, p1, None, 20, 1e-7, True, True, "test", "synthetic")
    centred = p0 - p0.mean(dim=1, keepdim=True)
    features, masks, weights, pre, bn, winner = net.ptnet(centred, -1)
    jacobian = net.Cal_Jac(masks, weights, pre, bn, winner, centred.shape[1], centred, "test")
    return {"template": template, "source": source, "features": features.detach().numpy(),
            "jacobian": jacobian.detach().numpy(), "transform": net.g.detach().numpy(), "iterations": np.array(net.itr)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dcp", type=Path, required=True, help="checkout of WangYueFt/dcp")
    parser.add_argument("--learning3d", type=Path, required=True, help="checkout of vinits5/learning3d")
    parser.add_argument("--revisited", type=Path, required=True, help="checkout of Lilac-Lee/PointNetLK_Revisited")
    cache = Path(os.environ.get("OMNET_CACHE_DIR", Path.home() / ".cache" / "omnet-registration"))
    parser.add_argument("--points", type=Path, default=cache / "modelnet40_resampled" / "train_points.npy")
    args = parser.parse_args()
    torch.manual_seed(0)
    points = np.load(args.points, mmap_mode="r")
    FIXTURES.mkdir(exist_ok=True)
    for name, make, code in (("dcp_v1", dcp_fixture, args.dcp),
                             ("learning3d_pointnetlk", learning3d_fixture, args.learning3d),
                             ("pointnetlk_revisited", revisited_fixture, args.revisited)):
        path = FIXTURES / f"published_{name}.npz"
        np.savez_compressed(path, **make(code, points))
        print(f"wrote {path} ({path.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
