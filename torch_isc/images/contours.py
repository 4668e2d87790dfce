"""Curves as OpenCV contours: containment, the ``RETR_TREE`` / ``RETR_CCOMP`` hierarchy,
:func:`to_cv_contours`, the drop-in :func:`find_contours`, and the layout of the contours
``.npz`` (:func:`contour_arrays`, :func:`load_contours`)."""
from __future__ import annotations

import os
from typing import Dict, List, Optional, Tuple, Union

import numpy as np

from torch_isc.images.arrays import ImageLike
from torch_isc.images.masks import reconstruct_masks
from torch_isc.images.polylines import closed_polygons
from torch_isc.pipeline.config import ReconstructConfig

__all__ = ["contour_hierarchy", "to_cv_contours", "find_contours", "CONTOURS_FORMAT", "contour_arrays",
           "load_contours"]


def _containment(polys: List[np.ndarray]) -> np.ndarray:
    """``inside[a, b]`` (bool, N x N): the first vertex of polygon b lies inside polygon a
    (even-odd crossing test, only for pairs whose bounding boxes nest; chunked)."""
    N = len(polys)
    inside = np.zeros((N, N), bool)
    if N < 2:
        return inside
    counts = np.array([len(p) for p in polys])
    V = np.concatenate(polys)
    first = np.cumsum(counts) - counts
    owner = np.repeat(np.arange(N), counts)
    k = np.arange(V.shape[0]) - first[owner]
    A, B = V, V[first[owner] + (k + 1) % counts[owner]]
    lo = np.stack([np.minimum.reduceat(V, first)[:, 0], np.minimum.reduceat(V, first)[:, 1]], 1)
    hi = np.stack([np.maximum.reduceat(V, first)[:, 0], np.maximum.reduceat(V, first)[:, 1]], 1)
    q = V[first]                                                     # one vertex per polygon
    cand = ((q[None, :, :] > lo[:, None, :]) & (q[None, :, :] < hi[:, None, :])).all(2)
    np.fill_diagonal(cand, False)
    pa, pb = np.nonzero(cand)
    if pa.size == 0:
        return inside
    seg_first = first[pa]
    n_seg = counts[pa]
    chunk = max(1, (1 << 21) // max(1, int(n_seg.max())))
    for s in range(0, pa.size, chunk):
        a_, b_, f_, n_ = pa[s:s + chunk], pb[s:s + chunk], seg_first[s:s + chunk], n_seg[s:s + chunk]
        rep = np.repeat(np.arange(a_.size), n_)
        si = np.repeat(f_, n_) + (np.arange(rep.size) - np.repeat(np.cumsum(n_) - n_, n_))
        x, y = q[b_[rep], 0], q[b_[rep], 1]
        ax, ay, bx, by = A[si, 0], A[si, 1], B[si, 0], B[si, 1]
        straddle = (ay > y) != (by > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = ax + (y - ay) * (bx - ax) / (by - ay)
        cross = straddle & (x < xc)
        odd = np.bincount(rep, weights=cross, minlength=a_.size).astype(np.int64) % 2 == 1
        inside[a_[odd], b_[odd]] = True
    return inside


def contour_hierarchy(polys: List[np.ndarray], mode: str = "tree") -> np.ndarray:
    """OpenCV hierarchy ``(N, 4)`` int32 ``[next, prev, first_child, parent]`` of closed,
    non-crossing polygons, from their containment.

    ``mode="tree"`` (``cv2.RETR_TREE``): the full nesting tree. ``mode="ccomp"``
    (``cv2.RETR_CCOMP``): two levels, the outer boundaries of components (even depth) at the top,
    each hole (odd depth) under its component; an island inside a hole is a top-level contour
    again. ``next``/``prev`` link contours with the same parent, in list order; -1 for none.

    >>> sq = lambda a, b: np.array([[a, a], [b, a], [b, b], [a, b]], float)
    >>> contour_hierarchy([sq(0, 9), sq(1, 8), sq(2, 7)], "tree").tolist()
    [[-1, -1, 1, -1], [-1, -1, 2, 0], [-1, -1, -1, 1]]
    >>> contour_hierarchy([sq(0, 9), sq(1, 8), sq(2, 7)], "ccomp").tolist()
    [[2, -1, 1, -1], [-1, -1, -1, 0], [-1, 0, -1, -1]]
    """
    return _hierarchy(polys, mode)[0]


def _hierarchy(polys: List[np.ndarray], mode: str) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`contour_hierarchy` and the nesting depth ``(N,)`` of each polygon (0: outermost),
    from one containment test."""
    if mode not in ("tree", "ccomp"):
        raise ValueError(f"mode must be 'tree' or 'ccomp', got {mode!r}")
    N = len(polys)
    h = np.full((N, 4), -1, np.int32)
    if N == 0:
        return h, np.zeros(0, np.int64)
    inside = _containment(polys)
    depth = inside.sum(0)
    # parent: the containing polygon of largest depth
    key = np.where(inside, depth[:, None] * N + np.arange(N)[:, None], -1)
    best = key.max(0)
    parent = np.where(best >= 0, best % N, -1)
    if mode == "ccomp":
        parent = np.where(depth % 2 == 1, parent, -1)
    order = np.lexsort((np.arange(N), parent))           # grouped by parent, list order within
    par_sorted = parent[order]
    same_next = np.r_[par_sorted[1:] == par_sorted[:-1], False]
    same_prev = np.r_[False, par_sorted[1:] == par_sorted[:-1]]
    h[order, 0] = np.where(same_next, np.r_[order[1:], -1], -1)
    h[order, 1] = np.where(same_prev, np.r_[-1, order[:-1]], -1)
    h[:, 3] = parent
    firsts = order[~same_prev]
    has_par = parent[firsts] >= 0
    h[parent[firsts[has_par]], 2] = firsts[has_par]
    return h, depth


def to_cv_contours(src, mode: str = "tree", dtype=np.float32) -> Tuple[List[np.ndarray], np.ndarray]:
    """Curves as OpenCV contours, so code written for ``cv2.findContours`` can use them.

    Args:
        src: polylines in the pixel convention of :mod:`torch_isc.images`, in any form that
            :func:`~torch_isc.images.polylines.polyline_dicts` takes (a result, its ``polylines``
            list of ``{"closed", "points"}`` dicts, or packed ``Polylines``). Open chains are
            left out (OpenCV contours are closed).
        mode: ``"tree"`` (like ``cv2.RETR_TREE``) or ``"ccomp"`` (``cv2.RETR_CCOMP``).
        dtype: ``np.float32`` (sub-pixel; fine for ``cv2.contourArea``, ``pointPolygonTest``,
            ``fitEllipse``...) or ``np.int32`` (rounded; what ``cv2.drawContours`` needs).

    Returns:
        ``(contours, hierarchy)``: a list of ``(n, 1, 2)`` arrays in OpenCV's coordinates
        (pixel centres at integers: our ``(x, y)`` becomes ``(x - 0.5, y - 0.5)``), oriented
        as OpenCV orients them (outer boundaries clockwise on screen with y down, i.e. negative
        ``cv2.contourArea(c, oriented=True)``; holes the other way), ordered as OpenCV's
        raster scan finds them (by topmost, then leftmost vertex), each starting at that vertex;
        and the ``(1, N, 4)`` int32 hierarchy ``[next, prev, first_child, parent]`` (``None``
        when there is no contour, as OpenCV returns).

    >>> sq = np.array([[1., 1], [5, 1], [5, 5], [1, 5]])
    >>> c, h = to_cv_contours([{"closed": True, "points": sq}, {"closed": True, "points": sq[::-1] * 0.5 + 1.5}])
    >>> c[0][:2, 0].tolist(), h.tolist()
    ([[0.5, 0.5], [0.5, 4.5]], [[[-1, -1, 1, -1], [-1, -1, -1, 0]]])
    """
    polys = closed_polygons(src)
    if not polys:
        return [], None  # type: ignore[return-value]
    # raster order of OpenCV: by the topmost, then leftmost vertex
    starts = [int(np.lexsort((p[:, 0], p[:, 1]))[0]) for p in polys]
    tops = np.array([[p[s, 1], p[s, 0]] for p, s in zip(polys, starts)])
    order = np.lexsort((tops[:, 1], tops[:, 0]))
    polys = [np.roll(polys[i], -starts[i], 0) for i in order]
    h, depth = _hierarchy(polys, mode)
    depth_parity = depth % 2
    out = []
    for p, par in zip(polys, depth_parity):
        x, y = p[:, 0], p[:, 1]
        area2 = float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum())
        # OpenCV: outer (even depth) negative shoelace area, holes positive
        want_neg = par == 0
        if (area2 > 0) == want_neg:
            p = np.concatenate([p[:1], p[1:][::-1]])
        q = p - 0.5
        q = np.rint(q).astype(np.int32) if np.issubdtype(np.dtype(dtype), np.integer) else q.astype(dtype)
        out.append(np.ascontiguousarray(q.reshape(-1, 1, 2)))
    return out, h[None]


def find_contours(mask: ImageLike, mode: str = "tree", config: Optional[ReconstructConfig] = None,
                  dtype=np.float32, **kw) -> Tuple[List[np.ndarray], np.ndarray]:
    """A sub-pixel stand-in for ``cv2.findContours(mask, RETR_TREE or RETR_CCOMP, ...)``:
    :func:`reconstruct_masks` on one mask, then :func:`to_cv_contours`.

    >>> m = np.zeros((40, 40), np.uint8); m[5:35, 5:35] = 1; m[15:25, 15:25] = 0
    >>> c, h = find_contours(m, "ccomp")
    >>> len(c), h[0, :, 3].tolist()
    (2, [-1, 0])
    """
    res = reconstruct_masks([mask], config, **kw)[0]
    return to_cv_contours(res, mode, dtype)


#: Version of the contours ``.npz`` layout (:func:`contour_arrays`).
CONTOURS_FORMAT = 1


def contour_arrays(src, mode: str = "tree") -> Dict[str, np.ndarray]:
    """The arrays of a contours ``.npz`` (written by :func:`torch_isc.io.write_contours`):
    ``points (P, 2)`` float32 in OpenCV coordinates (:func:`to_cv_contours`), ``counts (N,)``
    vertices per contour, ``hierarchy (N, 4)`` int32, ``mode``, ``format``."""
    contours, h = to_cv_contours(src, mode)
    pts = np.concatenate([c.reshape(-1, 2) for c in contours]) if contours else np.zeros((0, 2), np.float32)
    return {
        "points": pts.astype(np.float32), "counts": np.array([len(c) for c in contours], np.int64),
        "hierarchy": (h[0] if h is not None else np.zeros((0, 4), np.int32)).astype(np.int32),
        "mode": np.array(mode), "format": np.array(CONTOURS_FORMAT, np.int64),
    }


def load_contours(path: Union[str, os.PathLike], dtype=np.float32) -> Tuple[List[np.ndarray], Optional[np.ndarray]]:
    """Read a contours ``.npz`` (:func:`contour_arrays`): ``(contours [(n, 1, 2)], hierarchy (1, N, 4) or None)``,
    as ``cv2.findContours`` returns them."""
    with np.load(path, allow_pickle=False) as z:
        pts, counts, h = z["points"], z["counts"], z["hierarchy"]
    pieces = np.split(pts, np.cumsum(counts)[:-1]) if counts.size else []
    if np.issubdtype(np.dtype(dtype), np.integer):
        pieces = [np.rint(p).astype(np.int32) for p in pieces]
    return [p.reshape(-1, 1, 2).astype(dtype) for p in pieces], (h[None] if counts.size else None)
