"""Distances between sets of polylines, and the scoring rule of the evaluation cases.

A *polyline set* is a list whose items are either ``(points, closed)`` pairs or
``{"closed": bool, "points": ...}`` dicts (the form of :attr:`ReconstructionResult.polylines`);
``points`` is an ``(n, 2)`` tensor, array or nested list. A closed polyline does not need to
repeat its first vertex (a repeated one is harmless).

Distances are measured from densely resampled points of one set to the *segments* of the other
set (exact point-to-segment distances), so a directed distance is exact up to half the
resampling spacing. The search prunes far segments block by block (nothing that can be nearest
is skipped) and every temporary is chunked, so memory stays bounded whatever the sizes. The
public functions run torch on one CPU thread while they work (see :func:`_one_thread`).

Only numpy and torch are used (CPU, float64).
"""
from __future__ import annotations

import contextlib
import functools
import math
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

__all__ = [
    "resample_polyline",
    "point_distances",
    "directed_distances",
    "hausdorff",
    "chamfer",
    "distance_summary",
    "match_topology",
    "score_case",
    "bbox_diagonal",
]

_DT = torch.float64
_CHUNK_ELEMS = 1 << 20  # entries per temporary (1M doubles, 8 MB)
_BLOCK = 128            # points per spatial block of the nearest-segment search


# ----------------------------------------------------------------------------- helpers

