"""Differentiable measures of implicit simplicial curves: area, length, centroid,
curvature, point-to-curve distance.

Everything is computed per triangle in closed form and summed per item with
``index_add_`` over the packed batch (no Python loop over items or segments), so it is
differentiable in the vertex positions and the nodal values (and, for the distance, in
the query points). Convention: ``f < 0`` inside.

In a triangle whose signs differ, one vertex ``m`` (the *lone* vertex) has the sign the
other two lack. The zero set there is the segment between the crossing points
``p1 = v_m + t1 (v_{m+1} - v_m)`` and ``p2 = v_m + t2 (v_{m+2} - v_m)``,
``t_k = f_m / (f_m - f_{m+k})``; it cuts off the corner triangle ``(v_m, p1, p2)`` of
area ``t1 t2 A``. The inside part of the triangle is that corner (lone vertex negative)
or the triangle minus that corner (lone vertex positive).
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import torch

from torch_isc.core.curve import ImplicitCurve
from torch_isc.core.locate import finite_rows
from torch_isc.core.segments import expand_in_chunks

__all__ = ["area", "length", "centroid", "curvature", "point_curve_distance", "TriangleSegments",
           "triangle_segments"]

_MAX_PAIRS = 1 << 22


class TriangleSegments(NamedTuple):
    """The zero-set segments, one per sign-changing triangle (ascending triangle index, so
    each item's segments are contiguous).

    Attributes:
        tri: ``(S,)`` triangle index. item: ``(S,)`` item index.
        a, b: ``(S, 2)`` end points, oriented with the inside (``f < 0``) on the left.
        lone: ``(S,)`` global index of the lone vertex. lone_neg: ``(S,)`` bool, it is negative.
        t1, t2: ``(S,)`` crossing parameters on the edges ``(m, m+1)`` and ``(m, m+2)``.
    """
    tri: torch.Tensor
    item: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor
    lone: torch.Tensor
    lone_neg: torch.Tensor
    t1: torch.Tensor
    t2: torch.Tensor


def check_curve(curve, what: str) -> None:
    """A clear error where an :class:`~torch_isc.core.curve.ImplicitCurve` is expected (a
    reconstruction's result has one: ``result.curve``)."""
    if not isinstance(curve, ImplicitCurve):
        hint = " (use result.curve)" if hasattr(curve, "curve") else ""
        raise TypeError(f"{what}: expected an ImplicitCurve{hint}, got {type(curve).__name__}")


def triangle_segments(mesh, values: torch.Tensor) -> TriangleSegments:
    """The zero-set segment of every sign-changing triangle (differentiable end points)."""
    with torch.no_grad():
        fneg = values.detach()[mesh.faces] < 0                    # (T,3)
        nneg = fneg.sum(1)
        tri = ((nneg > 0) & (nneg < 3)).nonzero().squeeze(1)
        fn = fneg[tri].to(torch.int8)
        lone_neg = nneg[tri] == 1
        k = torch.where(lone_neg, torch.argmax(fn, 1), torch.argmin(fn, 1))
        f = mesh.faces[tri]
        im = f.gather(1, k[:, None]).squeeze(1)
        i1 = f.gather(1, ((k + 1) % 3)[:, None]).squeeze(1)
        i2 = f.gather(1, ((k + 2) % 3)[:, None]).squeeze(1)
    v = mesh.verts
    fm, f1, f2 = values[im], values[i1], values[i2]
    t1 = fm / (fm - f1)
    t2 = fm / (fm - f2)
    vm = v[im]
    p1 = vm + t1[:, None] * (v[i1] - vm)
    p2 = vm + t2[:, None] * (v[i2] - vm)
    ln = lone_neg[:, None]
    a = torch.where(ln, p1, p2)
    b = torch.where(ln, p2, p1)
    return TriangleSegments(tri, mesh.face_item[tri], a, b, im, lone_neg, t1, t2)


def _per_item(mesh, idx: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    out = torch.zeros((mesh.num_items,) + tuple(x.shape[1:]), dtype=x.dtype, device=x.device)
    return out.index_add(0, idx, x)


def _area_parts(curve):
    mesh, values = curve.mesh, curve.values
    det = mesh.signed_areas()                                     # twice the areas (T,)
    all_neg = (values.detach()[mesh.faces] < 0).all(1)
    seg = triangle_segments(mesh, values)
    return mesh, values, det, all_neg, seg


def area(curve) -> torch.Tensor:
    """``(B,)`` area of the inside region ``{f < 0}`` of every item.

    Exact for the piecewise-linear function: the sum over triangles of the area of the
    part of each triangle where ``f < 0`` (closed form, see the module docstring), plus, for
    an ``enclosed`` item (a band mesh), the inside holes of its mesh.

    Example:
        >>> from torch_isc import ImplicitCurve, square_mesh
        >>> m = square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 4)
        >>> c = ImplicitCurve(m, m.verts.abs().amax(1) - 0.6)   # the square |x|, |y| < 0.6
        >>> area(c)
        tensor([1.4400], dtype=torch.float64)
    """
    check_curve(curve, "area")
    curve, sc = curve.unit_scaled()              # exact; areas back by / s / s (no overflow first)
    mesh, values, det, all_neg, seg = _area_parts(curve)
    full = torch.where(all_neg, 0.5 * det, torch.zeros_like(det))
    out = _per_item(mesh, mesh.face_item, full)
    A = 0.5 * det[seg.tri]
    corner = A * seg.t1 * seg.t2
    part = torch.where(seg.lone_neg, corner, A - corner)
    out = out.index_add(0, seg.item, part)
    if curve.enclosed is not None:
        # the inside holes of a band mesh: -Σ (a × b) / 2 over their edges (mesh on the left)
        ab, w, item = curve.hole_edges()
        a, b = mesh.verts[ab[:, 0]], mesh.verts[ab[:, 1]]
        out = out.index_add(0, item, -0.5 * w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    return out / sc / sc


def length(curve) -> torch.Tensor:
    """``(B,)`` total length of every item's zero set (the sum of its segments).

    Example:
        >>> from torch_isc import ImplicitCurve, square_mesh
        >>> m = square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 4)
        >>> c = ImplicitCurve(m, m.verts.abs().amax(1) - 0.6)
        >>> length(c)
        tensor([4.8000], dtype=torch.float64)
    """
    check_curve(curve, "length")
    curve, sc = curve.unit_scaled()
    mesh = curve.mesh
    seg = triangle_segments(mesh, curve.values)
    d = seg.b - seg.a
    ln = torch.sqrt((d * d).sum(1).clamp_min(torch.finfo(d.dtype).tiny))
    return torch.zeros(mesh.num_items, dtype=d.dtype, device=d.device).index_add(0, seg.item, ln) / sc


def centroid(curve) -> torch.Tensor:
    """``(B, 2)`` centroid of every item's inside region ``{f < 0}`` (NaN where it is empty).

    Example:
        >>> from torch_isc import ImplicitCurve, square_mesh
        >>> m = square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 4)
        >>> c = ImplicitCurve(m, m.verts[:, 0] - 0.3)      # inside: the part x < 0.3 of the square
        >>> centroid(c)
        tensor([[-0.3500,  0.0000]], dtype=torch.float64)
    """
    check_curve(curve, "centroid")
    curve, sc = curve.unit_scaled()
    mesh, values, det, all_neg, seg = _area_parts(curve)
    v = mesh.verts
    cT = v[mesh.faces].mean(1)                                    # (T,2)
    A = 0.5 * det
    full_a = torch.where(all_neg, A, torch.zeros_like(A))
    mom = _per_item(mesh, mesh.face_item, full_a[:, None] * cT)
    ar = _per_item(mesh, mesh.face_item, full_a)
    As = A[seg.tri]
    ac = As * seg.t1 * seg.t2
    vm = v[seg.lone]
    cc = (vm + seg.a + seg.b) / 3.0                               # the corner triangle (v_m, p1, p2)
    ln = seg.lone_neg
    part_a = torch.where(ln, ac, As - ac)
    part_m = torch.where(ln[:, None], ac[:, None] * cc, As[:, None] * cT[seg.tri] - ac[:, None] * cc)
    mom = mom.index_add(0, seg.item, part_m)
    ar = ar.index_add(0, seg.item, part_a)
    if curve.enclosed is not None:
        # inside holes: the polygon moments -Σ (a + b)(a × b) / 6 and areas -Σ (a × b) / 2
        ab, w, item = curve.hole_edges()
        a, b = v[ab[:, 0]], v[ab[:, 1]]
        cr = w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
        mom = mom.index_add(0, item, -(a + b) * cr[:, None] / 6.0)
        ar = ar.index_add(0, item, -0.5 * cr)
    # an item with no inside region: NaN, with a zero gradient (0/0 would poison the shared graph)
    empty = ar == 0
    out = mom / torch.where(empty, torch.ones_like(ar), ar)[:, None] / sc[:, None]
    return torch.where(empty[:, None], torch.full_like(out, float("nan")), out)


def curvature(curve, polylines=None, method: str = "turning") -> torch.Tensor:
    """``(Q,)`` signed curvature of the zero set at each of its vertices, aligned with
    ``curve.zero_set().points``.

    At a vertex ``q`` with neighbours ``p`` (before) and ``r`` (after) along its polyline:

    * ``method="turning"`` (default): the turning angle over the local arc length,
      ``κ = θ / ((|q - p| + |r - q|) / 2)``, ``θ = atan2((q-p)×(r-q), (q-p)·(r-q))``. The zero
      set is a polygon, whose curvature is concentrated at its vertices: ``Σ κ ℓ = Σ θ`` is
      exactly ``2π`` around a counter-clockwise loop (an inside region) and ``-2π`` around a
      hole, so the length-weighted mean of ``κ`` over a loop is ``2π / length``.
    * ``method="circle"``: the curvature of the circle through ``p, q, r`` (Menger),
      ``κ = 2 ((q - p) × (r - q)) / (|q - p| |r - q| |r - p|)``, exactly ``1/ρ`` for three
      points on a circle of radius ``ρ``.

    Both are noisy where two zero-set vertices nearly coincide (a mesh vertex whose value is
    near 0): average with the arc-length weights for a stable estimate. Positive where the
    curve turns toward the inside. The two end points of an open chain get 0.

    Args:
        polylines: the :class:`~torch_isc.core.extract.Polylines` to use (default
            ``curve.zero_set()``, differentiable).

    Example:
        >>> from torch_isc import ImplicitCurve, hexagon_mesh
        >>> m = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 1)
        >>> vals = torch.ones(7, dtype=torch.float64); vals[3] = -1     # a regular hexagon of radius 1/2
        >>> curvature(ImplicitCurve(m, vals), method="circle").round(decimals=9)
        tensor([2., 2., 2., 2., 2., 2.], dtype=torch.float64)
        >>> curvature(ImplicitCurve(m, vals))                          # (pi/3) / (1/2)
        tensor([2.0944, 2.0944, 2.0944, 2.0944, 2.0944, 2.0944], dtype=torch.float64)
    """
    check_curve(curve, "curvature")
    pl = curve.zero_set() if polylines is None else polylines
    pts = pl.points
    Q = pts.shape[0]
    dev = pts.device
    with torch.no_grad():
        first = torch.repeat_interleave(pl.first, pl.counts)
        n = torch.repeat_interleave(pl.counts, pl.counts)
        closed = torch.repeat_interleave(pl.closed, pl.counts)
        loc = torch.arange(Q, device=dev) - first
        prev = first + (loc - 1) % n.clamp_min(1)
        nxt = first + (loc + 1) % n.clamp_min(1)
        end = ~closed & ((loc == 0) | (loc == n - 1)) | (n < 3)
    p, q, r = pts[prev], pts, pts[nxt]
    u, w = q - p, r - q
    tiny = torch.finfo(pts.dtype).tiny

    def nrm(x):
        return torch.sqrt((x * x).sum(1).clamp_min(tiny))

    cr = u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]
    if method == "circle":
        # the product of three norms underflows to 0 at coincident points (0/0); clamped, k stays
        # below 2 / |r - p| (cr is at most |u| |w|)
        k = 2.0 * cr / (nrm(u) * nrm(w) * nrm(r - p)).clamp_min(tiny)
    elif method == "turning":
        dot = (u * w).sum(1)
        k = torch.atan2(cr, dot) / (0.5 * (nrm(u) + nrm(w)))
    else:
        raise ValueError(f"method must be 'turning' or 'circle', got {method!r}")
    return torch.where(end, torch.zeros_like(k), k)


def _point_segment_dist2(p, a, b):
    d = b - a
    L2 = (d * d).sum(-1)
    t = (((p - a) * d).sum(-1) / L2.clamp_min(torch.finfo(p.dtype).tiny)).clamp(0.0, 1.0)
    e = p - (a + t[..., None] * d)
    return (e * e).sum(-1)


def point_curve_distance(curve, points: torch.Tensor, point_item: Optional[torch.Tensor] = None,
                         return_segment: bool = False):
    """``(N,)`` exact Euclidean distance from each point to its item's zero set.

    The zero set is the union of the triangle segments; the nearest segment of each
    point is found under ``no_grad`` (all pairs of a point and a segment of its item,
    chunked), then the distance to it is recomputed differentiably (in the points, the
    vertex positions and the values). Items without a zero set give ``inf`` (no gradient).

    Args:
        points: ``(N, 2)``. point_item: ``(N,)`` long (default: all item 0).
        return_segment: also return the ``(N,)`` index of the nearest segment into
            :func:`triangle_segments` (-1 where there is none).

    Example:
        >>> from torch_isc import ImplicitCurve, square_mesh
        >>> m = square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), 4)
        >>> c = ImplicitCurve(m, m.verts.abs().amax(1) - 0.6)
        >>> point_curve_distance(c, torch.tensor([[0., 0.], [0.9, 0.], [0.8, 0.9]], dtype=torch.float64))
        tensor([0.6000, 0.3000, 0.3606], dtype=torch.float64)
    """
    check_curve(curve, "point_curve_distance")
    pts = points.to(curve.mesh.dtype)
    point_item = curve._point_item(pts, point_item)
    safe, ok = finite_rows(pts)
    unit, sc = curve.unit_scaled()                # exact; distances back by / s
    s_p = sc[point_item]
    d, best = unit_distance(unit, safe * s_p[:, None], point_item)
    # a point at infinity is infinitely far, a NaN point's distance is NaN (no gradient; no sync)
    bad = torch.where(pts.isnan().any(1), float("nan"), float("inf")).to(d.dtype)
    d = torch.where(ok, d / s_p, bad)
    best = torch.where(ok, best, torch.full_like(best, -1))
    return (d, best) if return_segment else d


def unit_distance(curve, pts: torch.Tensor, point_item: torch.Tensor):
    """:func:`point_curve_distance` of finite ``pts (N, 2)`` on a curve already brought to unit
    size (:meth:`~torch_isc.core.curve.ImplicitCurve.unit_scaled`), arguments already checked:
    ``(d (N,), best (N,))``."""
    mesh = curve.mesh
    N, dev = pts.shape[0], pts.device
    seg = triangle_segments(mesh, curve.values)
    with torch.no_grad():
        B = mesh.num_items
        cnt = torch.bincount(seg.item, minlength=B)
        sfirst = torch.cumsum(cnt, 0) - cnt
        ns = cnt[point_item]
        best = torch.full((N,), -1, dtype=torch.long, device=dev)
        a, b, p = seg.a.detach(), seg.b.detach(), pts.detach()
        for i0, i1, cp, off in expand_in_chunks(ns, _MAX_PAIRS):
            cs = sfirst[point_item[cp]] + off
            d2 = _point_segment_dist2(p[cp], a[cs], b[cs])
            mn = torch.full((i1 - i0,), float("inf"), dtype=d2.dtype, device=dev)
            mn = mn.scatter_reduce(0, cp - i0, d2, "amin")
            hit = d2 == mn[cp - i0]
            big = torch.iinfo(torch.long).max
            bs = torch.full((i1 - i0,), big, dtype=torch.long, device=dev)
            bs = bs.scatter_reduce(0, (cp - i0)[hit], cs[hit], "amin")
            best[i0:i1] = torch.where(bs == big, torch.full_like(bs, -1), bs)
        has = best >= 0
    if seg.a.shape[0] == 0:
        return torch.full((N,), float("inf"), dtype=pts.dtype, device=dev), best
    bc = best.clamp_min(0)
    d2 = _point_segment_dist2(pts, seg.a[bc], seg.b[bc])
    d = torch.sqrt(d2.clamp_min(torch.finfo(pts.dtype).tiny))
    return torch.where(has, d, torch.full_like(d, float("inf"))), best
