"""Curves as OpenCV contours: containment, the ``RETR_TREE`` / ``RETR_CCOMP`` hierarchy,
:func:`to_cv_contours`, the drop-in :func:`find_contours`, and the layout of the contours
``.npz`` (:func:`contour_arrays`, :func:`load_contours`)."""
from __future__ import annotations

import os
import warnings
from typing import Dict, List, Optional, Tuple, Union

import numpy as np

from torch_isc._helpers import finite_real, load_npz_arrays
from torch_isc.images.arrays import ImageError, ImageLike
from torch_isc.images.polylines import closed_polygons

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
    try:
        polys = [np.asarray(p, np.float64) for p in polys]
    except (TypeError, ValueError) as e:
        raise ValueError(f"polys: expected a list of (n, 2) point arrays ({e})") from None
    for i, p in enumerate(polys):
        if p.ndim == 3 and p.shape[1] == 1:          # OpenCV's (n, 1, 2) contours
            polys[i] = p = p.reshape(-1, 2)
        if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] == 0:
            raise ValueError(f"polys[{i}]: expected (n, 2) or OpenCV's (n, 1, 2) points, got shape {p.shape}")
    return _hierarchy(_unit_frame(polys), mode)[0]


def _unit_frame(polys: List[np.ndarray]) -> List[np.ndarray]:
    """``polys`` moved and scaled by a power of two into about [-1, 1]^2 (containment and
    orientation are unchanged): the crossing test and the shoelace products overflowed to inf
    and NaN for coordinates near 1e300 (an outer contour came out reversed)."""
    V = np.concatenate(polys)
    lo, hi = V.min(0), V.max(0)
    c = lo / 2 + hi / 2
    ext = float(np.max(hi / 2 - lo / 2))
    if not np.isfinite(ext) or ext <= 0:
        return [p - c for p in polys] if np.isfinite(c).all() else polys
    k = -int(np.frexp(ext)[1])
    return [np.ldexp(p - c, k) for p in polys]