@contextlib.contextmanager
def _one_thread():
    """Run torch's CPU ops on one thread meanwhile. The work here is many small blocks, which
    gain nothing from intra-op threads and slow down badly (tens of times) when those threads
    compete with other processes for the cores."""
    n = torch.get_num_threads()
    if n == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _single_threaded(fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with _one_thread():
            return fn(*args, **kwargs)
    return wrapper


def _as_points(points: Any) -> torch.Tensor:
    if isinstance(points, torch.Tensor):
        t = points.detach().to(device="cpu", dtype=_DT)
    else:
        t = torch.as_tensor(np.asarray(points, dtype=np.float64))
    t = t.reshape(-1, 2) if t.numel() else t.reshape(0, 2)
    return t


def _normalize(polylines: Any) -> List[Tuple[torch.Tensor, bool]]:
    """Polyline set -> list of ``(points float64 (n,2), closed)`` with empty polylines dropped."""
    if hasattr(polylines, "polylines"):  # a ReconstructionResult
        polylines = polylines.polylines
    out: List[Tuple[torch.Tensor, bool]] = []
    for p in polylines:
        if isinstance(p, dict):
            pts, closed = p["points"], p.get("closed", False)
        else:
            pts, closed = p
        t = _as_points(pts)
        if t.shape[0] == 0:
            continue
        out.append((t, bool(closed)))
    return out


def _segments(points: torch.Tensor, closed: bool) -> Tuple[torch.Tensor, torch.Tensor]:
    """Segment start points and end points ``(S, 2)`` each (a single point gives one
    degenerate segment)."""
    if points.shape[0] == 1:
        return points, points
    if closed:
        return points, torch.roll(points, -1, 0)
    return points[:-1], points[1:]


def _all_segments(polylines: List[Tuple[torch.Tensor, bool]]) -> Tuple[torch.Tensor, torch.Tensor, List[int]]:
    """Segments of a whole set, and ``bounds`` (polyline ``g`` owns ``bounds[g]:bounds[g+1]``)."""
    if not polylines:
        z = torch.zeros(0, 2, dtype=_DT)
        return z, z, [0]
    a, b = zip(*(_segments(p, c) for p, c in polylines))
    bounds = [0]
    for s in a:
        bounds.append(bounds[-1] + s.shape[0])
    return torch.cat(a), torch.cat(b), bounds


def _morton_order(q: torch.Tensor) -> torch.Tensor:
    """A permutation of the points along a Z-order curve (nearby points end up nearby)."""
    lo = q.amin(0)
    ext = (q.amax(0) - lo).clamp_min(1e-300)
    g = ((q - lo) / ext * 65535).long().clamp_(0, 65535)

    def spread(x):
        x = (x | (x << 8)) & 0x00FF00FF
        x = (x | (x << 4)) & 0x0F0F0F0F
        x = (x | (x << 2)) & 0x33333333
        return (x | (x << 1)) & 0x55555555

    return torch.argsort(spread(g[:, 0]) | (spread(g[:, 1]) << 1))


def _point_segment_min(q: torch.Tensor, a: torch.Tensor, b: torch.Tensor,
                       bounds: Optional[Sequence[int]] = None):
    """Exact distance from each point of ``q (M,2)`` to the nearest segment ``a[s]b[s]``.

    Returns ``(M,)``; with ``bounds = [0, s1, ..., S]`` (contiguous segment groups, one per
    polyline) returns ``(M, G)``, the distance to each group (``inf`` for an empty group).

    The points are cut into spatially compact blocks (Z-order); for a block, a segment is
    measured only when the distance from the block's box to the segment's box is not larger
    than an upper bound of the block's distance to the segment's group (the farthest box corner
    to a vertex of the group), so nothing that can be nearest is skipped. Blocks of bounds and
    of point-segment pairs hold at most ``_CHUNK_ELEMS`` entries, so memory stays bounded.
    """
    M, S = q.shape[0], a.shape[0]
    grouped = bounds is not None
    if not grouped:
        bounds = [0, S]
    G = len(bounds) - 1
    out = torch.full((M, G), math.inf, dtype=_DT)
    if M and S:
        gid = torch.repeat_interleave(torch.arange(G), torch.as_tensor(bounds).diff())
        d = b - a
        inv_dd = 1.0 / (d * d).sum(1).clamp_min(1e-300)  # degenerate segments -> t = 0
        smin, smax = torch.minimum(a, b), torch.maximum(a, b)
        order = _morton_order(q)
        nblk = (M + _BLOCK - 1) // _BLOCK
        per_batch = max(1, _CHUNK_ELEMS // max(S, G))
        for k0 in range(0, nblk, per_batch):
            ks = range(k0, min(nblk, k0 + per_batch))
            idxs = [order[k * _BLOCK:(k + 1) * _BLOCK] for k in ks]
            lo = torch.stack([q[ix].amin(0) for ix in idxs])          # (nb, 2)
            hi = torch.stack([q[ix].amax(0) for ix in idxs])
            # lower bound: box-to-box distance; upper bound: farthest corner to vertex a_s
            gap = (smin[None] - hi[:, None]).clamp_min(0) + (lo[:, None] - smax[None]).clamp_min(0)
            low = torch.linalg.vector_norm(gap, dim=-1)                    # (nb, S)
            far = torch.maximum((lo[:, None] - a[None]).abs(), (hi[:, None] - a[None]).abs())
            up = torch.linalg.vector_norm(far, dim=-1)                     # (nb, S)
            up_g = torch.full((len(idxs), G), math.inf, dtype=_DT).scatter_reduce_(
                1, gid.expand(len(idxs), S), up, "amin")
            cand = low <= up_g[:, gid] * (1 + 1e-9)
            del gap, low, far, up
            for j, ix in enumerate(idxs):
                cs = torch.nonzero(cand[j]).squeeze(1)
                qx, qy = q[ix, 0:1], q[ix, 1:2]                           # (m, 1)
                r2 = torch.full((len(ix), G), math.inf, dtype=_DT)        # squared distances
                step = max(1, _CHUNK_ELEMS // len(ix))
                for c0 in range(0, cs.numel(), step):
                    c = cs[c0:c0 + step]
                    ax, ay, dx, dy = a[c, 0], a[c, 1], d[c, 0], d[c, 1]
                    wx, wy = qx - ax, qy - ay                               # (m, C)
                    t = (wx * dx + wy * dy).mul_(inv_dd[c]).clamp_(0.0, 1.0)
                    wx.sub_(t * dx)
                    wy.sub_(t.mul_(dy))
                    r = wx.mul_(wx).add_(wy.mul_(wy))
                    if G == 1:
                        r2 = torch.minimum(r2, r.amin(1, keepdim=True))
                    else:
                        r2.scatter_reduce_(1, gid[c].expand(len(ix), c.numel()), r, "amin")
                out[ix] = r2.sqrt_()
    return out if grouped else out[:, 0]


def bbox_diagonal(polylines_or_points: Any) -> float:
    """Diagonal of the bounding box of a polyline set, or of an ``(N, 2)`` point array."""
    if isinstance(polylines_or_points, (torch.Tensor, np.ndarray)):
        pts = _as_points(polylines_or_points)
    else:
        pl = _normalize(polylines_or_points)
        pts = torch.cat([p for p, _ in pl]) if pl else torch.zeros(0, 2, dtype=_DT)
    if pts.shape[0] == 0:
        return 0.0
    ext = pts.amax(0) - pts.amin(0)
    return float(torch.linalg.vector_norm(ext))


# ----------------------------------------------------------------------------- resampling

def _resample(points: torch.Tensor, closed: bool, spacing: float) -> Tuple[torch.Tensor, torch.Tensor]:
    """Uniform arc-length samples ``(m, 2)`` and their arc-length weights ``(m,)``
    (summing to the length; a zero-length polyline gives its vertices with unit weights)."""
    n = points.shape[0]
    if n == 1:
        return points.clone(), torch.ones(1, dtype=_DT)
    a, b = _segments(points, closed)
    seg_len = torch.linalg.vector_norm(b - a, dim=1)
    total = float(seg_len.sum())
    if total <= 0.0:
        return points[:1].clone(), torch.ones(1, dtype=_DT)
    m = max(1, int(math.ceil(total / spacing)))      # number of intervals
    h = total / m
    if closed:
        s = torch.arange(m, dtype=_DT) * h
        w = torch.full((m,), h, dtype=_DT)
    else:
        s = torch.arange(m + 1, dtype=_DT) * h
        s[-1] = total
        w = torch.full((m + 1,), h, dtype=_DT)
        w[0] = w[-1] = 0.5 * h                        # trapezoid rule
    cum = torch.cat([torch.zeros(1, dtype=_DT), torch.cumsum(seg_len, 0)])
    idx = torch.searchsorted(cum, s, right=True).sub_(1).clamp_(0, a.shape[0] - 1)
    frac = ((s - cum[idx]) / seg_len[idx].clamp_min(1e-300)).clamp_(0.0, 1.0)
    pts = a[idx] + frac[:, None] * (b[idx] - a[idx])
    return pts, w


def resample_polyline(points: Any, closed: bool, spacing: float):
    """Dense uniform (arc-length) resampling of one polyline.

    Args:
        points: ``(n, 2)`` vertices (tensor or array); a closed polyline need not repeat its first.
        closed: whether the last vertex connects back to the first.
        spacing: the largest distance along the curve between consecutive samples (> 0).

    Returns:
        ``(m, 2)`` samples, the same kind as ``points`` (a float64 tensor for a tensor input,
        a float64 numpy array otherwise). An open polyline keeps both end points; a closed one
        does not repeat its first sample. ``m = ceil(length / spacing)`` (+1 when open).
    """
    if not spacing > 0:
        raise ValueError(f"spacing must be > 0, got {spacing!r}")
    t = _as_points(points)
    if t.shape[0] == 0:
        out = t
    else:
        out, _ = _resample(t, bool(closed), float(spacing))
    return out if isinstance(points, torch.Tensor) else out.numpy()


def _default_spacing(*sets: List[Tuple[torch.Tensor, bool]]) -> float:
    pts = [p for s in sets for p, _ in s]
    if not pts:
        return 1.0
    diag = bbox_diagonal(torch.cat(pts))
    return diag * 1e-3 if diag > 0 else 1.0


# ----------------------------------------------------------------------------- distances

@_single_threaded
def point_distances(points: Any, polylines: Any) -> torch.Tensor:
    """``(N,)`` exact distance from each point to the nearest segment of ``polylines``
    (``inf`` when the set is empty)."""
    q = _as_points(points)
    a, b, _ = _all_segments(_normalize(polylines))
    return _point_segment_min(q, a, b)


def _sample_set(A, spacing):
    """Resampled points of a set, their arc-length weights and the index of their polyline."""
    if not A:
        return torch.zeros(0, 2, dtype=_DT), torch.zeros(0, dtype=_DT), torch.zeros(0, dtype=torch.long)
    qs, ws, own = [], [], []
    for i, (p, c) in enumerate(A):
        q, w = _resample(p, c, spacing)
        qs.append(q)
        ws.append(w)
        own.append(torch.full((q.shape[0],), i, dtype=torch.long))
    return torch.cat(qs), torch.cat(ws), torch.cat(own)


def _directed(A, B, spacing, sel):
    """Samples of ``A``: ``(weights (m,), owner (m,), distance to the set B (m,), distance to
    each polyline ``B[k]``, ``k`` in ``sel`` (m, len(sel)))``."""
    q, w, own = _sample_set(A, spacing)
    a, b, _ = _all_segments(B)
    nearest = _point_segment_min(q, a, b)
    a, b, bounds = _all_segments([B[k] for k in sel])
    return w, own, nearest, _point_segment_min(q, a, b, bounds)


@_single_threaded
def directed_distances(a_polylines: Any, b_polylines: Any, spacing: Optional[float] = None):
    """Samples of ``a`` resampled at ``spacing``, their arc-length weights, and their distance
    to the set ``b``: ``(samples (m,2), weights (m,), distances (m,))``."""
    A, B = _normalize(a_polylines), _normalize(b_polylines)
    if spacing is None:
        spacing = _default_spacing(A, B)
    q, w, _ = _sample_set(A, float(spacing))
    a, b, _ = _all_segments(B)
    return q, w, _point_segment_min(q, a, b)


class _Cross:
    """Both directed distance fields between two normalized sets (computed once, reused).

    ``a_sel`` / ``b_sel``: the polylines of each set that take part in the pairwise Hausdorff
    matrix (default: all)."""

    def __init__(self, A, B, spacing: float, a_sel: Optional[Sequence[int]] = None,
                 b_sel: Optional[Sequence[int]] = None):
        self.nA, self.nB = len(A), len(B)
        self.a_sel = list(range(self.nA)) if a_sel is None else list(a_sel)
        self.b_sel = list(range(self.nB)) if b_sel is None else list(b_sel)
        self.wa, self.own_a, self.da, self.Dab = _directed(A, B, spacing, self.b_sel)  # Dab (Ma, |b_sel|)
        self.wb, self.own_b, self.db, self.Dba = _directed(B, A, spacing, self.a_sel)  # Dba (Mb, |a_sel|)

    def summary(self) -> Dict[str, float]:
        if self.nA == 0 and self.nB == 0:
            return dict(hausdorff=0.0, chamfer=0.0, a_to_b_max=0.0, b_to_a_max=0.0, a_to_b_mean=0.0, b_to_a_mean=0.0)
        if self.nA == 0 or self.nB == 0:
            inf = math.inf
            return dict(hausdorff=inf, chamfer=inf, a_to_b_max=inf, b_to_a_max=inf, a_to_b_mean=inf, b_to_a_mean=inf)
        da, db = self.da, self.db
        ab_max, ba_max = float(da.max()), float(db.max())
        ab_mean = float((self.wa * da).sum() / self.wa.sum())
        ba_mean = float((self.wb * db).sum() / self.wb.sum())
        return dict(hausdorff=max(ab_max, ba_max), chamfer=0.5 * (ab_mean + ba_mean),
                    a_to_b_max=ab_max, b_to_a_max=ba_max, a_to_b_mean=ab_mean, b_to_a_mean=ba_mean)

    def hausdorff_matrix(self) -> torch.Tensor:
        """``(len(a_sel), len(b_sel))`` pairwise symmetric Hausdorff distances."""
        na, nb = len(self.a_sel), len(self.b_sel)
        if na == 0 or nb == 0:
            return torch.zeros(na, nb, dtype=_DT)
        # max over the samples of polyline i of the distance to polyline j, and vice versa
        ab = torch.zeros(self.nA, nb, dtype=_DT).scatter_reduce_(
            0, self.own_a[:, None].expand_as(self.Dab), self.Dab, "amax")[self.a_sel]
        ba = torch.zeros(self.nB, na, dtype=_DT).scatter_reduce_(
            0, self.own_b[:, None].expand_as(self.Dba), self.Dba, "amax")[self.b_sel]
        return torch.maximum(ab, ba.T)


@_single_threaded
def distance_summary(a_polylines: Any, b_polylines: Any, spacing: Optional[float] = None) -> Dict[str, float]:
    """Both directions at once: ``{"hausdorff", "chamfer", "a_to_b_max", "b_to_a_max",
    "a_to_b_mean", "b_to_a_mean"}`` (``inf`` everywhere when one set is empty and the other is
    not; 0 when both are empty). Means are taken along the curves (arc-length weighted)."""
    A, B = _normalize(a_polylines), _normalize(b_polylines)
    if spacing is None:
        spacing = _default_spacing(A, B)
    return _Cross(A, B, float(spacing)).summary()


def hausdorff(a_polylines: Any, b_polylines: Any, spacing: Optional[float] = None) -> float:
    """Symmetric Hausdorff distance between two polyline sets (exact up to ``spacing / 2``;
    default spacing: 1e-3 of the bounding-box diagonal of both sets)."""
    return distance_summary(a_polylines, b_polylines, spacing)["hausdorff"]


def chamfer(a_polylines: Any, b_polylines: Any, spacing: Optional[float] = None) -> float:
    """Mean symmetric (Chamfer) distance: the mean of the two directed mean nearest distances,
    each mean taken along the curve (arc-length weighted)."""
    return distance_summary(a_polylines, b_polylines, spacing)["chamfer"]


# ----------------------------------------------------------------------------- topology

def _match(H: torch.Tensor, n_open: int, max_dist: float) -> Dict[str, Any]:
    """Topology verdict from the ``(n_closed, n_truth)`` Hausdorff matrix (already / diag)."""
    n_closed, n_truth = H.shape
    matches: List[Optional[int]] = []
    distances: List[float] = []
    matched_distances: List[Optional[float]] = []
    for j in range(n_truth):
        if n_closed == 0:
            matches.append(None)
            distances.append(math.inf)
            matched_distances.append(None)
            continue
        i = int(torch.argmin(H[:, j]))
        dist = float(H[i, j])
        distances.append(dist)
        if int(torch.argmin(H[i, :])) == j and dist < max_dist:
            matches.append(i)
            matched_distances.append(dist)
        else:
            matches.append(None)
            matched_distances.append(None)
    reasons = []
    if n_closed != n_truth:
        reasons.append(f"{n_closed} closed curve(s) for {n_truth} truth curve(s)")
    if n_open:
        reasons.append(f"{n_open} open chain(s)")
    unmatched = [j for j, m in enumerate(matches) if m is None]
    if unmatched:
        reasons.append("unmatched truth curve(s) " + ", ".join(str(j) for j in unmatched))
    ok = not reasons
    return dict(ok=ok, n_closed=n_closed, n_open=n_open, n_truth=n_truth, matches=matches,
                distances=distances, matched_distances=matched_distances,
                reason="ok" if ok else "; ".join(reasons))


@_single_threaded
def match_topology(recon_polylines: Any, truth_polylines: Any, diag: float, max_dist: float = 0.10,
                   spacing: Optional[float] = None) -> Dict[str, Any]:
    """The cases' topology rule.

    Right when the number of closed reconstructed curves equals the number of truth curves,
    there is no open chain, and every truth curve has a closed reconstructed curve that is its
    mutually nearest one by Hausdorff distance (the truth's nearest reconstructed curve has that
    truth curve as its own nearest) at a Hausdorff distance below ``max_dist * diag``. Mutual
    nearest pairs are one to one, so with equal counts this is a one-to-one matching.

    Args:
        recon_polylines: polyline set of the reconstruction (closed and open).
        truth_polylines: polyline set of the truth (taken as given; the cases' truth curves are
            all closed).
        diag: the truth's bounding-box diagonal (distances are reported divided by it).
        max_dist: the largest matched Hausdorff distance, as a fraction of ``diag``.
        spacing: resampling spacing (default ``1e-3 * diag``).

    Returns:
        ``{"ok", "n_closed", "n_open", "n_truth", "matches", "distances", "matched_distances",
        "reason"}``: ``matches[j]`` is the index (among the closed reconstructed curves, in
        order) of truth ``j``'s partner or ``None``; ``distances[j]`` is the Hausdorff distance /
        diag from truth ``j`` to its nearest closed reconstructed curve (``inf`` if none);
        ``matched_distances[j]`` is that distance when truth ``j`` is matched, else ``None``.
    """
    R = _normalize(recon_polylines)
    T = _normalize(truth_polylines)
    closed = [(p, c) for p, c in R if c]
    diag = float(diag)
    if not diag > 0:
        diag = bbox_diagonal(T) or 1.0
    if spacing is None:
        spacing = 1e-3 * diag
    H = _Cross(closed, T, float(spacing)).hausdorff_matrix() / diag
    return _match(H, len(R) - len(closed), max_dist)


@_single_threaded
def score_case(result_polylines: Any, truth_json_dict: Dict[str, Any], spacing_frac: float = 1e-3,
               max_dist: float = 0.10) -> Dict[str, Any]:
    """Score a reconstruction against a case's truth (``NAME.truth.json`` loaded as a dict).

    Args:
        result_polylines: the reconstruction's polyline set (``result.polylines`` or the result).
        truth_json_dict: ``{"curves": [[[x, y], ...], ...], "n_components", ...}``; every truth
            curve is closed.
        spacing_frac: resampling spacing as a fraction of the truth's bounding-box diagonal.
        max_dist: topology matching threshold (fraction of the diagonal).

    Returns:
        ``{"topology_ok", "hausdorff", "chamfer", "n_closed", "n_open", "n_truth", "diag",
        "topology"}``: distances divided by the truth's bounding-box diagonal (``inf`` when the
        reconstruction is empty); ``topology`` is :func:`match_topology`'s dict.
    """
    truth = [(c, True) for c in truth_json_dict["curves"]]
    T = _normalize(truth)
    diag = bbox_diagonal(T)
    if not diag > 0:
        raise ValueError("truth curves have an empty bounding box")
    spacing = spacing_frac * diag
    R = _normalize(result_polylines)
    closed = [i for i, (_, c) in enumerate(R) if c]
    cross = _Cross(R, T, spacing, a_sel=closed)
    H = cross.hausdorff_matrix() / diag
    topo = _match(H, len(R) - len(closed), max_dist)
    n_truth = int(truth_json_dict.get("n_components", len(T)))
    if n_truth != len(T):  # the rule counts n_components; the curves list must agree
        topo["ok"] = False
        topo["reason"] = f"truth lists n_components={n_truth} but has {len(T)} curves"
    d = cross.summary()
    return dict(topology_ok=bool(topo["ok"]), hausdorff=d["hausdorff"] / diag, chamfer=d["chamfer"] / diag,
                n_closed=topo["n_closed"], n_open=topo["n_open"], n_truth=n_truth, diag=diag, topology=topo)
