"""Nesting of closed, non-crossing polygons: which curve encloses which, and the polygons with
holes that the nesting defines (even depth = exterior, odd depth = hole).

The curves of an implicit simplicial curve never cross or touch (they are level-set pieces of one
piecewise-linear function), so polygon ``b`` lies inside polygon ``a`` exactly when any vertex of
``b`` does; one even-odd crossing test per candidate pair decides it. numpy only, float64.

Example (an outline, its hole, an island in the hole):
    >>> sq = lambda a, b: np.array([[a, a], [b, a], [b, b], [a, b]], float)
    >>> parent, depth = polygon_nesting([sq(0, 9), sq(1, 8), sq(2, 7)])
    >>> parent.tolist(), depth.tolist()
    ([-1, 0, 1], [0, 1, 2])
    >>> polygons_with_holes([sq(0, 9), sq(1, 8), sq(2, 7)])
    [(0, [1]), (2, [])]
"""
from __future__ import annotations

from typing import List, Sequence, Tuple

import math

import numpy as np

__all__ = ["points_in_polygon", "polygon_nesting", "polygons_with_holes", "signed_area"]


def signed_area(poly: np.ndarray) -> float:
    """Shoelace area of a closed polygon ``(n, 2)`` (last vertex not repeated): positive when
    counter-clockwise in a y-up frame."""
    # in units of the polygon's extent about its first vertex: coordinates near 1e300 would
    # overflow the products (NaN, and a wrong orientation); the area itself may still be inf
    d = np.asarray(poly, dtype=np.float64)
    d = d - d[:1]
    s = float(np.abs(d).max()) if d.size else 0.0
    if not s > 0 or not np.isfinite(s):
        return 0.0 if not s > 0 else float("nan")
    x, y = d[:, 0] / s, d[:, 1] / s
    a = 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
    with np.errstate(over="ignore", under="ignore"):
        out = float(np.float64(a) * s * s)
    return out if out != 0 or a == 0 else math.copysign(5e-324, a)     # keep the sign of an underflow


def points_in_polygon(q: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd test: ``(m,)`` bool, ``q[i]`` strictly inside ``poly`` (points on an edge may go
    either way; the curves this module serves never touch)."""
    a = poly
    b = np.roll(poly, -1, 0)
    x, y = q[:, None, 0], q[:, None, 1]                      # (m, 1) against (n,) edges
    ay, by = a[None, :, 1], b[None, :, 1]
    straddle = (ay > y) != (by > y)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # the fraction first: it is in [0, 1] where the edge straddles, so no product overflows near 1e300
        xc = a[None, :, 0] + (y - ay) / (by - ay) * (b[None, :, 0] - a[None, :, 0])
    return ((straddle & (x < xc)).sum(1) % 2) == 1


def polygon_nesting(polys: Sequence[np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
    """``(parent, depth)``, both ``(N,)`` int64: the nearest enclosing polygon of each polygon
    (-1 for an outermost one) and how many polygons enclose it.

    Only pairs whose bounding boxes nest are tested, each with the first vertex of the inner one.
    """
    N = len(polys)
    parent = np.full(N, -1, np.int64)
    depth = np.zeros(N, np.int64)
    if N < 2:
        return parent, depth
    lo = np.array([p.min(0) for p in polys])
    hi = np.array([p.max(0) for p in polys])
    first = np.array([p[0] for p in polys])
    inside = np.zeros((N, N), bool)                          # inside[a, b]: b lies inside a
    for a in range(N):
        cand = np.flatnonzero(((first > lo[a]) & (first < hi[a])).all(1))
        cand = cand[cand != a]
        if cand.size:
            inside[a, cand] = points_in_polygon(first[cand], polys[a])
    depth = inside.sum(0).astype(np.int64)
    # the nearest enclosing polygon is the enclosing one of largest depth (they form a chain)
    key = np.where(inside, depth[:, None], -1)
    best = key.argmax(0)
    parent = np.where(inside.any(0), best, -1).astype(np.int64)
    return parent, depth


def polygons_with_holes(polys: Sequence[np.ndarray]) -> List[Tuple[int, List[int]]]:
    """The polygons with holes of the nesting: ``[(exterior, [holes...]), ...]`` as indices into
    ``polys``, exteriors in list order. Even depth is an exterior, odd depth a hole of its nearest
    enclosing curve (an exterior); an island inside a hole is an exterior again."""
    parent, depth = polygon_nesting(polys)
    holes: dict = {int(i): [] for i in np.flatnonzero(depth % 2 == 0)}
    for h in np.flatnonzero(depth % 2 == 1):
        holes[int(parent[h])].append(int(h))
    return [(e, holes[e]) for e in sorted(holes)]
