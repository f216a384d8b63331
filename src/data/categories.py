"""ModelNet40 category lists and the OMNet splits (paper Sec. 4.1, official code)."""

from __future__ import annotations

MODELNET40_CATEGORIES: tuple[str, ...] = (
    "airplane", "bathtub", "bed", "bench", "bookshelf", "bottle", "bowl", "car", "chair", "cone",
    "cup", "curtain", "desk", "door", "dresser", "flower_pot", "glass_box", "guitar", "keyboard",
    "lamp", "laptop", "mantel", "monitor", "night_stand", "person", "piano", "plant", "radio",
    "range_hood", "sink", "sofa", "stairs", "stool", "table", "tent", "toilet", "tv_stand", "vase",
    "wardrobe", "xbox",
)
"""The 40 categories in the order of ``shape_names.txt`` (label = index)."""

AXISYMMETRIC_CATEGORIES: tuple[str, ...] = (
    "bottle", "bowl", "cone", "cup", "flower_pot", "lamp", "tent", "vase",
)
"""Removed by OMNet: any rotation about their axis is a valid registration."""

FIRST_HALF: tuple[str, ...] = MODELNET40_CATEGORIES[:20]
SECOND_HALF: tuple[str, ...] = MODELNET40_CATEGORIES[20:]


def half_categories(half: int, remove_axisymmetric: bool = True) -> list[str]:
    """Categories of the first (``half=1``: train/val) or second (``half=2``: test) half.

    With ``remove_axisymmetric`` (the paper's default) this gives the 14 train/val and 18 test
    categories of ``modelnet40_half{1,2}_rm_rotate``.
    """
    if half not in (1, 2):
        raise ValueError(f"half must be 1 or 2, got {half}")
    names = FIRST_HALF if half == 1 else SECOND_HALF
    return [c for c in names if not (remove_axisymmetric and c in AXISYMMETRIC_CATEGORIES)]
