"""The embedded default dataset ``data=synthetic``: procedural CAD-like solids, built offline.

Each shape is a union of closed, outward-oriented primitive meshes (no boolean operations), drawn
from a per-category builder with random dimensions, proportions, part counts and optional parts,
then stretched by a random per-axis factor. Shapes are y-up like the ModelNet40 HDF5 clouds, with
their front towards +z; the caller normalises them into the unit sphere.

The categories mimic ModelNet40's: thin wings, legs, plates, frames with holes and asymmetric
details, some mirror-symmetric like real furniture and vehicles, none axisymmetric (OMNet drops
those because a rotation about their axis is unobservable). Half 1 trains, half 2 holds out
genuinely different categories, with vehicles and furniture in both.

Everything is deterministic per ``(seed, category, split, index)``.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Iterator, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from src.data.mesh import MeshShape
from src.utils.errors import ConfigError

_TAU = 2.0 * np.pi
_STRETCH = 0.15
"""Final per-axis scale factors are ``exp(U(-_STRETCH, _STRETCH))``."""


# ----------------------------------------------------------------------------------------------
# Primitive library. Every primitive is a closed mesh with outward faces; matrices are 4x4.


class _Part(NamedTuple):
    """A triangle mesh: ``(V, 3)`` float vertices and ``(F, 3)`` int faces."""

    vertices: np.ndarray
    faces: np.ndarray


def _translation(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = x, y, z
    return m


def _rotation(axis: str, angle: float) -> np.ndarray:
    """Right-handed rotation by ``angle`` radians about the ``"x"``, ``"y"`` or ``"z"`` axis."""
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    m = np.eye(4)
    c, s = np.cos(angle), np.sin(angle)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def _transform(part: _Part, matrix: np.ndarray) -> _Part:
    """Apply a 4x4 affine map, keeping faces outward under reflections."""
    linear = matrix[:3, :3]
    faces = part.faces if np.linalg.det(linear) > 0 else part.faces[:, ::-1]
    return _Part(part.vertices @ linear.T + matrix[:3, 3], faces)


def _merge(parts: Sequence[_Part]) -> _Part:
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    return _Part(
        np.concatenate([p.vertices for p in parts]).astype(np.float64),
        np.concatenate([p.faces + o for p, o in zip(parts, offsets)]).astype(np.int64),
    )


def _outward(part: _Part) -> _Part:
    """Flip a consistently oriented closed mesh whose signed volume is negative."""
    tri = part.vertices[part.faces]
    volume = np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
    return part if volume > 0 else _Part(part.vertices, part.faces[:, ::-1].copy())


def _loft(rings: np.ndarray, start: Sequence[float] | None = None, end: Sequence[float] | None = None,
          wrap: bool = False) -> _Part:
    """Closed surface through ``(K, M, 3)`` rings of points.

    Consecutive rings are joined by quads; the ends are closed by fans to ``start``/``end``
    (default: the ring centroid, i.e. a flat cap), or, with ``wrap``, the last ring joins the first.
    """
    k, m, _ = rings.shape
    grid = np.arange(k * m).reshape(k, m)
    nxt = np.roll(grid, -1, axis=1)
    below, above = (grid, np.roll(grid, -1, axis=0)) if wrap else (grid[:-1], grid[1:])
    below_n, above_n = (nxt, np.roll(nxt, -1, axis=0)) if wrap else (nxt[:-1], nxt[1:])
    faces = [np.stack([below, below_n, above_n], -1).reshape(-1, 3),
             np.stack([below, above_n, above], -1).reshape(-1, 3)]
    vertices = [rings.reshape(-1, 3)]
    if not wrap:
        caps = [rings[0].mean(0) if start is None else start, rings[-1].mean(0) if end is None else end]
        vertices.append(np.asarray(caps, dtype=float))
        faces.append(np.stack([np.full(m, k * m), nxt[0], grid[0]], -1))
        faces.append(np.stack([np.full(m, k * m + 1), grid[-1], nxt[-1]], -1))
    return _outward(_Part(np.concatenate(vertices), np.concatenate(faces)))


_AXES = {"x": [2, 0, 1], "y": [0, 2, 1], "z": [0, 1, 2]}


def _stack(outline: np.ndarray, levels: Sequence[float] | np.ndarray, scale: ArrayLike = 1.0, shift: ArrayLike = 0.0,
           axis: str = "y", start: Sequence[float] | None = None, end: Sequence[float] | None = None) -> _Part:
    """Solid through copies of a 2-D ``(M, 2)`` outline placed at ``levels`` along ``axis``.

    ``scale`` and ``shift`` broadcast to ``(K, 2)`` and act on the outline coordinates, which map
    to (y, z), (x, z) or (x, y) for axis x, y or z. ``start``/``end`` are optional cap apexes.
    """
    levels = np.atleast_1d(np.asarray(levels, dtype=float))
    k = len(levels)
    flat = outline[None] * np.broadcast_to(np.asarray(scale, float), (k, 2))[:, None]
    flat = flat + np.broadcast_to(np.asarray(shift, float), (k, 2))[:, None]
    coords = np.concatenate([flat, np.broadcast_to(levels[:, None, None], (k, len(outline), 1))], -1)
    return _loft(coords[..., _AXES[axis]], start, end)


def _superellipse(n: int, exponent: float = 2.0) -> np.ndarray:
    """``(n, 2)`` points of ``|x|^p + |y|^p = 1``: a circle (n-gon) at p=2, a rounded square for large p."""
    t = np.linspace(0.0, _TAU, n, endpoint=False)
    c, s = np.cos(t), np.sin(t)
    return np.stack([np.sign(c) * np.abs(c) ** (2 / exponent), np.sign(s) * np.abs(s) ** (2 / exponent)], 1)


def _airfoil(n: int, thickness: float) -> np.ndarray:
    """``(2n, 2)`` symmetric NACA-00xx section as (thickness, chord): leading edge 0, trailing edge -1."""
    x = (1 - np.cos(np.linspace(0.0, np.pi, n + 1))) / 2
    half = 5 * thickness * (0.2969 * np.sqrt(x) - 0.126 * x - 0.3516 * x**2 + 0.2843 * x**3 - 0.1036 * x**4)
    return np.stack([np.concatenate([half, -half[-2:0:-1]]), -np.concatenate([x, x[-2:0:-1]])], 1)


def _torus(major: float, minor: float, arc: float = _TAU, n_major: int = 24, n_minor: int = 8) -> _Part:
    """Torus about the y axis, or a capped segment of ``arc`` radians starting on +x."""
    closed = arc >= _TAU - 1e-9
    phi = np.linspace(0.0, arc, n_major, endpoint=not closed)
    circle = _superellipse(n_minor) * minor
    radial = major + circle[:, 0]
    rings = np.stack([np.outer(np.cos(phi), radial), np.broadcast_to(circle[:, 1], (n_major, n_minor)),
                      np.outer(np.sin(phi), radial)], -1)
    return _loft(rings, wrap=closed)


_SQUARE = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
_CUBE = _stack(_SQUARE, [-1.0, 1.0])
_CYLINDER = _stack(_superellipse(12), [-1.0, 1.0])
_TWIG = _stack(_superellipse(6), [-1.0, 1.0])


def _ellipsoid(n_lon: int, n_lat: int) -> _Part:
    """Unit sphere with ``n_lat`` latitude rings of ``n_lon`` points between the poles."""
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 2)[1:-1]
    return _stack(_superellipse(n_lon), np.sin(lat), np.cos(lat)[:, None], start=(0, -1, 0), end=(0, 1, 0))


_SPHERE = _ellipsoid(10, 5)
_LEAF = _ellipsoid(6, 3)
"""Templates spanning [-1, 1] on every axis (cylinders along y), copied by :func:`_instances`."""


def _instances(template: _Part, linear: np.ndarray, offset: np.ndarray) -> _Part:
    """Copies of ``template`` mapped by ``(N, 3, 3)`` linear maps and ``(N, 3)`` offsets."""
    n, nv = len(linear), len(template.vertices)
    vertices = np.einsum("nij,vj->nvi", linear, template.vertices) + np.asarray(offset, float)[:, None]
    faces = template.faces[None] + nv * np.arange(n)[:, None, None]
    flip = np.linalg.det(linear) < 0
    faces[flip] = faces[flip][:, :, ::-1]
    return _Part(vertices.reshape(-1, 3), faces.reshape(-1, 3))


def _boxes(centers: ArrayLike, sizes: ArrayLike, template: _Part = _CUBE) -> _Part:
    """Axis-aligned boxes (or other templates) with given ``(N, 3)`` centres and full sizes."""
    centers = np.atleast_2d(np.asarray(centers, dtype=float))
    sizes = np.broadcast_to(np.asarray(sizes, dtype=float), centers.shape)
    linear = np.zeros((len(centers), 3, 3))
    linear[:, [0, 1, 2], [0, 1, 2]] = sizes / 2
    return _instances(template, linear, centers)


def _frames(directions: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` right-handed frames whose second column is the unit direction."""
    y = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    helper = np.where(np.abs(y[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    x = np.cross(y, helper)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return np.stack([x, y, np.cross(x, y)], axis=2)


def _rods(p0: ArrayLike, p1: ArrayLike, radius: ArrayLike, template: _Part = _CYLINDER) -> _Part:
    """Cylinders (or square bars with ``_CUBE``) of the given radii from points ``p0`` to ``p1``."""
    p0, p1 = np.broadcast_arrays(np.atleast_2d(np.asarray(p0, float)), np.atleast_2d(np.asarray(p1, float)))
    d = p1 - p0
    length = np.linalg.norm(d, axis=1)
    r = np.broadcast_to(np.asarray(radius, float), length.shape)
    linear = _frames(d) * np.stack([r, length / 2, r], 1)[:, None, :]
    return _instances(template, linear, (p0 + p1) / 2)


def _slab(width: float, thickness: float, depth: float, center: Sequence[float] = (0.0, 0.0, 0.0),
          exponent: float = 10.0, bevel: float = 0.25) -> _Part:
    """Horizontal slab with a superelliptic outline and bevelled edges (cushions, tops, mattresses)."""
    e = bevel * thickness
    w, d = width / 2, depth / 2
    levels = center[1] + np.array([-1, -1, 1, 1]) * thickness / 2 + np.array([0, e, -e, 0])
    scale = [[w - e, d - e], [w, d], [w, d], [w - e, d - e]]
    return _stack(_superellipse(24, exponent), levels, scale, shift=(center[0], center[2]))


def _wing(span: float, root: float, tip: float, sweep: float, dihedral: float, thickness: float,
          mirrored: bool = True) -> _Part:
    """Tapered swept wing along x with its root leading edge at the origin, trailing towards -z.

    ``sweep`` and ``dihedral`` are angles in radians; ``mirrored=False`` gives one half (a fin).
    """
    x = np.array([-span, 0.0, span]) if mirrored else np.array([0.0, span])
    chord = np.where(x == 0, root, tip)
    shift = np.stack([np.abs(x) * np.tan(dihedral), -np.abs(x) * np.tan(sweep)], 1)
    return _stack(_airfoil(8, thickness), x, chord[:, None], shift, axis="x")


def _rotor(radius: float, blades: int, chord: float, phase: float, hub: float) -> _Part:
    """Propeller spinning about z: flat blades from a cylindrical hub."""
    angle = phase + _TAU * np.arange(blades) / blades
    radial = np.stack([np.cos(angle), np.sin(angle), np.zeros(blades)], 1)
    tangent = np.stack([-np.sin(angle), np.cos(angle), np.zeros(blades)], 1)
    normal = np.broadcast_to([0.0, 0.0, 1.0], (blades, 3))
    linear = np.stack([radial * radius / 2, tangent * chord / 2, normal * chord / 10], axis=2)
    return _merge([_instances(_CUBE, linear, radial * radius / 2),
                   _rods([0, 0, -hub], [0, 0, hub], hub)])


# ----------------------------------------------------------------------------------------------
# Shared parts.


def _fuselage_profile(t: np.ndarray, radius: float, nose: float, tail: float, tail_radius: float,
                      upsweep: float, pointed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Centre height and radius along a fuselage at ``t`` in [0, 1] (0 = tail, 1 = nose tip)."""
    s = np.clip((t - 1 + nose) / nose, 0, 1)
    q = np.clip((tail - t) / tail, 0, 1)
    r = radius * np.sqrt(1 - s ** (1 if pointed else 2)) * (1 - (1 - tail_radius) * q)
    return upsweep * radius * q**1.5, r


def _fuselage(length: float, radius: float, nose: float, tail: float, tail_radius: float, upsweep: float,
              pointed: bool, height: float = 1.0) -> _Part:
    """Tube along z (nose at +length/2) with a rounded or pointed nose and a raised tapering tail."""
    t = np.concatenate([tail * np.array([0.0, 0.3, 0.55, 0.8, 1.0]),
                        1 - nose + nose * np.array([0.0, 0.35, 0.6, 0.8, 0.92, 0.98])])
    y, r = _fuselage_profile(t, radius, nose, tail, tail_radius, upsweep, pointed)
    return _stack(_superellipse(16), (t - 0.5) * length, np.stack([r, r * height], 1),
                  np.stack([0 * y, y], 1), axis="z", end=(0.0, 0.0, length / 2))


def _legs(xz: ArrayLike, height: float, radius: float, splay: float = 0.0, square: bool = False) -> _Part:
    """Legs from the floor up to ``height`` under ``(N, 2)`` corner points, splayed outwards."""
    xz = np.atleast_2d(np.asarray(xz, float))
    out = xz / np.maximum(np.linalg.norm(xz, axis=1, keepdims=True), 1e-9)
    foot = xz + splay * height * out
    n = len(xz)
    bottom = np.stack([foot[:, 0], np.zeros(n), foot[:, 1]], 1)
    top = np.stack([xz[:, 0], np.full(n, height), xz[:, 1]], 1)
    return _rods(bottom, top, radius, _CUBE if square else _CYLINDER)


def _corners(half_x: float, half_z: float) -> np.ndarray:
    return np.array([[half_x, half_z], [-half_x, half_z], [-half_x, -half_z], [half_x, -half_z]])


def _panel(rng: np.random.Generator, width: float, height: float, thickness: float) -> _Part:
    """Backrest/headboard in x-y from y=0 to ``height``: solid, slatted or an open frame with a hole."""
    style = rng.choice(("solid", "vertical", "horizontal", "frame"))
    if style == "solid":
        return _transform(_slab(width, thickness, height, (0, 0, 0), rng.uniform(3, 10), 0.3),
                          _translation(0, height / 2, 0) @ _rotation("x", -np.pi / 2))
    post, rail = rng.uniform(0.04, 0.08) * width, rng.uniform(0.06, 0.15) * height
    inner_w, low = width - 2 * post, rng.uniform(0.0, 0.4) * height
    centers = [[-(width - post) / 2, height / 2, 0], [(width - post) / 2, height / 2, 0],
               [0, height - rail / 2, 0], [0, low + rail / 2, 0]]
    sizes = [[post, height, thickness]] * 2 + [[width, rail, thickness], [width, rail, thickness * 0.8]]
    if style != "frame":
        n = int(rng.integers(2, 7))
        along = (np.arange(n) + 0.5) / n
        y0, y1 = low + rail, height - rail
        if style == "vertical":
            centers += [[-inner_w / 2 + a * inner_w, (y0 + y1) / 2, 0] for a in along]
            sizes += [[inner_w / n * rng.uniform(0.3, 0.7), y1 - y0, thickness * 0.7]] * n
        else:
            centers += [[0, y0 + a * (y1 - y0), 0] for a in along]
            sizes += [[inner_w, (y1 - y0) / n * rng.uniform(0.3, 0.6), thickness * 0.7]] * n
    return _boxes(centers, sizes)


def _drawers(x0: float, x1: float, y0: float, y1: float, z: float, n: int, round_handles: bool) -> _Part:
    """``n`` drawer fronts stacked between y0 and y1 on the plane z, each with a handle."""
    h = (y1 - y0) / n
    cy = y0 + (np.arange(n) + 0.5) * h
    cx, w = (x0 + x1) / 2, x1 - x0
    fronts = _boxes(np.stack([np.full(n, cx), cy, np.full(n, z + 0.01)], 1), [w - 0.01, h - 0.01, 0.02])
    if round_handles:
        handle = _torus(min(0.04, w / 6), 0.006, np.pi, 8, 6)
        handles = _merge([_transform(handle, _translation(cx, c, z + 0.02)) for c in cy])
    else:
        handles = _boxes(np.stack([np.full(n, cx), cy, np.full(n, z + 0.03)], 1), [min(0.12, w / 3), 0.015, 0.02])
    return _merge([fronts, handles])


# ----------------------------------------------------------------------------------------------
# Category builders: one function per category, returning the parts of one random shape.


_AIRPLANES = {
    # fuselage radius, wing half-span, root chord, taper, sweep (deg), dihedral (deg), wing height (radii)
    "airliner": ((0.045, 0.07), (0.38, 0.55), (0.14, 0.22), (0.2, 0.4), (20, 38), (3, 7), (-0.7, -0.3)),
    "fighter": ((0.05, 0.08), (0.2, 0.32), (0.3, 0.45), (0.08, 0.3), (35, 60), (-6, 0), (-0.3, 0.2)),
    "propeller": ((0.05, 0.08), (0.4, 0.65), (0.1, 0.16), (0.5, 1.0), (-3, 8), (0, 6), (-0.7, 0.85)),
    "glider": ((0.03, 0.05), (0.75, 1.1), (0.06, 0.1), (0.3, 0.6), (0, 6), (2, 6), (0.5, 0.85)),
}


def _airplane(rng: np.random.Generator) -> list[_Part]:
    """Fuselage, swept wings, tailplane, one or two fins, engines or a propeller, maybe a canopy."""
    kind = str(rng.choice(list(_AIRPLANES), p=[0.45, 0.25, 0.2, 0.1]))
    radius, span, chord, taper, sweep, dihedral, mount = (rng.uniform(*r) for r in _AIRPLANES[kind])
    fighter = kind == "fighter"
    body = dict(radius=radius, nose=rng.uniform(0.2, 0.3) if fighter else rng.uniform(0.08, 0.18),
                tail=rng.uniform(0.2, 0.35), tail_radius=rng.uniform(0.15, 0.35), upsweep=rng.uniform(0.0, 0.8),
                pointed=fighter or rng.random() < 0.3)
    parts = [_fuselage(1.0, height=rng.uniform(0.9, 1.15), **body)]
    wing_y, wing_z = mount * radius, rng.uniform(0.0, 0.15)
    sweep, dihedral = np.radians(sweep), np.radians(dihedral)
    parts.append(_transform(_wing(span, chord, chord * taper, sweep, dihedral, rng.uniform(0.06, 0.14)),
                            _translation(0, wing_y, wing_z)))

    fin_h, fin_c = rng.uniform(0.09, 0.2), rng.uniform(0.1, 0.2)
    fin_sweep = np.radians(rng.uniform(25, 55))
    fin_y = sum(_fuselage_profile(np.array(fin_c / 2), **body)) * 0.9
    fin = _transform(_wing(fin_h, fin_c, fin_c * rng.uniform(0.3, 0.7), fin_sweep, 0, 0.1, mirrored=False),
                     _rotation("z", np.pi / 2))
    fin_z = -0.5 + fin_c * rng.uniform(1.0, 1.3)
    if fighter and rng.random() < 0.6:
        cant, dx = np.radians(rng.uniform(10, 25)), rng.uniform(0.3, 0.8) * radius
        parts += [_transform(fin, _translation(s * dx, fin_y, fin_z) @ _rotation("z", -s * cant)) for s in (-1, 1)]
    else:
        parts.append(_transform(fin, _translation(0, fin_y, fin_z)))
    t_tail = not fighter and rng.random() < (0.6 if kind == "glider" else 0.25)
    tail_c = rng.uniform(0.12, 0.18) if fighter else rng.uniform(0.06, 0.11)
    tail = _wing(rng.uniform(0.12, 0.22), tail_c, tail_c * rng.uniform(0.4, 0.8), sweep + np.radians(5),
                 np.radians(rng.uniform(-2, 8)), 0.09)
    tail_pos = (fin_y + fin_h, fin_z - fin_h * np.tan(fin_sweep)) if t_tail else (fin_y * 0.6, -0.5 + tail_c * 1.1)
    parts.append(_transform(tail, _translation(0, *tail_pos)))

    nacelle_r = rng.uniform(0.5, 0.8) * radius
    nacelle_l = rng.uniform(0.1, 0.16)
    nacelle = _stack(_superellipse(12), nacelle_l * np.array([-0.5, -0.25, 0.3, 0.5]),
                     nacelle_r * np.array([[0.55], [1.0], [1.0], [0.9]]), axis="z")
    if kind == "airliner":
        fractions = np.array([0.35]) if rng.random() < 0.7 else np.array([0.3, 0.6])
        for f in fractions:
            for s in (-1, 1):
                x, y = s * f * span, wing_y + f * span * np.tan(dihedral)
                z = wing_z - f * span * np.tan(sweep)
                parts.append(_transform(nacelle, _translation(x, y - 1.3 * nacelle_r, z + 0.1 * nacelle_l)))
                parts.append(_boxes([x, y - 0.6 * nacelle_r, z - 0.2 * nacelle_l],
                                    [0.2 * nacelle_r, 1.2 * nacelle_r, 0.7 * nacelle_l]))
    elif kind == "propeller":
        rotor = _rotor(rng.uniform(0.08, 0.14), int(rng.integers(2, 5)), rng.uniform(0.015, 0.025),
                       rng.uniform(0, _TAU), 0.2 * radius)
        if rng.random() < 0.6:
            parts.append(_transform(rotor, _translation(0, 0, 0.5)))
        else:
            x, y = rng.uniform(0.25, 0.4) * span, wing_y
            for s in (-1, 1):
                parts.append(_transform(nacelle, _translation(s * x, y, wing_z + 0.3 * nacelle_l)))
                parts.append(_transform(rotor, _translation(s * x, y, wing_z + 0.8 * nacelle_l)))
    if kind != "airliner":
        nose_t = 1 - body["nose"]
        canopy_y = sum(_fuselage_profile(np.array(nose_t), **body)) * 0.8
        parts.append(_boxes([0, canopy_y, nose_t - 0.5 - 0.05], [radius * 1.2, radius, rng.uniform(0.12, 0.22)],
                            _SPHERE))
    return parts


def _helicopter(rng: np.random.Generator) -> list[_Part]:
    """Cabin, tapering tail boom with fin and tail rotor, main rotor on a mast, skids or wheels."""
    length, radius = rng.uniform(0.3, 0.42), rng.uniform(0.07, 0.1)
    tall = rng.uniform(1.1, 1.4)
    cabin_z = 0.5 - length / 2
    parts = [_transform(_fuselage(length, radius, rng.uniform(0.3, 0.45), rng.uniform(0.3, 0.45), 0.45,
                                  rng.uniform(0.2, 0.6), False, tall), _translation(0, 0, cabin_z))]
    rise = rng.uniform(0.0, 0.06)
    boom_start = cabin_z - length / 2 + 0.05
    parts.append(_stack(_superellipse(10), [-0.5, boom_start], np.array([[0.12], [0.3]]) * radius,
                        np.array([[0, radius * 0.3 + rise], [0, radius * 0.3]]), axis="z"))
    fin_h, fin_c = rng.uniform(0.1, 0.16), rng.uniform(0.07, 0.11)
    fin = _wing(fin_h, fin_c, fin_c * 0.6, np.radians(rng.uniform(20, 50)), 0, 0.1, mirrored=False)
    parts.append(_transform(fin, _translation(0, radius * 0.3 + rise, -0.5 + fin_c) @ _rotation("z", np.pi / 2)))
    if rng.random() < 0.7:
        stab_c = rng.uniform(0.04, 0.07)
        parts.append(_transform(_wing(rng.uniform(0.06, 0.1), stab_c, stab_c * 0.7, 0.1, 0, 0.1),
                                _translation(0, radius * 0.3 + rise * 0.8, -0.5 + fin_c * 2.5)))
    side = rng.choice((-1, 1))
    tail_rotor = _rotor(rng.uniform(0.06, 0.1), int(rng.integers(2, 5)), 0.015, rng.uniform(0, _TAU), 0.01)
    hub = _translation(side * 0.025, radius * 0.3 + rise + fin_h * 0.7, -0.5 + fin_c * 0.7)
    parts.append(_transform(tail_rotor, hub @ _rotation("y", np.pi / 2)))
    top = radius * tall
    mast_top = top + rng.uniform(0.04, 0.09)
    parts.append(_rods([0, top * 0.8, cabin_z], [0, mast_top, cabin_z], 0.012))
    main = _rotor(rng.uniform(0.4, 0.55), int(rng.integers(2, 6)), rng.uniform(0.03, 0.045), rng.uniform(0, _TAU),
                  0.025)
    parts.append(_transform(main, _translation(0, mast_top, cabin_z) @ _rotation("x", np.pi / 2)))
    if rng.random() < 0.6:
        parts.append(_boxes([0, top * 0.9, cabin_z - rng.uniform(0.03, 0.08)],
                            [radius * 1.1, radius * 0.7, rng.uniform(0.1, 0.16)]))
    bottom = -radius * tall
    if rng.random() < 0.75:
        x, y = rng.uniform(0.9, 1.4) * radius, bottom - rng.uniform(0.04, 0.07)
        z0, z1 = cabin_z - length * 0.4, cabin_z + length * 0.35
        for s in (-1, 1):
            parts.append(_rods([[s * x, y, z0], [s * x, y, z1]], [[s * x, y, z1], [s * x, y + 0.03, z1 + 0.04]], 0.008))
            struts = np.array([[s * x, y, z0 + 0.05], [s * x, y, z1 - 0.08]])
            parts.append(_rods(struts, struts * [0, 0, 1] + [s * radius * 0.5, bottom * 0.7, 0.02], 0.007))
    else:
        wheels = np.array([[0, cabin_z + length * 0.3], [-radius * 0.9, cabin_z - length * 0.2],
                           [radius * 0.9, cabin_z - length * 0.2]])
        y = bottom - 0.04
        parts.append(_rods(np.stack([wheels[:, 0], np.full(3, y), wheels[:, 1]], 1),
                           np.stack([wheels[:, 0] * 0.8, np.full(3, bottom * 0.7), wheels[:, 1]], 1), 0.006))
        parts.append(_rods(np.stack([wheels[:, 0] - 0.01, np.full(3, y), wheels[:, 1]], 1),
                           np.stack([wheels[:, 0] + 0.01, np.full(3, y), wheels[:, 1]], 1), 0.022))
    return parts


_CARS = {
    # body height, cabin height, cabin stations (windshield base, roof front, roof back, rear base), rear height
    "sedan": ((0.14, 0.18), (0.12, 0.15), (0.22, 0.05, -0.18, -0.33), 0.05),
    "hatchback": ((0.14, 0.18), (0.13, 0.16), (0.2, 0.05, -0.36, -0.45), 0.5),
    "suv": ((0.2, 0.26), (0.15, 0.19), (0.22, 0.12, -0.44, -0.48), 0.8),
    "pickup": ((0.2, 0.24), (0.14, 0.17), (0.22, 0.14, -0.06, -0.08), 0.9),
    "van": ((0.2, 0.25), (0.2, 0.28), (0.42, 0.3, -0.47, -0.49), 0.9),
    "sports": ((0.1, 0.13), (0.08, 0.1), (0.1, -0.05, -0.18, -0.4), 0.05),
}


def _car(rng: np.random.Generator) -> list[_Part]:
    """Rounded body, tapered greenhouse, four wheels; mirrors, spoiler, roof rack, pickup bed, exhaust."""
    kind = str(rng.choice(list(_CARS)))
    body_h, cabin_h, stations, rear = _CARS[kind]
    body_h, cabin_h = rng.uniform(*body_h), rng.uniform(*cabin_h)
    width, wheel_r = rng.uniform(0.38, 0.48), rng.uniform(0.07, 0.1) * (1.2 if kind in ("suv", "pickup") else 1)
    clear = wheel_r * rng.uniform(0.5, 0.9)
    z = np.linspace(-0.5, 0.5, 11)
    end = np.clip((np.abs(z) - 0.3) / 0.2, 0, 1) ** 2
    h = body_h * (1 - rng.uniform(0.2, 0.5) * end)
    parts = [_stack(_superellipse(20, rng.uniform(3, 6)), z, np.stack([width / 2 * (1 - 0.12 * end), h / 2], 1),
                    np.stack([0 * z, clear + (body_h - h) * 0.3 + h / 2], 1), axis="z")]
    cabin_w = width * rng.uniform(0.8, 0.92)
    tumble = rng.uniform(0.7, 0.85)
    trapezoid = np.array([[1, 0], [tumble, 1], [-tumble, 1], [-1, 0]], float)
    cz = np.array(stations) * rng.uniform(0.9, 1.1) + rng.uniform(-0.03, 0.03)
    ch = cabin_h * np.array([0.05, 1, 1, rear])
    parts.append(_stack(trapezoid, cz, np.stack([np.full(4, cabin_w / 2), ch], 1),
                        np.stack([np.zeros(4), np.full(4, clear + body_h - 0.01)], 1), axis="z"))
    top = clear + body_h
    axle = rng.uniform(0.28, 0.36)
    tire = rng.uniform(0.06, 0.09)
    wx, wz = width / 2 + 0.005, np.array([axle, axle, -axle, -axle])
    sx = np.array([1, -1, 1, -1])
    parts.append(_rods(np.stack([sx * wx, np.full(4, wheel_r), wz], 1),
                       np.stack([sx * (wx - tire), np.full(4, wheel_r), wz], 1), wheel_r))
    parts.append(_boxes([[s * (width / 2 + 0.005), top - 0.005, cz[0] - 0.03] for s in (-1, 1)], [0.05, 0.025, 0.02]))
    if kind == "pickup":
        bed_z0, bed_z1 = -0.5, cz[3] - 0.02
        wall = rng.uniform(0.06, 0.1)
        parts.append(_boxes([[-width / 2 + 0.01, top + wall / 2, (bed_z0 + bed_z1) / 2],
                             [width / 2 - 0.01, top + wall / 2, (bed_z0 + bed_z1) / 2],
                             [0, top + wall / 2, bed_z0 + 0.01]],
                            [[0.02, wall, bed_z1 - bed_z0], [0.02, wall, bed_z1 - bed_z0], [width, wall, 0.02]]))
    if kind in ("sports", "sedan") and rng.random() < 0.4:
        sz = -0.5 + 0.05
        parts.append(_boxes([[0, top + 0.05, sz], [-width / 3, top + 0.025, sz], [width / 3, top + 0.025, sz]],
                            [[width * 0.9, 0.012, 0.06], [0.015, 0.05, 0.03], [0.015, 0.05, 0.03]]))
    roof = clear + body_h + cabin_h
    if kind == "suv" and rng.random() < 0.5:
        parts.append(_rods([[s * cabin_w * 0.3, roof + 0.015, cz[1]] for s in (-1, 1)],
                           [[s * cabin_w * 0.3, roof + 0.015, cz[2]] for s in (-1, 1)], 0.008))
    if rng.random() < 0.6:
        ex = rng.choice((-1, 1)) * width * rng.uniform(0.2, 0.35)
        parts.append(_rods([ex, clear + 0.01, -0.52], [ex, clear + 0.01, -0.4], 0.012))
    if rng.random() < 0.2:
        ax = rng.choice((-1, 1)) * cabin_w * 0.3
        parts.append(_rods([ax, roof - 0.01, cz[2]], [ax, roof + rng.uniform(0.1, 0.2), cz[2] - 0.05], 0.003))
    return parts


def _chair(rng: np.random.Generator) -> list[_Part]:
    """Seat and backrest on four legs, an office star base or sled runners, maybe armrests."""
    width, depth = rng.uniform(0.4, 0.55), rng.uniform(0.38, 0.52)
    thick, seat_y = rng.uniform(0.03, 0.08), rng.uniform(0.4, 0.5)
    base = rng.choice(("legs", "legs", "office", "sled"))
    parts = [_slab(width, thick, depth, (0, seat_y - thick / 2, 0), rng.uniform(3, 10), 0.3)]
    under = seat_y - thick
    if base == "legs":
        inset = rng.uniform(0.02, 0.05)
        parts.append(_legs(_corners(width / 2 - inset, depth / 2 - inset), under, rng.uniform(0.012, 0.025),
                           rng.uniform(0, 0.12), rng.random() < 0.5))
        if rng.random() < 0.4:
            y = under * rng.uniform(0.2, 0.4)
            c = _corners(width / 2 - inset, depth / 2 - inset)
            ends = np.concatenate([c, np.roll(c, -1, axis=0)], 1)
            parts.append(_rods(np.insert(ends[:, :2], 1, y, axis=1), np.insert(ends[:, 2:], 1, y, axis=1), 0.008))
    elif base == "office":
        parts.append(_rods([0, 0.06, 0], [0, under, 0], 0.025))
        angle = rng.uniform(0, _TAU) + _TAU * np.arange(5) / 5
        feet = rng.uniform(0.28, 0.34) * np.stack([np.cos(angle), np.full(5, 0.15), np.sin(angle)], 1)
        parts.append(_rods(np.broadcast_to([0.0, 0.07, 0.0], (5, 3)), feet, 0.018, _CUBE))
        parts.append(_boxes(feet - [0, 0.02, 0], 0.05, _SPHERE))
    else:
        x = width / 2 - 0.02
        for s in (-1, 1):
            path = np.array([[s * x, under, depth / 2 - 0.03], [s * x, 0.01, depth / 2 + 0.02],
                             [s * x, 0.01, -depth / 2], [s * x, under, -depth / 2 + 0.03]])
            parts.append(_rods(path[:-1], path[1:], 0.012))
    back_h, tilt = rng.uniform(0.3, 0.55), np.radians(rng.uniform(0, 18))
    back = _panel(rng, width * rng.uniform(0.85, 1.0), back_h, rng.uniform(0.02, 0.05))
    parts.append(_transform(back, _translation(0, seat_y - 0.01, -depth / 2 + 0.02) @ _rotation("x", -tilt)))
    if rng.random() < (0.5 if base == "office" else 0.3):
        arm_y, x = seat_y + rng.uniform(0.17, 0.25), width / 2 + 0.03
        pads = np.array([[s * x, arm_y, -0.02] for s in (-1, 1)])
        parts.append(_boxes(pads, [0.05, 0.025, depth * 0.8]))
        front = pads + [0, 0, depth * 0.25]
        parts.append(_rods(front, front * [1, 0, 1] + [0, seat_y - thick, 0], 0.012))
    return parts


def _bookshelf(rng: np.random.Generator) -> list[_Part]:
    """Side panels, top and bottom, shelves, maybe a back panel, dividers, lower doors and books."""
    width, height, depth = rng.uniform(0.5, 1.4), rng.uniform(0.6, 2.0), rng.uniform(0.22, 0.4)
    t = rng.uniform(0.015, 0.035)
    plinth = rng.uniform(0.0, 0.08)
    n = max(1, int(round(height / rng.uniform(0.25, 0.42))))
    levels = plinth + t / 2 + (height - plinth - t) * np.arange(n + 1) / n
    levels[1:-1] += rng.uniform(-0.3, 0.3, n - 1) * (height - plinth) / n * 0.3
    centers = [[s * (width - t) / 2, height / 2, 0] for s in (-1, 1)] + [[0, y, 0] for y in levels]
    sizes = [[t, height, depth]] * 2 + [[width - 2 * t, t, depth]] * (n + 1)
    if plinth > 0:
        centers.append([0, plinth / 2, depth / 2 - 0.02])
        sizes.append([width - 2 * t, plinth, t])
    if rng.random() < 0.7:
        centers.append([0, height / 2, -depth / 2 + t / 4])
        sizes.append([width, height, t / 2])
    parts = [_boxes(centers, sizes)]
    inner = width - 2 * t
    doors = int(rng.integers(1, min(n, 2) + 1)) if rng.random() < 0.3 else 0
    if doors:
        y0, y1 = levels[0] + t / 2, levels[doors] - t / 2
        panels = 1 if inner < 0.6 else 2
        for i in range(panels):
            x0 = -inner / 2 + i * inner / panels
            parts.append(_drawers(x0, x0 + inner / panels, y0, y1, depth / 2, 1, rng.random() < 0.5))
    for lo, hi in zip(levels[doors:-1], levels[doors + 1:]):
        gap = hi - lo - t
        if rng.random() < 0.25:
            dx = rng.uniform(-0.3, 0.3) * inner
            parts.append(_boxes([dx, lo + gap / 2 + t / 2, 0], [t, gap, depth]))
        if rng.random() < 0.6:
            k = int(rng.integers(4, 20))
            thick = rng.uniform(0.015, 0.05, k)
            x = np.cumsum(thick) - thick / 2
            keep = x + thick / 2 < inner * rng.uniform(0.4, 1.0)
            if keep.any():
                thick, x = thick[keep], x[keep]
                tall = gap * rng.uniform(0.55, 0.92, len(x))
                sign = rng.choice((-1, 1))
                book_d = depth * rng.uniform(0.6, 0.9)
                parts.append(_boxes(np.stack([sign * (inner / 2 - x), lo + t / 2 + tall / 2,
                                              np.full(len(x), depth / 2 - book_d / 2 - 0.01)], 1),
                                    np.stack([thick * 0.95, tall, np.full(len(x), book_d)], 1)))
    return parts


def _desk(rng: np.random.Generator) -> list[_Part]:
    """Top on drawer pedestals, panels or legs; maybe a modesty panel, hutch, return wing, tray."""
    width, depth = rng.uniform(1.0, 1.8), rng.uniform(0.5, 0.8)
    t, height = rng.uniform(0.025, 0.05), rng.uniform(0.7, 0.78)
    parts = [_slab(width, t, depth, (0, height - t / 2, 0), 14, 0.2)]
    under = height - t
    support = rng.choice(("pedestals", "pedestal_panel", "panels", "legs"))
    ped_w = rng.uniform(0.3, 0.45)
    left, right = -width / 2 + 0.02, width / 2 - 0.02
    if support == "legs":
        parts.append(_legs(_corners(width / 2 - 0.05, depth / 2 - 0.05), under, rng.uniform(0.015, 0.03),
                           0, rng.random() < 0.6))
    else:
        sides = {"pedestals": ("ped", "ped"), "pedestal_panel": ("ped", "panel"), "panels": ("panel", "panel")}[support]
        for side, x_out in zip(rng.permutation(sides), (left, right)):
            w = ped_w if side == "ped" else 0.03
            cx = x_out + np.sign(-x_out) * w / 2
            parts.append(_boxes([cx, under / 2, 0], [w, under, depth - 0.04]))
            if side == "ped":
                parts.append(_drawers(cx - w / 2, cx + w / 2, 0.05, under - 0.02, depth / 2 - 0.02,
                                      int(rng.integers(2, 5)), rng.random() < 0.5))
    if support != "legs" and rng.random() < 0.6:
        parts.append(_boxes([0, under * 0.6, -depth / 2 + 0.06], [width - 0.1, under * 0.6, 0.02]))
    if rng.random() < 0.25:
        hutch_h, hutch_d = rng.uniform(0.3, 0.6), depth * rng.uniform(0.3, 0.45)
        z = -depth / 2 + hutch_d / 2
        parts.append(_boxes([[left + 0.01, height + hutch_h / 2, z], [right - 0.01, height + hutch_h / 2, z],
                             [0, height + hutch_h, z], [0, height + hutch_h * 0.5, z]],
                            [[0.02, hutch_h, hutch_d], [0.02, hutch_h, hutch_d], [width, 0.02, hutch_d],
                             [width - 0.04, 0.02, hutch_d]]))
    if rng.random() < 0.2:
        side = rng.choice((-1, 1))
        length = rng.uniform(0.6, 1.0)
        x = side * (width / 2 - depth / 2)
        parts.append(_boxes([[x, height - t / 2, depth / 2 + length / 2], [x, under / 2, depth / 2 + length - 0.02]],
                            [[depth, t, length], [depth - 0.04, under, 0.03]]))
    if rng.random() < 0.2:
        parts.append(_boxes([0, under - 0.06, depth / 2 - 0.2], [width * 0.4, 0.015, 0.35]))
    return parts


def _polar_union(angles: np.ndarray, ellipses: np.ndarray) -> np.ndarray:
    """Boundary of a union of ellipses (cx, cy, a, b, rotation) that all contain the origin, as (N, 2)."""
    cx, cy, a, b, rot = ellipses.T[:, :, None]
    c, s = np.cos(angles - rot), np.sin(angles - rot)
    ox, oy = -(cx * np.cos(rot) + cy * np.sin(rot)), cx * np.sin(rot) - cy * np.cos(rot)
    qa = (c / a) ** 2 + (s / b) ** 2
    qb = 2 * (c * ox / a**2 + s * oy / b**2)
    qc = (ox / a) ** 2 + (oy / b) ** 2 - 1
    r = ((-qb + np.sqrt(qb**2 - 4 * qa * qc)) / (2 * qa)).max(0)
    return np.stack([r * np.cos(angles), r * np.sin(angles)], 1)


def _guitar(rng: np.random.Generator) -> list[_Part]:
    """Waisted (acoustic) or horned (electric) body, neck with frets, tilted headstock with pegs."""
    acoustic = rng.random() < 0.5
    body_l = rng.uniform(0.4, 0.5) if acoustic else rng.uniform(0.33, 0.42)
    body_w = body_l * rng.uniform(0.7, 0.85)
    depth = rng.uniform(0.08, 0.12) if acoustic else rng.uniform(0.035, 0.05)
    if acoustic:
        ellipses = [[0, -0.2 * body_l, body_w / 2, 0.3 * body_l, 0],
                    [0, 0.23 * body_l, body_w * rng.uniform(0.34, 0.42), 0.27 * body_l, 0]]
    else:
        ellipses = [[0, -0.15 * body_l, body_w / 2, 0.35 * body_l, 0], [0, 0.1 * body_l, body_w * 0.3, 0.3 * body_l, 0]]
        horns = ((rng.uniform(95, 115), rng.uniform(0.5, 0.65)), (rng.uniform(60, 80), rng.uniform(0.3, 0.5)))
        for phi, reach in horns:
            phi, reach = np.radians(phi), reach * body_l
            ellipses.append([reach / 2 * np.cos(phi), reach / 2 * np.sin(phi), reach / 2 + 0.02,
                             rng.uniform(0.07, 0.11) * body_l, phi])
    outline = _polar_union(np.linspace(0, _TAU, 64, endpoint=False), np.array(ellipses))
    parts = [_stack(outline, depth * np.array([-0.5, -0.35, 0.35, 0.5]), np.array([[0.96], [1], [1], [0.96]]),
                    axis="z")]
    nut = 0.5 * body_l + rng.uniform(0.4, 0.5)
    neck_w = rng.uniform(0.045, 0.06)
    neck_t = rng.uniform(0.02, 0.03)
    neck_z = 0.35 * depth + neck_t / 2
    neck_start = 0.35 * body_l
    neck_size = np.array([[neck_w / 2, neck_t / 2], [neck_w * 0.42, neck_t / 2]])
    parts.append(_stack(_superellipse(12, 4), [neck_start, nut], neck_size, (0, neck_z), axis="y"))
    scale_l = 2 * (nut - (-0.2 * body_l))
    frets = nut - scale_l * (1 - 2.0 ** (-np.arange(1, int(rng.integers(12, 21))) / 12))
    frets = frets[frets > neck_start + 0.02]
    parts.append(_boxes(np.stack([np.zeros(len(frets)), frets, np.full(len(frets), neck_z + neck_t / 2)], 1),
                        [neck_w * 0.9, 0.003, 0.004]))
    head_l, head_w = rng.uniform(0.12, 0.18), rng.uniform(0.06, 0.09)
    inline = not acoustic and rng.random() < 0.6
    tilt = 0 if inline else np.radians(rng.uniform(5, 15))
    pegs_y = (np.arange(6) % 3 + 1) * head_l / 4 if not inline else (np.arange(6) + 0.5) * head_l / 6.5
    pegs_x = np.where(np.arange(6) < 3, -1, 1) * head_w / 2 if not inline else np.full(6, -head_w / 2)
    pegs_at = np.stack([pegs_x, pegs_y, np.zeros(6)], 1)
    pegs = _rods(pegs_at, pegs_at + np.stack([np.sign(pegs_x) * 0.035, np.zeros(6), np.zeros(6)], 1), 0.005)
    head = _merge([_boxes([0, head_l / 2, 0], [head_w, head_l, 0.016]), pegs])
    parts.append(_transform(head, _translation(0, nut, neck_z) @ _rotation("x", -tilt)))
    bridge_y = -0.2 * body_l
    parts.append(_boxes([0, bridge_y, depth / 2], [body_w * 0.35, 0.02, 0.012]))
    if acoustic:
        parts.append(_transform(_torus(body_w * 0.12, 0.006, n_major=32, n_minor=6),
                                _translation(0, 0.12 * body_l, depth / 2) @ _rotation("x", np.pi / 2)))
    else:
        k = int(rng.integers(1, 4))
        parts.append(_boxes(np.stack([np.zeros(k), bridge_y + 0.05 + 0.05 * np.arange(k), np.full(k, depth / 2)], 1),
                            [neck_w * 1.2, 0.025, 0.012]))
        k = int(rng.integers(2, 5))
        knobs = np.stack([body_w * (0.22 + 0.06 * (np.arange(k) % 2)), bridge_y - body_l * (0.05 + 0.05 * np.arange(k)),
                          np.full(k, depth / 2)], 1)
        parts.append(_rods(knobs, knobs + [0, 0, 0.02], 0.01))
    if rng.random() < 0.5:
        guard = _superellipse(16) * [body_w * 0.15, body_l * 0.15]
        parts.append(_stack(guard, [depth / 2 - 0.002, depth / 2 + 0.003], shift=(body_w * 0.2, 0.05 * body_l),
                            axis="z"))
    return parts


def _bed(rng: np.random.Generator) -> list[_Part]:
    """Frame on legs, mattress, headboard, maybe a footboard, pillows, blanket or four posts."""
    length, width = rng.uniform(1.9, 2.2), rng.uniform(0.9, 2.0)
    frame_y, frame_h = rng.uniform(0.1, 0.25), rng.uniform(0.12, 0.25)
    top = frame_y + frame_h
    mattress = rng.uniform(0.15, 0.3)
    parts = [_boxes([0, frame_y + frame_h / 2, 0], [width, frame_h, length]),
             _slab(width - 0.04, mattress, length - 0.06, (0, top + mattress / 2, 0.01), rng.uniform(6, 12), 0.3),
             _legs(_corners(width / 2 - 0.05, length / 2 - 0.05), frame_y, rng.uniform(0.02, 0.04), 0,
                   rng.random() < 0.7)]
    head_h = rng.uniform(0.5, 1.2)
    head = _panel(rng, width + 0.04, head_h, rng.uniform(0.03, 0.07))
    parts.append(_transform(head, _translation(0, 0, -length / 2)))
    if rng.random() < 0.5:
        foot = _panel(rng, width + 0.04, head_h * rng.uniform(0.5, 0.8), 0.04)
        parts.append(_transform(foot, _translation(0, 0, length / 2)))
    n_pillows = 1 if width < 1.3 else int(rng.integers(1, 3))
    pillow_w = rng.uniform(0.45, 0.7)
    xs = [rng.uniform(-0.2, 0.2) * width] if n_pillows == 1 else [-width / 4, width / 4]
    pillow_y = top + mattress + 0.05
    parts.append(_boxes([[x, pillow_y, -length / 2 + 0.3] for x in xs], [pillow_w, 0.14, 0.38], _SPHERE))
    if rng.random() < 0.4:
        cover = rng.uniform(0.4, 0.7) * length
        parts.append(_boxes([0, top + mattress * 0.55, length / 2 - cover / 2],
                            [width + 0.04, mattress * 1.1 + 0.02, cover]))
    if rng.random() < 0.15:
        post_h = rng.uniform(1.6, 2.1)
        c = _corners(width / 2 + 0.02, length / 2)
        parts.append(_legs(c, post_h, 0.03))
        parts.append(_rods(np.insert(c, 1, post_h, axis=1), np.insert(np.roll(c, -1, 0), 1, post_h, axis=1), 0.02))
    return parts


def _desk_lamp(rng: np.random.Generator) -> list[_Part]:
    """Base, two-segment articulated arm (single or parallel rods), tilted shade with a bulb."""
    base_w, base_d, base_t = rng.uniform(0.15, 0.25), rng.uniform(0.12, 0.22), rng.uniform(0.02, 0.05)
    parts = [_slab(base_w, base_t, base_d, (0, base_t / 2, 0), rng.choice((2.0, 4.0, 10.0)), 0.3)]
    p0 = np.array([0, base_t, -rng.uniform(0, 0.3) * base_d])
    a1, a2 = np.radians(rng.uniform(-30, 35)), np.radians(rng.uniform(50, 115))
    l1, l2 = rng.uniform(0.3, 0.45), rng.uniform(0.25, 0.45)
    p1 = p0 + l1 * np.array([0, np.cos(a1), np.sin(a1)])
    p2 = p1 + l2 * np.array([0, np.cos(a2), np.sin(a2)])
    gap = rng.uniform(0.015, 0.03) if rng.random() < 0.5 else 0.0
    offsets = np.array([[-gap, 0, 0], [gap, 0, 0]]) if gap else np.zeros((1, 3))
    r = rng.uniform(0.006, 0.012)
    arm = [_rods(np.concatenate([p0 + offsets, p1 + offsets]), np.concatenate([p1 + offsets, p2 + offsets]), r),
           _rods(np.stack([p0, p1, p2]) - [gap + 0.02, 0, 0], np.stack([p0, p1, p2]) + [gap + 0.02, 0, 0], r * 1.8)]
    if rng.random() < 0.4:
        arm.append(_rods(p0 + [0, 0.05, -0.03], p1 * 0.6 + p0 * 0.4 + [0, 0, -0.03], r * 1.5))
    a3 = np.radians(rng.uniform(120, 200))
    direction = np.array([0, np.cos(a3), np.sin(a3)])
    frame = np.eye(4)
    frame[:3, :3] = _frames(direction[None])[0]
    frame[:3, 3] = p2
    if rng.random() < 0.75:
        r0, r1, shade_l = rng.uniform(0.02, 0.04), rng.uniform(0.06, 0.11), rng.uniform(0.1, 0.18)
        shade = _stack(_superellipse(16), [0, shade_l * 0.35, shade_l], np.array([[r0], [r0 * 1.15], [r1]]))
        bulb = _boxes([0, shade_l * 0.75, 0], r1 * 0.9, _SPHERE)
        arm += [_transform(shade, frame), _transform(bulb, frame)]
    else:
        head_l = rng.uniform(0.15, 0.3)
        arm.append(_transform(_boxes([0, 0.01, head_l / 2 - 0.02], [0.05, 0.02, head_l]), frame))
    yaw = _translation(*p0) @ _rotation("y", np.radians(rng.uniform(-50, 50))) @ _translation(*-p0)
    parts += [_transform(p, yaw) for p in arm]
    corner = rng.choice((-1, 1))
    parts.append(_boxes([corner * base_w * 0.3, base_t + 0.008, base_d * 0.3], [0.02, 0.016, 0.03]))
    return parts


def _monitor(rng: np.random.Generator) -> list[_Part]:
    """Bezel frame around a recessed screen, back housing (flat or CRT), stand, buttons, webcam."""
    width = rng.uniform(0.5, 0.75)
    height = width / rng.choice((16 / 9, 16 / 10, 4 / 3, 21 / 9))
    t, border = rng.uniform(0.012, 0.03), rng.uniform(0.008, 0.04)
    crt = rng.random() < 0.15
    screen = [
        _boxes([[0, (height - border) / 2, 0], [0, -(height - border) / 2, 0], [-(width - border) / 2, 0, 0],
                [(width - border) / 2, 0, 0], [0, 0, -t * 0.2]],
               [[width, border, t], [width, border, t], [border, height, t], [border, height, t],
                [width, height, t * 0.6]])]
    if crt:
        back_l = width * rng.uniform(0.6, 0.9)
        screen.append(_stack(_SQUARE, [-t / 2, -back_l], np.array([[width / 2, height / 2], [width / 5, height / 5]]),
                             axis="z"))
    elif rng.random() < 0.7:
        screen.append(_boxes([0, rng.uniform(-0.1, 0.05) * height, -t / 2 - 0.015],
                             [width * rng.uniform(0.4, 0.8), height * rng.uniform(0.4, 0.8), 0.03]))
    k = int(rng.integers(2, 6))
    screen.append(_boxes(np.stack([width / 2 - border - 0.02 * np.arange(1, k + 1), np.full(k, -height / 2),
                                   np.full(k, t * 0.3)], 1), [0.01, 0.006, 0.01]))
    if rng.random() < 0.3:
        screen.append(_boxes([0, height / 2 + 0.01, 0], [0.05, 0.02, 0.02]))
    stand = rng.choice(("plate", "v", "feet"))
    neck_h = rng.uniform(0.05, 0.2)
    back_z = -t / 2 - (0.3 * width if crt else 0.03)
    if stand == "feet":
        center_y = 0.03 + height / 2
        feet = [[s * width * rng.uniform(0.3, 0.42), 0.015, 0] for s in (-1, 1)]
        parts = [_boxes(feet, [0.03, 0.03, rng.uniform(0.15, 0.25)]),
                 _rods(np.array(feet) + [0, 0.015, 0], np.array(feet) + [0, 0.04 + border, 0], 0.01, _CUBE)]
    else:
        center_y = 0.02 + neck_h + height / 2
        foot_w, foot_d = rng.uniform(0.2, 0.35), rng.uniform(0.15, 0.25)
        if stand == "plate":
            foot = _slab(foot_w, 0.02, foot_d, (0, 0.01, back_z), rng.uniform(2, 10), 0.3)
        else:
            tips = np.array([[s * foot_w / 2, 0.01, back_z + foot_d] for s in (-1, 1)])
            foot = _rods(np.array([[0, 0.01, back_z]] * 2), tips, 0.012, _CUBE)
        parts = [foot, _rods([0, 0.01, back_z], [0, center_y, back_z], rng.uniform(0.015, 0.035), _CUBE)]
    tilt = np.radians(rng.uniform(-5, 12))
    parts += [_transform(p, _translation(0, center_y, 0) @ _rotation("x", -tilt)) for p in screen]
    return parts


def _keys(n_white: int, key_w: float, depth: float, y: float, z_front: float) -> _Part:
    """A keyboard: ``n_white`` white keys and the black keys of the 2-3 pattern, fronts at z_front."""
    x = (np.arange(n_white) - (n_white - 1) / 2) * key_w
    black = x[:-1][np.isin(np.arange(n_white - 1) % 7, (0, 1, 3, 4, 5))] + key_w / 2
    white = _boxes(np.stack([x, np.full(n_white, y), np.full(n_white, z_front - depth / 2)], 1),
                   [key_w * 0.92, 0.02, depth])
    black = _boxes(np.stack([black, np.full(len(black), y + 0.015), np.full(len(black), z_front - depth * 0.65)], 1),
                   [key_w * 0.55, 0.02, depth * 0.6])
    return _merge([white, black])


def _piano(rng: np.random.Generator) -> list[_Part]:
    """Upright piano (case, cheeks, keys, fallboard, music desk, pedals) or a digital piano on a stand."""
    n_white, key_w = int(rng.choice((36, 52))), rng.uniform(0.021, 0.024)
    cheek = rng.uniform(0.04, 0.1)
    width = n_white * key_w + 2 * cheek
    key_y, key_d = rng.uniform(0.68, 0.76), rng.uniform(0.13, 0.16)
    if rng.random() < 0.65:
        height, case_d = rng.uniform(1.0, 1.35), rng.uniform(0.3, 0.4)
        front = case_d / 2 + key_d + 0.02
        parts = [_boxes([[0, height / 2, 0], [0, key_y - 0.06, case_d / 2 + key_d / 2],
                         [-(width - cheek) / 2, key_y - 0.02, front - key_d / 2 - 0.01],
                         [(width - cheek) / 2, key_y - 0.02, front - key_d / 2 - 0.01],
                         [0, key_y + 0.08, case_d / 2 + 0.03]],
                        [[width, height, case_d], [width, 0.08, key_d], [cheek, 0.16, key_d + 0.02],
                         [cheek, 0.16, key_d + 0.02], [width - 2 * cheek, 0.12, 0.06]])]
        parts.append(_rods([[s * (width - cheek) / 2, 0.0, front - 0.04] for s in (-1, 1)],
                           [[s * (width - cheek) / 2, key_y - 0.1, front - 0.04] for s in (-1, 1)],
                           rng.uniform(0.025, 0.04), _CUBE if rng.random() < 0.6 else _CYLINDER))
        k = int(rng.integers(2, 4))
        pedals = np.stack([(np.arange(k) - (k - 1) / 2) * 0.07, np.full(k, 0.04), np.full(k, case_d / 2 + 0.05)], 1)
        parts.append(_boxes(pedals, [0.03, 0.015, 0.1]))
        if rng.random() < 0.6:
            desk_h = rng.uniform(0.15, 0.3)
            stand = _boxes([0, desk_h / 2, 0], [width * rng.uniform(0.4, 0.7), desk_h, 0.015])
            parts.append(_transform(stand, _translation(0, key_y + 0.14, case_d / 2 + 0.04) @ _rotation("x", -0.25)))
    else:
        body_d = key_d + rng.uniform(0.12, 0.2)
        front = body_d / 2
        parts = [_slab(width, 0.08, body_d, (0, key_y - 0.05, 0), 12, 0.3)]
        stand = rng.choice(("panels", "x", "legs"))
        if stand == "panels":
            side_y = (key_y - 0.09) / 2
            parts.append(_boxes([[-(width / 2 - 0.03), side_y, 0], [width / 2 - 0.03, side_y, 0],
                                 [0, 0.25, -body_d / 2 + 0.02]],
                                [[0.03, 2 * side_y, body_d], [0.03, 2 * side_y, body_d], [width - 0.06, 0.3, 0.02]]))
        elif stand == "x":
            spread = rng.uniform(0.3, 0.45)
            feet = np.array([[s * spread, 0.0, z] for s in (-1, 1) for z in (-0.2, 0.2)])
            parts.append(_rods(feet, feet * [-1, 0, 1] + [0, key_y - 0.09, 0], 0.02, _CUBE))
        else:
            parts.append(_legs(_corners(width / 2 - 0.05, body_d / 2 - 0.04), key_y - 0.09, 0.02, 0, True))
    parts.append(_keys(n_white, key_w, key_d, key_y, front))
    if rng.random() < 0.4:
        bench_w, bench_z = rng.uniform(0.5, 0.8), front + rng.uniform(0.25, 0.45)
        parts.append(_slab(bench_w, 0.05, 0.32, (0, 0.47, bench_z), 14, 0.3))
        parts.append(_legs(_corners(bench_w / 2 - 0.04, 0.12) + [0, bench_z], 0.45, 0.02, 0, True))
    return parts


def _plant(rng: np.random.Generator) -> list[_Part]:
    """Polygonal tapered pot with a rim; branching stems with leaves, or a rosette of long leaves."""
    pot_r, pot_h = rng.uniform(0.08, 0.15), rng.uniform(0.12, 0.3)
    outline = _superellipse(int(rng.choice((4, 6, 8, 16))), rng.choice((2.0, 2.0, 5.0)))
    parts = [_stack(outline, [0, pot_h], np.array([[rng.uniform(0.65, 0.95)], [1.0]]) * pot_r)]
    if rng.random() < 0.6:
        parts.append(_stack(outline, [pot_h - 0.03, pot_h + 0.01], pot_r * 1.1))
    if rng.random() < 0.6:
        length = rng.uniform(0.2, 0.4)
        tips, dirs = _branches(rng, np.array([0, pot_h, 0]), length, rng.uniform(0.005, 0.012), parts)
        per_tip = int(rng.integers(1, 4))
        tips, dirs = np.repeat(tips, per_tip, 0), np.repeat(dirs, per_tip, 0)
        dirs = dirs + rng.normal(0, 0.5, dirs.shape)
        leaf_l, leaf_w = length * rng.uniform(0.4, 0.7), rng.uniform(0.25, 0.5)
    else:
        n = int(rng.integers(6, 18))
        az, el = rng.uniform(0, _TAU, n), np.radians(rng.uniform(25, 80, n))
        dirs = np.stack([np.cos(az) * np.cos(el), np.sin(el), np.sin(az) * np.cos(el)], 1)
        tips = np.array([0, pot_h, 0]) + dirs * rng.uniform(0, 0.3, (n, 1)) * pot_r
        leaf_l, leaf_w = rng.uniform(0.25, 0.6), rng.uniform(0.1, 0.25)
        if rng.random() < 0.5:
            dx, dz = rng.uniform(-0.3, 0.3, 2) * pot_r
            stalk = np.array([dx, pot_h + rng.uniform(0.3, 0.6), dz])
            parts += [_rods([0, pot_h, 0], stalk, 0.006), _boxes(stalk, rng.uniform(0.03, 0.06), _SPHERE)]
    frames = _frames(dirs)
    roll = rng.uniform(0, np.pi, len(tips))
    across = frames[:, :, 0] * np.cos(roll)[:, None] + frames[:, :, 2] * np.sin(roll)[:, None]
    half = leaf_l / 2 * rng.uniform(0.7, 1.0, (len(tips), 1))
    normal = np.cross(across, frames[:, :, 1])
    linear = np.stack([across * half * leaf_w, frames[:, :, 1] * half, normal * half * 0.04], 2)
    parts.append(_instances(_LEAF, linear, tips + frames[:, :, 1] * half))
    return parts


def _branches(rng: np.random.Generator, root: np.ndarray, length: float, radius: float,
              parts: list[_Part]) -> tuple[np.ndarray, np.ndarray]:
    """Grow 1-3 stems from ``root`` that fork twice or three times; add them to ``parts``.

    Returns the tip points and their unit growth directions.
    """
    trunks = int(rng.integers(1, 4))
    points = root + rng.normal(0, 0.02, (trunks, 3)) * [1, 0, 1]
    dirs = np.array([0.0, 1.0, 0.0]) + rng.normal(0, 0.35, (trunks, 3))
    for _ in range(int(rng.integers(2, 4))):
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        ends = points + dirs * length * rng.uniform(0.7, 1.0, (len(points), 1))
        parts.append(_rods(points, ends, radius, _TWIG))
        points = np.repeat(ends, 2, 0)
        dirs = np.repeat(dirs, 2, 0) + rng.normal(0, 0.6, (len(points), 3)) + [0, 0.3, 0]
        length, radius = length * rng.uniform(0.55, 0.8), radius * 0.7
    return points, dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def _sofa(rng: np.random.Generator) -> list[_Part]:
    """Base, seat and back cushions, arms (maybe rolled), legs, maybe a chaise and throw pillows."""
    width, depth = rng.uniform(1.4, 2.4), rng.uniform(0.8, 1.0)
    leg_h = rng.uniform(0.0, 0.12)
    seat_y, arm_h, back_h = rng.uniform(0.38, 0.45), rng.uniform(0.55, 0.7), rng.uniform(0.75, 0.95)
    cushion_t, back_t = rng.uniform(0.1, 0.18), rng.uniform(0.12, 0.22)
    base_top = seat_y - cushion_t
    arm_w = rng.uniform(0.08, 0.25) if rng.random() < 0.9 else 0.0
    inner = width - 2 * arm_w
    parts = [_boxes([[0, (leg_h + base_top) / 2, 0], [0, (leg_h + back_h) / 2, -depth / 2 + back_t / 2]],
                    [[width, base_top - leg_h, depth], [width, back_h - leg_h, back_t]])]
    if leg_h > 0.03:
        parts.append(_legs(_corners(width / 2 - 0.06, depth / 2 - 0.06), leg_h, 0.025, 0.1, rng.random() < 0.5))
    n = int(np.clip(round(inner / rng.uniform(0.5, 0.8)), 1, 4))
    seat_d = depth - back_t
    xs = -inner / 2 + inner * (np.arange(n) + 0.5) / n
    exponent = rng.uniform(6, 14)
    parts += [_slab(inner / n - 0.01, cushion_t, seat_d, (x, base_top + cushion_t / 2, back_t / 2), exponent)
              for x in xs]
    lean = np.radians(rng.uniform(5, 15))
    cushion_h = back_h - seat_y + rng.uniform(-0.05, 0.05)
    backs = [_slab(inner / n - 0.01, back_t * 0.8, cushion_h, (x, 0, 0), exponent) for x in xs]
    place = (_translation(0, seat_y, -depth / 2 + back_t * 1.2) @ _rotation("x", -lean)
             @ _translation(0, cushion_h / 2, 0) @ _rotation("x", np.pi / 2))
    parts += [_transform(b, place) for b in backs]
    if arm_w:
        rolled = rng.random() < 0.3
        arms = [[s * (width - arm_w) / 2, (leg_h + arm_h) / 2, 0] for s in (-1, 1)]
        parts.append(_boxes(arms, [arm_w, arm_h - leg_h, depth]))
        if rolled:
            parts.append(_rods([[s * (width - arm_w) / 2, arm_h, -depth / 2] for s in (-1, 1)],
                               [[s * (width - arm_w) / 2, arm_h, depth / 2 + 0.02] for s in (-1, 1)], arm_w * 0.6))
    if rng.random() < 0.25:
        side, chaise_l = rng.choice((-1, 1)), rng.uniform(0.5, 0.8)
        x = side * (width / 2 - arm_w - inner / n / 2)
        w = inner / n
        z = depth / 2 + chaise_l / 2
        parts.append(_boxes([x, (leg_h + base_top) / 2, z], [w, base_top - leg_h, chaise_l]))
        parts.append(_slab(w - 0.01, cushion_t, chaise_l, (x, base_top + cushion_t / 2, z - 0.01), exponent))
    if rng.random() < 0.4:
        k = int(rng.integers(1, 4))
        px = rng.uniform(-0.45, 0.45, k) * inner
        linear = np.broadcast_to(_rotation("x", -0.4)[:3, :3] @ np.diag([0.2, 0.2, 0.07]), (k, 3, 3))
        centers = np.stack([px, np.full(k, seat_y + 0.17), np.full(k, -depth / 2 + back_t + 0.1)], 1)
        parts.append(_instances(_SPHERE, linear, centers))
    return parts


def _table(rng: np.random.Generator) -> list[_Part]:
    """Rectangular, rounded or oval top on legs (apron, shelf), a trestle or a footed pedestal.

    No round tops: a disc on a pedestal is nearly axisymmetric.
    """
    shape = rng.choice(("rect", "rect", "rounded", "oval"))
    length = rng.uniform(0.8, 2.2)
    width = length * (rng.uniform(0.45, 0.65) if shape == "oval" else min(rng.uniform(0.6, 1.1) / length, 0.9))
    t, height = rng.uniform(0.02, 0.06), rng.uniform(0.42, 0.78)
    exponent = {"rect": 20.0, "rounded": 5.0, "oval": 2.0}[shape]
    parts = [_slab(length, t, width, (0, height - t / 2, 0), exponent, 0.25)]
    under = height - t
    support = rng.choice(("legs", "legs", "trestle", "pedestal"))
    inset = {"rect": 0.08, "rounded": 0.12, "oval": 0.35}[shape]
    hx, hz = length / 2 * (1 - inset), width / 2 * (1 - inset)
    if support == "legs":
        square = rng.random() < 0.6
        parts.append(_legs(_corners(hx, hz), under, rng.uniform(0.015, 0.04), rng.uniform(0, 0.08), square))
        if rng.random() < 0.5:
            apron = rng.uniform(0.06, 0.12)
            parts.append(_boxes([[0, under - apron / 2, hz], [0, under - apron / 2, -hz], [hx, under - apron / 2, 0],
                                 [-hx, under - apron / 2, 0]],
                                [[2 * hx, apron, 0.02], [2 * hx, apron, 0.02], [0.02, apron, 2 * hz],
                                 [0.02, apron, 2 * hz]]))
        if rng.random() < 0.2:
            parts.append(_boxes([0, under * rng.uniform(0.15, 0.35), 0], [2 * hx, 0.02, 2 * hz]))
        if rng.random() < 0.2:
            x0 = rng.uniform(-0.9, 0.3) * hx
            parts.append(_drawers(x0, x0 + 0.6 * hx, under - 0.1, under - 0.01, hz, 1, False))
    elif support == "trestle":
        foot = rng.uniform(0.6, 0.9) * width
        for s in (-1, 1):
            x = s * hx * rng.uniform(0.75, 0.9)
            parts.append(_boxes([[x, 0.03, 0], [x, under - 0.03, 0]], [[0.08, 0.06, foot], [0.08, 0.06, foot * 0.9]]))
            parts.append(_rods([[x, 0.05, -foot / 4], [x, 0.05, foot / 4]],
                               [[x, under - 0.05, -0.04], [x, under - 0.05, 0.04]], 0.03, _CUBE))
        parts.append(_boxes([0, under * rng.uniform(0.3, 0.6), 0], [2 * hx * 0.85, 0.05, 0.04]))
    else:
        k = int(rng.choice((3, 4)))
        column = rng.uniform(0.04, 0.08)
        parts.append(_rods([0, 0.04, 0], [0, under, 0], column, _CUBE if rng.random() < 0.5 else _CYLINDER))
        angle = rng.uniform(0, _TAU) + _TAU * np.arange(k) / k
        reach = min(hx, hz) * rng.uniform(0.6, 0.9)
        tips = np.stack([np.cos(angle) * reach, np.full(k, 0.02), np.sin(angle) * reach], 1)
        parts.append(_rods(np.broadcast_to([0.0, 0.05, 0.0], (k, 3)), tips, 0.03, _CUBE))
    return parts


_BUILDERS: dict[str, Callable[[np.random.Generator], list[_Part]]] = {
    "airplane": _airplane, "bed": _bed, "bookshelf": _bookshelf, "car": _car, "chair": _chair, "desk": _desk,
    "guitar": _guitar, "desk_lamp": _desk_lamp, "helicopter": _helicopter, "monitor": _monitor, "piano": _piano,
    "plant": _plant,
    "sofa": _sofa, "table": _table,
}

SYNTHETIC_HALVES: dict[str, list[str]] = {
    "1": ["airplane", "bed", "bookshelf", "car", "chair", "desk", "guitar"],
    "2": ["desk_lamp", "helicopter", "monitor", "piano", "plant", "sofa", "table"],
}
"""Half 1 trains and validates; half 2 holds out different categories (vehicles, furniture in both)."""

SYNTHETIC_CATEGORIES: tuple[str, ...] = tuple(SYNTHETIC_HALVES["1"] + SYNTHETIC_HALVES["2"])


def _build_shape(category: str, rng: np.random.Generator) -> _Part:
    """One random shape of ``category``: its builder's parts merged, then stretched per axis."""
    part = _merge(_BUILDERS[category](rng))
    return _Part(part.vertices * np.exp(rng.uniform(-_STRETCH, _STRETCH, 3)), part.faces)


def generate_shapes(num_train_per_category: int, num_test_per_category: int, seed: int) -> Iterator[MeshShape]:
    """Yield the synthetic dataset category by category, train shapes before test shapes.

    Shape ``index`` of a (category, split) uses ``np.random.default_rng([seed, crc32(category),
    split, index])``, so it does not depend on the counts or on the other categories.
    """
    counts = {"train": num_train_per_category, "test": num_test_per_category}
    for key, value in {**counts, "seed": seed}.items():
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise ConfigError(f"synthetic dataset: {key} must be a non-negative integer, got {value!r}")
    for category in SYNTHETIC_CATEGORIES:
        for split_code, (split, count) in enumerate(counts.items()):
            for index in range(count):
                rng = np.random.default_rng([seed, zlib.crc32(category.encode()), split_code, index])
                vertices, faces = _build_shape(category, rng)
                yield MeshShape(f"synthetic_{category}_{split}_{index:04d}", category, split, vertices, faces)
