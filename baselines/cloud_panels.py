"""Point clouds drawn as matplotlib 3D scatter panels, one camera and one axes box for every panel of a pair:
the figures of :mod:`benchmarks.plots.figures` and the before/after picture of :mod:`baselines.register_cli`."""

from __future__ import annotations

import numpy as np

#: Colours: the source, the reference, overlapping points of a mask, the rest.
SOURCE, REFERENCE, OVERLAP, REST = "#e69f00", "#0072b2", "#d62728", "#c8c8c8"


def centre(points: np.ndarray) -> np.ndarray:
    """The centre of the points' bounding box."""
    return (points.max(axis=0) + points.min(axis=0)) / 2


def half_size(*clouds: np.ndarray) -> float:
    """Half the side of the cube that holds each of ``clouds`` around its own centre."""
    return max(float(np.abs(c - centre(c)).max()) for c in clouds)


def panel(fig, grid, slot: int, clouds, centre: np.ndarray, half: float, view: tuple[float, float], title: str) -> None:
    """One 3D scatter of ``clouds`` (``(points, colour)`` pairs) in the cube of half side ``half`` around ``centre``."""
    ax = fig.add_subplot(*grid, slot, projection="3d")
    for points, color in clouds:
        ax.scatter(*points.T, s=1.2, c=color, depthshade=False, linewidths=0, axlim_clip=True)
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
           zlim=(centre[2] - half, centre[2] + half))
    ax.set_box_aspect((1, 1, 1), zoom=1.35)
    ax.view_init(elev=view[0], azim=view[1], vertical_axis="y")
    ax.set_axis_off()
    ax.set_title(title, fontsize=7, pad=0)
