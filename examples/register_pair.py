"""Register one pair of point clouds with any method of the registry, from Python, and print the result.

Shows the one interface every method sits behind (``baselines.get_registrator``): a pair of (N, 3) arrays in,
a 4x4 transform with ``ref ≈ R·src + t`` out, plus the time and the fit (``register_result``). Without files,
the pair is a built-in L-shaped solid moved by a known transform, so the errors against the truth are printed too.

    python examples/register_pair.py                              # ICP on the built-in pair
    python examples/register_pair.py --method fgr                 # any key of `python -m baselines`
    python examples/register_pair.py --method omnet               # a learned method: its shipped checkpoint
    python examples/register_pair.py --src a.ply --ref b.ply      # your own clouds (PLY, PCD or XYZ text)
"""

import argparse

import numpy as np

from baselines import get_registrator
from baselines.testing import euler_transform, make_pair, rotation_error_deg, translation_error
from src.data.point_files import read_points

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("--method", default="icp", help="a key of `python -m baselines` (default: icp)")
parser.add_argument("--src", help="the cloud to move (default: the built-in pair)")
parser.add_argument("--ref", help="the cloud to align it to")
parser.add_argument("--points", type=int, default=768, help="points per cloud of the built-in pair")
args = parser.parse_args()

truth = None
if args.src and args.ref:
    src, ref = read_points(args.src), read_points(args.ref)
else:  # the reference is the source's surface, sampled again and moved by 30°/20°/10° and (0.2, -0.1, 0.1)
    truth = euler_transform((30.0, 20.0, 10.0), (0.2, -0.1, 0.1))
    src, ref = make_pair(truth, args.points, seed=0, twice_sampled=True)

method = get_registrator(args.method)
result = method.register_result(src, ref)   # also: method.register(src, ref) -> the 4x4 alone
np.set_printoptions(precision=4, suppress=True)
print(f"method: {getattr(method, 'label', args.method)}  ({len(src)} -> {len(ref)} points)")
print(f"transform (ref ≈ R·src + t):\n{result.transform}")
print(f"seconds: {result.seconds:.3f}  fitness: {result.fitness:.3f}  inlier RMSE: {result.inlier_rmse:.4f}"
      + (f"  failed: {result.reason}" if result.failed else ""))
if truth is not None:
    print(f"Error(R): {rotation_error_deg(result.transform, truth):.3f} deg  "
          f"Error(t): {translation_error(result.transform, truth):.4f}")
