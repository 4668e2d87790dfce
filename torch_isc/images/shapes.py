"""Antialiased analytic shapes for accuracy checks: each shape's coverage of every pixel
(supersampled), its binary mask at coverage 1/2, and its true curves (pixel convention of
:mod:`torch_isc.images`)."""
from __future__ import annotations

import math
from typing import Callable, Dict, List, Tuple

import numpy as np

__all__ = ["SHAPES", "shape_mask", "corner_shapes", "shape_mask_of"]


def _circle(cx: float, cy: float, r: float, n: int = 0) -> np.ndarray:
    n = n or max(64, int(2 * math.pi * r / 0.05))
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return np.c_[cx + r * np.cos(t), cy + r * np.sin(t)]


def _poly_inside(poly: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    inside = np.zeros(x.shape, bool)
    n = len(poly)
    for k in range(n):
        (ax, ay), (bx, by) = poly[k], poly[(k + 1) % n]
        straddle = (ay > y) != (by > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = ax + (y - ay) * (bx - ax) / (by - ay)
        inside ^= straddle & (x < xc)
    return inside


def _rot_square(cx, cy, half, deg):
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    q = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * half
    return np.c_[cx + q[:, 0] * c - q[:, 1] * s, cy + q[:, 0] * s + q[:, 1] * c]


def _star(cx, cy, r_out, r_in, k=5, deg=0.0):
    t = np.arange(2 * k) * math.pi / k + math.radians(deg)
    r = np.where(np.arange(2 * k) % 2 == 0, r_out, r_in)
    return np.c_[cx + r * np.cos(t), cy + r * np.sin(t)]


def _discs(specs):
    def inside(x, y):
        out = np.zeros(x.shape, bool)
        for cx, cy, r, sign in specs:
            d = (x - cx) ** 2 + (y - cy) ** 2 < r * r
            out = out | d if sign > 0 else out & ~d
        return out
    return inside, [_circle(cx, cy, r) for cx, cy, r, _ in specs]


def _polys(polys):
    def inside(x, y):
        out = np.zeros(x.shape, bool)
        for p in polys:
            out ^= _poly_inside(p, x, y)
        return out
    return inside, [np.asarray(p, float) for p in polys]


#: name -> (height, width, inside(x, y), true curves)
SHAPES: Dict[str, Tuple[int, int, Callable, List[np.ndarray]]] = {}
for _name, _h, _w, (_in, _cv) in [
    ("disc r=40.3", 96, 96, _discs([(47.37, 48.81, 40.3, 1)])),
    ("disc r=150.2", 310, 310, _discs([(155.2, 154.7, 150.2, 1)])),
    ("disc r=4.3", 16, 16, _discs([(8.21, 7.63, 4.3, 1)])),
    ("disc r=1.6 (3 px)", 8, 8, _discs([(4.13, 3.91, 1.6, 1)])),
    ("annulus 30/18", 70, 70, _discs([(35.2, 34.6, 30.0, 1), (35.2, 34.6, 18.0, -1)])),
    ("ring 2 px", 50, 50, _discs([(25.3, 24.8, 20.0, 1), (25.3, 24.8, 18.0, -1)])),
    ("ring 3 px", 50, 50, _discs([(25.3, 24.8, 20.0, 1), (25.3, 24.8, 17.0, -1)])),
    ("two discs 2 px apart", 40, 60, _discs([(17.4, 20.2, 12.0, 1), (43.4, 20.2, 12.0, 1)])),
    ("square 20 deg", 60, 60, _polys([_rot_square(30.3, 29.8, 18.0, 20.0)])),
    ("square axis", 40, 40, _polys([_rot_square(20.0, 20.0, 12.0, 0.0)])),
    ("triangle", 60, 60, _polys([np.array([[8.3, 50.2], [52.1, 47.6], [25.7, 7.9]])])),
    ("star (notches)", 80, 80, _polys([_star(40.2, 39.7, 34.0, 14.0, 5, 7.0)])),
]:
    SHAPES[_name] = (_h, _w, _in, _cv)


def shape_mask(name: str, supersample: int = 16) -> Tuple[np.ndarray, np.ndarray, List[np.ndarray]]:
    """``(mask (H, W) bool, coverage (H, W) float, true curves)`` of a shape of :data:`SHAPES`:
    a pixel is foreground when the shape covers at least half of it."""
    return shape_mask_of(SHAPES[name], supersample)


def _regular(cx, cy, r, n, deg):
    t = np.arange(n) * 2 * math.pi / n + math.radians(deg)
    return np.c_[cx + r * np.cos(t), cy + r * np.sin(t)]


def _wedge(cx, cy, length, apex_deg, deg):
    """An isosceles triangle with apex angle ``apex_deg``, sides ``length``, centred on its centroid."""
    h = math.radians(apex_deg) / 2
    p = np.array([[0.0, 0.0], [length * math.cos(h), length * math.sin(h)], [length * math.cos(h), -length * math.sin(h)]])
    p -= p.mean(0)
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.c_[cx + p[:, 0] * c - p[:, 1] * s, cy + p[:, 0] * s + p[:, 1] * c]


def _ell(cx, cy, size, deg):
    """An L (a 90-degree notch): a square of side ``size`` less its top-right quarter."""
    q = np.array([[0, 0], [1, 0], [1, 0.5], [0.5, 0.5], [0.5, 1], [0, 1]], float) * size - size / 2
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.c_[cx + q[:, 0] * c - q[:, 1] * s, cy + q[:, 0] * s + q[:, 1] * c]


def corner_shapes(seed: int = 0) -> Dict[str, Tuple[int, int, Callable, List[np.ndarray]]]:
    """A broad set of polygons (random rotations and sub-pixel offsets from ``seed``): squares of
    3 to 290 px, wedges with apex angles 20 to 150 degrees, regular 5-, 6- and 12-gons (corners
    of 108, 120 and 150 degrees), stars and L shapes (notches); same layout as :data:`SHAPES`."""
    rng = np.random.default_rng(seed)
    out: Dict[str, Tuple[int, int, Callable, List[np.ndarray]]] = {}

    def add(name, extent, make):
        n = int(math.ceil(extent)) + 8
        cx, cy = n / 2 + rng.uniform(-0.5, 0.5), n / 2 + rng.uniform(-0.5, 0.5)
        deg = float(rng.uniform(0, 360))
        poly = make(cx, cy, deg)
        out[f"{name} rot {deg:.0f}"] = (n, n, *_polys([poly]))

    for side in (3, 6, 12, 40, 150, 290):
        add(f"square {side} px", side * 1.42, lambda cx, cy, deg, s=side: _rot_square(cx, cy, s / 2, deg))
    for apex in (20, 30, 45, 60, 90, 120, 150):
        L = 40.0
        add(f"wedge {apex} deg", 2 * L, lambda cx, cy, deg, a=apex: _wedge(cx, cy, L, a, deg))
    for n, r in ((5, 20.0), (6, 30.0), (12, 60.0)):
        add(f"{n}-gon r={r:g}", 2 * r, lambda cx, cy, deg, n=n, r=r: _regular(cx, cy, r, n, deg))
    add("wedge 60 deg small", 16, lambda cx, cy, deg: _wedge(cx, cy, 9.0, 60, deg))
    add("star 5 r=30/15", 60, lambda cx, cy, deg: _star(cx, cy, 30.0, 15.0, 5, deg))
    add("star 6 r=100/60", 200, lambda cx, cy, deg: _star(cx, cy, 100.0, 60.0, 6, deg))
    for size in (10, 50):
        add(f"L {size} px", size * 1.42, lambda cx, cy, deg, s=size: _ell(cx, cy, s, deg))
    return out


def shape_mask_of(spec, supersample: int = 16) -> Tuple[np.ndarray, np.ndarray, List[np.ndarray]]:
    """:func:`shape_mask` of a ``(H, W, inside, curves)`` spec."""
    H, W, inside, curves = spec
    s = supersample
    off = (np.arange(s) + 0.5) / s
    ys = (np.arange(H)[:, None] + off[None, :]).reshape(-1)
    xs = (np.arange(W)[:, None] + off[None, :]).reshape(-1)
    X, Y = np.meshgrid(xs, ys)
    cov = inside(X, Y).reshape(H, s, W, s).mean((1, 3))
    return cov >= 0.5, cov, curves
