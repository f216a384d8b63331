"""The authors' code on the golden pairs: one function per method, ``(checkout, pairs, dtype) -> (P, 4, 4)``.

Each loads the authors' ``model.py`` from a checkout outside the repository (never copied into it) with the
in-memory CPU edits of :mod:`benchmarks.studies.lockstep.prnet` / :mod:`benchmarks.studies.lockstep.idam` /
:mod:`benchmarks.studies.lockstep.omnet`, and the weights the golden file names: published weights from the shared
folder, or a shipped checkpoint of ours copied into the authors' network layer by layer (the lockstep modules'
weight maps). Pairs go through in batches of :data:`BATCH`, in eval mode (without gradients where the code takes none).
"""

from __future__ import annotations

from argparse import Namespace
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from benchmarks.studies.golden.library import CALLS, LIBRARIES, PACKAGES
from benchmarks.studies.golden.library import run as library_call
from src.utils.errors import ConfigError

BATCH = 8


def _se3(rotation: Tensor, translation: Tensor) -> np.ndarray:
    out = np.tile(np.eye(4), (rotation.shape[0], 1, 1))
    out[:, :3, :3], out[:, :3, 3] = rotation.double().numpy(), translation.reshape(-1, 3).double().numpy()
    return out


def _batched(pairs: dict[str, np.ndarray], dtype: torch.dtype, run: Callable[[Tensor, Tensor], np.ndarray],
             grad: bool = False) -> np.ndarray:
    """``run(src, ref)`` ((B, N, 3) tensors of ``dtype``) over the pairs in batches, without gradients unless
    ``grad``; (P, 4, 4) float64."""
    out = []
    with torch.set_grad_enabled(grad):
        for start in range(0, len(pairs["src"]), BATCH):
            src = torch.from_numpy(pairs["src"][start:start + BATCH]).to(dtype)
            ref = torch.from_numpy(pairs["ref"][start:start + BATCH]).to(dtype)
            out.append(run(src, ref))
    return np.concatenate(out)