def _hierarchy(polys: List[np.ndarray], mode: str) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`contour_hierarchy` and the nesting depth ``(N,)`` of each polygon (0: outermost),
    from one containment test; ``polys`` in :func:`_unit_frame` (no overflow near 1e300)."""
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
    units = _unit_frame(polys)
    h, depth = _hierarchy(units, mode)
    depth_parity = depth % 2
    out = []
    for p, u, par in zip(polys, units, depth_parity):
        x, y = u[:, 0], u[:, 1]
        area2 = float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum())
        # OpenCV: outer (even depth) negative shoelace area, holes positive
        want_neg = par == 0
        if (area2 > 0) == want_neg:
            p = np.concatenate([p[:1], p[1:][::-1]])
        q = cast_coordinates(p - 0.5, dtype, "to_cv_contours")
        out.append(np.ascontiguousarray(q.reshape(-1, 1, 2)))
    return out, h[None]


#: the coarsest step (pixels) a float output type may have at the contours' coordinates before
#: :func:`cast_coordinates` warns (float32 beyond about 10^6 px from the origin)
SUBPIXEL_STEP = 1.0 / 16


def warn_coarse(big: float, dtype, what: str) -> None:
    """Warn when ``dtype`` holds coordinates of magnitude ``big`` only in steps coarser than
    :data:`SUBPIXEL_STEP`: float32 at 1e8 holds every 8th pixel, and a sub-pixel curve would
    collapse onto a few columns with no sign of it. ``what`` starts the message."""
    dt = np.dtype(dtype)
    with np.errstate(over="ignore"):                  # beyond the type's range: inf, refused by the caller
        step = float(np.spacing(dt.type(big)))
    if step > SUBPIXEL_STEP:
        warnings.warn(f"{what} up to {big:.3g} hold only steps of {step:.3g} px in {dt.name} (sub-pixel detail "
                      f"lost); add so large an offset in float64 after the call", stacklevel=3)


def cast_coordinates(q: np.ndarray, dtype, what: str) -> np.ndarray:
    """Contour coordinates ``q (n, 2)`` in ``dtype``: rounded to the pixel for an integer type
    (through int32, OpenCV's point type), as they are for a float type.

    Raises:
        ImageError: a coordinate beyond what ``dtype`` holds (float32 turned it into inf, int32
            wrapped it to INT_MIN, with only numpy's warning), naming ``what``.
    """
    dt = np.dtype(dtype)
    integer = np.issubdtype(dt, np.integer)
    if integer:
        q = np.rint(q)
        info = np.iinfo(np.int32) if dt.itemsize >= 4 else np.iinfo(dt)
        lo, hi, name = float(info.min), float(info.max), "int32" if dt.itemsize >= 4 else dt.name
    else:
        hi = float(np.finfo(dt).max) if np.issubdtype(dt, np.floating) else np.inf
        lo, name = -hi, dt.name
    q = np.asarray(q)
    if q.size and not ((q >= lo) & (q <= hi)).all():
        worst = float(np.abs(q[np.isfinite(q)]).max()) if np.isfinite(q).any() else float("nan")
        hint = "" if integer else "; ask for dtype=np.float64"
        raise ImageError(f"{what}: contour coordinates up to {worst:.3g} are beyond what {name} holds{hint}")
    if (not integer and q.size and np.issubdtype(dt, np.floating) and np.issubdtype(q.dtype, np.floating)
            and np.finfo(q.dtype).eps < np.finfo(dt).eps):          # the cast narrows: it may lose detail
        warn_coarse(float(np.abs(q).max()), dt, f"{what}: contour coordinates")
    return q.astype(np.int32).astype(dt, copy=False) if integer else q.astype(dt)


#: OpenCV's contour approximation methods by name and constant (``CHAIN_APPROX_NONE`` = 1,
#: ``CHAIN_APPROX_SIMPLE`` = 2; the Teh-Chin ones, 3 and 4, are taken as SIMPLE).
CHAIN_METHODS = {"none": 1, "simple": 2, "tc89_l1": 3, "tc89_kcos": 4}


def _chain_method(method) -> str:
    from torch_isc.images.grid import cv_option
    name = cv_option(method, CHAIN_METHODS, "chain_approx_", "contour approximation method",
                     "none, simple or cv2.CHAIN_APPROX_NONE=1, SIMPLE=2, TC89_L1=3, TC89_KCOS=4")
    return "none" if name == "none" else "simple"


def _shoelace(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum())


def _as_cv(poly: np.ndarray, method: str, epsilon: float, integer: bool, offset, s0: Optional[int] = None) -> np.ndarray:
    """One loop of :func:`trace_masks` (foreground on the left) as an OpenCV contour: reversed
    (OpenCV's orientation), starting at node ``s0`` of ``poly`` (OpenCV's start: the crack left
    of the start pixel of an outer border, right of it for a hole; default: the top-left
    point), in OpenCV's coordinates."""
    q = poly[::-1] - 0.5
    s = int(np.lexsort((q[:, 0], q[:, 1]))[0]) if s0 is None else len(q) - 1 - int(s0)
    q = np.roll(q, -s, 0)
    if offset is not None:
        q = q + np.asarray(offset, np.float64).reshape(1, 2)
        lim = 2.0 ** 31 - 1 if integer else float(np.finfo(np.float32).max)
        if not (np.abs(q) <= lim).all():        # 1e308 became inf in float32, wrapped in int32
            raise ImageError(f"offset {tuple(float(v) for v in np.asarray(offset).ravel())}: contour coordinates "
                             f"beyond what {'int32' if integer else 'float32'} holds")
    if integer:
        q = np.rint(q)             # the foreground pixel centres (integers already)
        keep = np.r_[True, (q[1:] != q[:-1]).any(1)]
        q = q[keep]
        if len(q) > 1 and (q[-1] == q[0]).all():
            q = q[:-1]
        q = q.astype(np.int32)
        if method == "simple" and len(q) > 2:
            q = chain_simple(q)
    else:
        # repeated points (a tip vertex on a crossing, equal once in float32): one of each, as cv2
        q = q.astype(np.float32)
        keep = np.r_[True, (q[1:] != q[:-1]).any(1)]
        if keep.sum() > 1 and (q[-1] == q[0]).all():
            keep[-1] = False
        q = q[keep]
        if method == "simple" and len(q) > 2:
            q = cv2_approx(q, epsilon)
    return np.ascontiguousarray(q.reshape(-1, 1, 2).astype(np.int32 if integer else np.float32))


def chain_simple(q: np.ndarray) -> np.ndarray:
    """OpenCV's ``CHAIN_APPROX_SIMPLE`` of a closed pixel chain ``q (n, 2)`` (its NONE chain):
    the points where the step direction changes (the step into a point differs from the step
    out of it, the loop taken cyclically), in chain order (so a start point inside a straight
    run is dropped, as OpenCV does). ``cv2.approxPolyDP`` keeps the same corners but may start
    the loop elsewhere.

    >>> chain_simple(np.array([[1, 0], [2, 0], [2, 1], [1, 1], [0, 1], [0, 0]]))
    array([[2, 0],
           [2, 1],
           [0, 1],
           [0, 0]])
    """
    step = np.roll(q, -1, 0) - q                 # step out of each point
    keep = (step != np.roll(step, 1, 0)).any(1)  # differs from the step into it
    return q[keep] if keep.any() else q[:1]


def cv2_approx(q: np.ndarray, epsilon: float) -> np.ndarray:
    """Douglas-Peucker of a closed contour (``cv2.approxPolyDP``); with ``epsilon`` 0, only the
    collinear runs are merged (as CHAIN_APPROX_SIMPLE does on pixel chains)."""
    from torch_isc._helpers import import_cv2
    cv2 = import_cv2()
    # OpenCV refuses epsilon >= 1e30; any epsilon beyond the contour's extent gives the same polygon
    out = cv2.approxPolyDP(q.reshape(-1, 1, 2), min(float(epsilon), 1e29), True).reshape(-1, 2)
    return out if len(out) >= 1 else q


def _check_contour_options(offset, min_area, epsilon, smooth, dtype) -> None:
    """The numeric options of :func:`find_contours_batch`, checked with the option named (a
    smoothing of 10**12 iterations never ended; a NaN offset gave NaN contours)."""
    def real(v):
        return finite_real(v)

    if offset is not None:
        try:
            ok = len(offset) == 2 and all(real(v) for v in offset)
        except TypeError:
            ok = False
        if not ok:
            raise ImageError(f"offset must be (dx, dy), two finite numbers, got {offset!r:.60}")
    if not (real(min_area) and min_area >= 0):
        raise ImageError(f"min_area must be a finite number >= 0, got {min_area!r:.30}")
    if not (real(epsilon) and epsilon >= 0):
        raise ImageError(f"epsilon must be a finite number >= 0, got {epsilon!r:.30}")
    if not (isinstance(smooth, (int, np.integer)) and not isinstance(smooth, bool) and 0 <= smooth <= 10_000):
        raise ImageError(f"smooth must be an integer in [0, 10000] (iterations), got {smooth!r:.30}")
    try:
        dt = np.dtype(dtype)
    except TypeError:
        dt = None
    if dt not in (np.dtype(np.float32), np.dtype(np.int32)):
        raise ImageError(f"dtype must be np.float32 (sub-pixel) or np.int32 (pixel chain), got {dtype!r:.30}")
    if dt == np.dtype(np.int32) and offset is not None and any(float(v) != round(float(v)) for v in offset):
        # as cv2 (a Point offset): rounding half-pixel shifts merged neighbouring chain points
        raise ImageError(f"offset must be two integers with dtype=np.int32, got {offset!r:.60}")


def find_contours_batch(masks, mode=3, method=1, offset=None, *, connectivity: int = 8, dtype=np.float32,
                        min_area: float = 0.0, epsilon: float = 0.1, smooth: int = 12,
                        threshold: Optional[float] = None, batch_pixels: int = 1 << 22):
    """:func:`find_contours` of many masks, solved together: one ``(contours, hierarchy)`` per mask.
    ``batch_pixels`` bounds the padded pixels of one solve (each mask padded to the batch's
    largest height and width; masks are split into such batches, a mask alone may exceed it)."""
    from torch_isc.images.arrays import binarize, image_list
    from torch_isc.images.grid import padded_groups, retr_mode, trace_masks

    try:                                   # the library's own error type (a ValueError too)
        mode = retr_mode(mode)
        method = _chain_method(method)
    except ValueError as e:
        raise ImageError(str(e)) from None
    if connectivity not in (4, 8) or isinstance(connectivity, bool):
        raise ImageError(f"connectivity must be 8 or 4 (of the foreground), got {connectivity!r:.30}")
    if not (isinstance(batch_pixels, (int, np.integer)) and not isinstance(batch_pixels, bool) and batch_pixels >= 0):
        raise ImageError(f"batch_pixels must be an integer >= 0, got {batch_pixels!r:.30}")
    _check_contour_options(offset, min_area, epsilon, smooth, dtype)
    integer = np.issubdtype(np.dtype(dtype), np.integer)
    ts = [binarize(t, threshold) for t in image_list(masks, "mask")]
    if offset is not None and not integer and ts:
        warn_coarse(max(abs(float(v)) for v in offset) + max(max(t.shape) for t in ts), dtype,
                    f"offset {tuple(float(v) for v in offset)}: contour coordinates")
    out = []
    for b0, b1 in padded_groups([tuple(t.shape) for t in ts], batch_pixels):
        gc = trace_masks(ts[b0:b1], connectivity, smooth)
        out.extend(grid_contours(gc, mode, method, epsilon, integer, min_area, offset))
    return out


def grid_contours(gc, mode: str = "tree", method: str = "none", epsilon: float = 0.1, integer: bool = False,
                  min_area: float = 0.0, offset=None):
    """Per item of a :class:`~torch_isc.images.grid.GridCurves`: ``(contours tuple, hierarchy (1, N, 4)
    or None)`` in OpenCV's layout."""
    from torch_isc.images.grid import cv_layout
    pl = gc.polylines
    pts = (gc.inner if integer and gc.inner is not None else pl.points).detach().cpu().double().numpy()
    first = pl.first.cpu().numpy()
    counts = pl.counts.cpu().numpy()
    outer = gc.outer.cpu().numpy()
    parent = gc.parent.cpu().numpy()
    start = gc.start.cpu().numpy()
    ranges = gc.loop_ranges().cpu().numpy()
    s_node = gc.start_node.cpu().numpy() - first if gc.start_node is not None else None
    sub = pl.points.detach().cpu().double().numpy()
    pl_area = [_shoelace(sub[first[k]:first[k] + counts[k]]) for k in range(len(first))] if min_area > 0 else None
    res = []
    for b in range(gc.sizes.shape[0]):
        k0, k1 = int(ranges[b]), int(ranges[b + 1])
        polys = [pts[first[k]:first[k] + counts[k]] for k in range(k0, k1)]
        areas = [pl_area[k] for k in range(k0, k1)] if pl_area is not None else None
        par = np.where(parent[k0:k1] >= 0, parent[k0:k1] - k0, -1)
        if min_area > 0 and polys:
            small = np.array([abs(a) < min_area for a in areas])
            for _ in range(64):                  # a small loop takes its whole subtree with it
                nxt_small = small | (small[np.maximum(par, 0)] & (par >= 0))
                if (nxt_small == small).all():
                    break
                small = nxt_small
        else:
            small = np.zeros(len(polys), bool)
        order, h = cv_layout(outer[k0:k1], par, start[k0:k1], mode, keep=~small)
        cs = tuple(_as_cv(polys[k], method, epsilon, integer, offset, None if s_node is None else s_node[k0 + k])
                   for k in order.tolist())
        res.append((cs, h[None] if len(cs) else None))
    return res


def find_contours(mask: ImageLike, mode=3, method=1, offset=None, *, connectivity: int = 8, dtype=np.float32,
                  min_area: float = 0.0, epsilon: float = 0.1, smooth: int = 12,
                  threshold: Optional[float] = None) -> Tuple[tuple, Optional[np.ndarray]]:
    """A drop-in for ``cv2.findContours(mask, mode, method)`` with sub-pixel contours.

    The same contours (one per border of an 8-connected foreground component or 4-connected
    hole, with ``connectivity=8``, as OpenCV), in OpenCV's order, orientation and hierarchy
    layout, from the implicit simplicial curve of the mask on its pixel-centre grid
    (:func:`torch_isc.images.grid.trace_masks`): each point lies between a foreground and a
    background pixel centre, within a pixel of OpenCV's chain, and inside the image frame;
    except the tip inserted at a corner sharper than the pixel staircase (an acute wedge of a
    few pixels), which may lie up to a few pixels out along the corner's bisector, where the
    wedge's sides meet (``smooth=0``: none).

    Args:
        mask: 2D array or tensor; foreground is nonzero for integer masks (as OpenCV), above
            ``threshold`` (default 0.5) for float masks.
        mode: ``cv2.RETR_EXTERNAL``/``RETR_LIST``/``RETR_CCOMP``/``RETR_TREE`` or their names
            (``"tree"``...).
        method: ``cv2.CHAIN_APPROX_NONE`` (every crossing) or ``CHAIN_APPROX_SIMPLE`` (points
            dropped while the contour stays within ``epsilon`` pixels: ``cv2.approxPolyDP``;
            for int32 output, only collinear runs merged).
        offset: ``(dx, dy)`` added to every point, as OpenCV's ``offset``.
        connectivity: 8 (default) or 4, of the foreground.
        dtype: ``np.float32`` (sub-pixel, default) or ``np.int32`` (rounded to pixel centres,
            repeats dropped: what ``cv2.drawContours`` needs).
        min_area: drop contours enclosing less than this area (pixels^2) with their subtrees.
        smooth: smoothing iterations (0: the crack-midpoint polygon, as marching squares).

    Returns:
        ``(contours, hierarchy)`` as ``cv2.findContours``: a tuple of ``(n, 1, 2)`` arrays in
        OpenCV's coordinates (pixel centres at integers: our ``(x, y)`` is ``(x - 0.5, y - 0.5)``)
        and the ``(1, N, 4)`` int32 ``[next, prev, first_child, parent]``, None for no contour.

    >>> m = np.zeros((40, 40), np.uint8); m[5:35, 5:35] = 1; m[15:25, 15:25] = 0
    >>> c, h = find_contours(m, 2)
    >>> len(c), h[0, :, 3].tolist(), c[0].dtype.name
    (2, [-1, 0], 'float32')
    """
    shape = tuple(getattr(mask, "shape", ()))
    if len(shape) in (2, 3) and 0 in shape[:2] and shape[2:] in ((), (1,)):
        # an empty image has no contour (as cv2); the arguments are still checked, on a blank pixel
        mask = np.zeros((1, 1), np.uint8)
    return find_contours_batch([mask], mode, method, offset, connectivity=connectivity, dtype=dtype,
                               min_area=min_area, epsilon=epsilon, smooth=smooth, threshold=threshold)[0]


#: Version of the contours ``.npz`` layout (:func:`contour_arrays`).
CONTOURS_FORMAT = 1


def contour_arrays(src, mode: str = "tree") -> Dict[str, np.ndarray]:
    """The arrays of a contours ``.npz`` (written by :func:`torch_isc.io.write_contours`):
    ``points (P, 2)`` in OpenCV coordinates (:func:`to_cv_contours`; float32 for a mask's
    contours, float64 for a point set's, whose coordinates may sit far from the origin: float32
    merged the vertices of a curve 1e-2 across at 1e7), ``counts (N,)`` vertices per contour,
    ``hierarchy (N, 4)`` int32, ``mode``, ``format``."""
    pre = getattr(src, "cv_contours", None)
    if pre is not None and mode == "tree":           # a mask's grid result: OpenCV's own order
        contours, h = pre
    else:
        contours, h = to_cv_contours(src, mode, dtype=np.float64)
    pts = np.concatenate([c.reshape(-1, 2) for c in contours]) if contours else np.zeros((0, 2), np.float32)
    return {
        "points": pts.astype(np.float32 if pre is not None else np.float64),
        "counts": np.array([len(c) for c in contours], np.int64),
        "hierarchy": (h[0] if h is not None else np.zeros((0, 4), np.int32)).astype(np.int32),
        "mode": np.array(mode), "format": np.array(CONTOURS_FORMAT, np.int64),
    }


def load_contours(path: Union[str, os.PathLike], dtype=np.float32) -> Tuple[List[np.ndarray], Optional[np.ndarray]]:
    """Read a contours ``.npz`` (:func:`contour_arrays`): ``(contours [(n, 1, 2)], hierarchy (1, N, 4) or None)``,
    as ``cv2.findContours`` returns them.

    Raises:
        ImageError: missing, unreadable or inconsistent file (one line naming it; the reading
            is bounded: :func:`torch_isc._helpers.load_npz_arrays`)."""
    z = load_npz_arrays(path, ImageError, "a contours file")
    try:
        pts, counts, h = z["points"], z["counts"], z["hierarchy"]
    except KeyError as e:
        raise ImageError(f"{path}: not a contours file (no {e} array)") from None
    real = (np.issubdtype(pts.dtype, np.floating) or np.issubdtype(pts.dtype, np.integer)) and np.isfinite(pts).all()
    ok = (real and pts.ndim == 2 and pts.shape[1] == 2 and counts.ndim == 1 and np.issubdtype(counts.dtype, np.integer)
          and (counts >= 0).all() and int(counts.astype(object).sum()) == pts.shape[0] and h.shape == (counts.size, 4)
          and np.issubdtype(h.dtype, np.integer) and (h.size == 0 or (h.min() >= -1 and h.max() < counts.size)))
    if not ok:       # the hierarchy indexes the contours (-1: none); points are finite numbers
        raise ImageError(f"{path}: inconsistent contours file (points {pts.shape}, counts {counts.shape}, "
                         f"hierarchy {h.shape})")
    pts = cast_coordinates(pts, dtype, str(path))
    pieces = np.split(pts, np.cumsum(counts)[:-1]) if counts.size else []
    return [p.reshape(-1, 1, 2) for p in pieces], (h[None] if counts.size else None)
