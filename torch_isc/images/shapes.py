"""Antialiased analytic shapes for accuracy checks: each shape's coverage of every pixel
(supersampled), its binary mask at coverage 1/2, and its true curves (pixel convention of
:mod:`torch_isc.images`)."""
from __future__ import annotations

import math
from typing import Callable, Dict, List, Tuple

import numpy as np

__all__ = ["SHAPES", "shape_mask"]


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
    H, W, inside, curves = SHAPES[name]
    s = supersample
    off = (np.arange(s) + 0.5) / s
    ys = (np.arange(H)[:, None] + off[None, :]).reshape(-1)
    xs = (np.arange(W)[:, None] + off[None, :]).reshape(-1)
    X, Y = np.meshgrid(xs, ys)
    cov = inside(X, Y).reshape(H, s, W, s).mean((1, 3))
    return cov >= 0.5, cov, curves