def dcp_v1(checkout: Path, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """WangYueFt/dcp's DCP-v1 (main.py's flags: dgcnn, identity pointer, svd head, emb_dims 512) with the
    published ``dcp_v1.t7``; ``forward(src, tgt)`` on (B, 3, N) returns R_ab, t_ab (model.py:454-470)."""
    from benchmarks.studies.lockstep.harness import load_authors_model
    from benchmarks.studies.lockstep.prnet import cpu_torch
    from src.utils.paths import shared_path

    model = load_authors_model(checkout, "WangYueFt/dcp", "dcp")  # model.py:16: from util import quat2mat
    model.torch = cpu_torch()  # model.py:56: torch.device('cuda')
    net = model.DCP(Namespace(emb_nn="dgcnn", pointer="identity", head="svd", emb_dims=512, cycle=False,
                              n_blocks=1, n_heads=4, ff_dims=1024, dropout=0.0))
    net.load_state_dict(torch.load(shared_path("weights", "dcp_v1.t7"), map_location="cpu"))
    net = net.to(dtype).eval()

    def run(src: Tensor, ref: Tensor) -> np.ndarray:
        rotation, translation, *_ = net(src.transpose(1, 2).contiguous(), ref.transpose(1, 2).contiguous())
        return _se3(rotation, translation)

    return _batched(pairs, dtype, run)


def shipped_network(method: str, dtype: torch.dtype) -> tuple[torch.nn.Module, dict]:
    """The network of ``method``'s shipped checkpoint (the framework's default one), in eval mode and ``dtype``,
    and its settings (the checkpoint's ``model.network``)."""
    from baselines import get_registrator

    module = get_registrator(method, device="cpu").module
    return module.network.to(dtype).eval(), dict(module.hparams["network"])


def omnet(checkout: Path, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """hxwork/OMNet_Pytorch's OMNet (the authors' PyTorch port) with the shipped OMNet checkpoint's weights, its
    layers at the checkpoint's width (:func:`benchmarks.studies.lockstep.omnet.load_authors`); ``forward(data)``
    (model/net.py) takes the ground truth for its mask labels only, the pose never sees it. In float64 its
    ``.float()`` casts keep float64 (:func:`benchmarks.studies.lockstep.harness.float64_mode`)."""
    import contextlib

    from benchmarks.studies.lockstep.harness import float64_mode
    from benchmarks.studies.lockstep.omnet import OMNetPair, copy_weights, load_authors

    ours, settings = shipped_network("omnet", dtype)
    authors = load_authors(checkout, settings["width"])
    theirs = authors.OMNet(Namespace(titer=ours.num_iters, overlap_dist=ours.overlap_dist))
    copy_weights(ours, theirs, ours.num_iters)
    pair = OMNetPair(ours, theirs.to(dtype).eval(), authors.compute_loss, None)
    gt = torch.from_numpy(pairs["transform_gt"]).to(dtype)

    done = [0]

    def run(src: Tensor, ref: Tensor) -> np.ndarray:
        batch = {"points_src": src, "points_ref": ref, "transform_gt": gt[done[0]:done[0] + len(src)]}
        done[0] += len(src)
        return _as_np(theirs(pair._authors_inputs(batch))["transform_pair"][1])

    with float64_mode() if dtype == torch.float64 else contextlib.nullcontext():
        return _batched(pairs, dtype, run)


def idam(checkout: Path, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """jiahaowork/idam's IDAM(GNN(64), emb_dims=64, num_iter=3) with the shipped IDAM checkpoint's weights
    (:func:`benchmarks.studies.lockstep.idam.copy_weights`), eval mode (top-k selection, no ground truth: model.py:188),
    its SVDHead replaced by our weighted Procrustes: the one documented deviation of ours
    (``baselines/learned/idam.py``: weighted centroids; theirs centres the covariance on the uniform means,
    model.py:139-140); everything before the head is theirs."""
    import contextlib

    from benchmarks.studies.lockstep.idam import (
        IDAMPair,
        _procrustes_head,
        copy_weights,
        load_authors,
    )
    from benchmarks.studies.lockstep.harness import float64_mode

    ours, settings = shipped_network("idam", dtype)
    authors = load_authors(checkout)
    theirs = authors.IDAM(authors.GNN(settings["emb_dims"]), Namespace(emb_dims=settings["emb_dims"], num_iter=ours.num_iters))
    copy_weights(ours, theirs)
    theirs = theirs.to(dtype).eval()
    theirs.head.forward = _procrustes_head
    pair = IDAMPair(ours, theirs)

    def run(src: Tensor, ref: Tensor) -> np.ndarray:
        return pair.outputs("authors", {"points_src": src, "points_ref": ref, "transform_gt": None})[1].double().numpy()

    with float64_mode() if dtype == torch.float64 else contextlib.nullcontext():
        return _batched(pairs, dtype, run)


def rpmnet(checkout: Path, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """yewzijian/RPMNet's RPM-Net with the shipped RPM-Net checkpoint's weights, in eval mode, with its evaluation
    iterations (:mod:`benchmarks.studies.golden.authors_rpmnet`), given the normals ours estimates."""
    from benchmarks.studies.golden.authors_rpmnet import authors_estimate, authors_network

    ours, settings = shipped_network("rpmnet", dtype)
    if settings["normals"] != "estimated":
        raise ConfigError(f"the shipped RPM-Net checkpoint takes normals {settings['normals']!r}: the golden pairs carry none")
    theirs = authors_network(checkout, ours, settings)
    return _batched(pairs, dtype, lambda src, ref: authors_estimate(theirs, ours, src, ref, settings["num_iters"]).double().numpy())


def prnet(checkout: Path, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """WangYueFt/prnet's PRNet with the shipped PRNet checkpoint's weights, its layers at the checkpoint's width,
    drawing our Gumbel noise as ours does (:mod:`benchmarks.studies.golden.authors_prnet`)."""
    from benchmarks.studies.golden.authors_prnet import (
        authors_network,
        pose,
        same_noise,
    )

    ours, network = shipped_network("prnet", dtype)
    model, theirs = authors_network(checkout, ours, network, dtype)
    with same_noise(model, dtype):
        return _batched(pairs, dtype, lambda src, ref: pose(theirs, src, ref))


def fmr(checkout: Path, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """XiaoshuiHuang/fmr's FMR with the shipped FMR checkpoint's weights, their test's estimate (10 iterations,
    xtol 1e-7, one pair at a time: :mod:`benchmarks.studies.golden.authors_fmr`)."""
    from benchmarks.studies.golden.authors_fmr import authors_network, pose

    ours, network = shipped_network("fmr", dtype)
    theirs = authors_network(checkout, ours, network)
    return _batched(pairs, dtype, lambda src, ref: pose(theirs, src, ref))


def deepgmr(checkout: Path, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """wentaoyuan/deepgmr's DeepGMR with the shipped DeepGMR checkpoint's weights, its layers at the checkpoint's
    width, given the RRI features their data loader computes (:mod:`benchmarks.studies.golden.authors_deepgmr`); in
    float64 their float32 literals keep float64 (:func:`benchmarks.studies.lockstep.harness.float64_mode`)."""
    import contextlib

    from benchmarks.studies.golden.authors_deepgmr import (
        authors_estimate,
        authors_network,
    )
    from benchmarks.studies.lockstep.harness import float64_mode

    ours, settings = shipped_network("deepgmr", dtype)
    authors, theirs = authors_network(checkout, ours, settings)

    def run(src: Tensor, ref: Tensor) -> np.ndarray:
        return _as_np(authors_estimate(authors, theirs, settings["k"], src, ref))

    with float64_mode() if dtype == torch.float64 else contextlib.nullcontext():
        return _batched(pairs, dtype, run)


def learning3d_pointnetlk(checkout: Path, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """vinits5/learning3d's PointNetLK (``models/pointnetlk.py``, PointNet(emb_dims=1024, use_bn=True)) with the
    published ``learning3d_pointnetlk.t7``, ``forward(template=ref, source=src, maxiter=10)``; the estimate is its
    ``iclk`` pose g on the centred clouds, uncentred as ``T(m_ref)·g·T(−m_src)``: ours, which fixes learning3d's
    ``postprocess_data`` (it composes ``T(−m_ref)``; ``baselines/learned/pointnetlk.py``). Rotations are theirs."""
    from src.utils.paths import shared_path
    from tests.helpers.make_published_fixtures import package

    if not (checkout / "models" / "pointnetlk.py").is_file():
        raise ConfigError(f"--authors {checkout}: no models/pointnetlk.py (a checkout of vinits5/learning3d is needed)")
    package("learning3d", checkout)
    package("learning3d.models", checkout / "models")
    package("learning3d.ops", checkout / "ops")
    from learning3d.models.pointnet import PointNet
    from learning3d.models.pointnetlk import PointNetLK

    net = PointNetLK(feature_model=PointNet(emb_dims=1024, use_bn=True))
    net.load_state_dict(torch.load(shared_path("weights", "learning3d_pointnetlk.t7"), map_location="cpu"))
    net = net.to(dtype).eval()

    def run(src: Tensor, ref: Tensor) -> np.ndarray:
        result = net(ref, src, maxiter=10)
        g = np.tile(np.eye(4), (len(src), 1, 1))
        g[:, :3, :3], g[:, :3, 3] = result["est_R"].double().numpy(), result["est_t"].double().numpy()
        left, right = np.tile(np.eye(4), (2, len(src), 1, 1))
        left[:, :3, 3], right[:, :3, 3] = ref.double().mean(1).numpy(), -src.double().mean(1).numpy()
        return left @ g @ right

    return _batched(pairs, dtype, run)


def pointnetlk_revisited(checkout: Path, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """Lilac-Lee/PointNetLK_Revisited's AnalyticalPointNetLK (``model.py``, Pointnet_Features(1024)) with the
    published weights, ``do_forward(template=ref, source=src, maxiter=20, xtol=1e-7, zero means, 'test',
    'synthetic')``: its ``g``. The CPU edit of :mod:`tests.helpers.make_published_fixtures` (a writable copy of the
    identity, ``.clone()``); in float64 its ``.float()`` casts keep float64 (:func:`benchmarks.studies.lockstep.harness.float64_mode`)."""
    import contextlib
    import sys

    from benchmarks.studies.lockstep.harness import float64_mode
    from src.utils.paths import shared_path
    from tests.helpers.make_published_fixtures import load_module

    if not (checkout / "model.py").is_file() or not (checkout / "utils.py").is_file():
        raise ConfigError(f"--authors {checkout}: no model.py/utils.py (a checkout of Lilac-Lee/PointNetLK_Revisited)")
    sys.path.insert(0, str(checkout))
    try:
        load_module("utils", checkout / "utils.py")
        model = load_module("plkr_model", checkout / "model.py", {
            "p0.size(0), 4, 4).to(p0)  # [B, 4, 4]": "p0.size(0), 4, 4).to(p0).clone()  # [B, 4, 4]",
            "p1.size(0), 4, 4).to(p1)  # [B, 4, 4]": "p1.size(0), 4, 4).to(p1).clone()  # [B, 4, 4]",
        })
    finally:
        sys.path.remove(str(checkout))
    net = model.AnalyticalPointNetLK(model.Pointnet_Features(1024), "cpu")
    net.load_state_dict(torch.load(shared_path("weights", "pointnetlk_revisited_modelnet40.pth"), map_location="cpu"))
    net = net.to(dtype).eval()

    def run(src: Tensor, ref: Tensor) -> np.ndarray:
        model.AnalyticalPointNetLK.do_forward(net, ref, None, src, None, 20, 1e-7, True, True, "test", "synthetic")
        return net.g.detach().double().numpy()

    with float64_mode() if dtype == torch.float64 else contextlib.nullcontext():
        return _batched(pairs, dtype, run, grad=True)  # its Jacobian takes autograd's


def _as_np(transform: Tensor) -> np.ndarray:
    out = np.tile(np.eye(4), (transform.shape[0], 1, 1))
    out[:, :3, :] = transform[:, :3, :].double().numpy()
    return out


@dataclass(frozen=True)
class Reference:
    """A golden method's reference: the authors' repository (a checkout is needed) or library, the weights
    (``official:<name>``, a shipped checkpoint's name, or empty) and the function running their code."""

    repo: str
    weights: str
    run: Callable[[Path | None, dict[str, np.ndarray], torch.dtype], np.ndarray]
    library: bool = False


def _library(method: str) -> Reference:
    """A classical method's reference: its library call (:mod:`benchmarks.studies.golden.library`), float64."""
    repo = PACKAGES[LIBRARIES[method]][1] if method in LIBRARIES else "isl-org/Open3D"
    return Reference(repo, "", lambda checkout, pairs, dtype: library_call(method, pairs), library=True)


def cpd(checkout: Path, pairs: dict[str, np.ndarray], dtype: torch.dtype) -> np.ndarray:
    """Myronenko's CPD package (MATLAB, in GNU Octave), rigid with the scale fixed, float64
    (:mod:`benchmarks.studies.golden.authors_cpd`)."""
    from benchmarks.studies.golden.authors_cpd import cpd as authors_cpd

    return authors_cpd(checkout, pairs)


REFERENCES: dict[str, Reference] = {
    "dcp_v1": Reference("WangYueFt/dcp", "official:dcp_v1", dcp_v1),
    "omnet": Reference("hxwork/OMNet_Pytorch", "omnet_real_airplane_ts_prnet", omnet),
    "idam": Reference("jiahaowork/idam", "idam_real_airplane_ts_prnet", idam),
    "rpmnet": Reference("yewzijian/RPMNet", "rpmnet_real_airplane_ts_prnet", rpmnet),
    "prnet": Reference("WangYueFt/prnet", "prnet_real_airplane_ts_prnet", prnet),
    "fmr": Reference("XiaoshuiHuang/fmr", "fmr_real_airplane_ts_prnet", fmr),
    "deepgmr": Reference("wentaoyuan/deepgmr", "deepgmr_real_airplane_ts_prnet", deepgmr),
    "learning3d_pointnetlk": Reference("vinits5/learning3d", "official:learning3d_pointnetlk", learning3d_pointnetlk),
    "pointnetlk_revisited": Reference("Lilac-Lee/PointNetLK_Revisited", "official:pointnetlk_revisited", pointnetlk_revisited),
    "cpd": Reference("dpacheco0921/MeshVol_CPD_Registration", "", cpd),  # its core/: the CPD package (golden README)
    **{method: _library(method) for method in CALLS},
}
