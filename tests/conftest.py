"""Shared fixtures and independent reference implementations for the torch_isc tests.

The references here are deliberately naive (Python loops, exact rational arithmetic,
float64 linear solves) and share no code with the library, so that a test comparing the
library against them can actually fail. Test modules import them with
``from conftest import ...`` (tests/ is on sys.path under pytest's default import mode).
"""
from __future__ import annotations

import math
from fractions import Fraction
from typing import Callable, List, Optional, Sequence, Tuple

import pytest
import torch

# ----------------------------------------------------------------------------- fixtures


def _devices() -> List[str]:
    out = ["cpu"]
    if torch.cuda.is_available():
        out.append("cuda")
    return out


@pytest.fixture(params=_devices())
def device(request) -> torch.device:
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    return request.param


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield


def tols(dtype: torch.dtype) -> Tuple[float, float]:
    """(rtol, atol) for comparing computed geometry of unit-scale meshes."""
    return (1e-5, 1e-5) if dtype == torch.float32 else (1e-11, 1e-11)


@pytest.fixture
def tol(dtype):
    return tols(dtype)


def assert_same(a: torch.Tensor, b: torch.Tensor, rtol: float = 1e-6, atol: float = 1e-9) -> None:
    """Bit equality on the CPU. On CUDA, scatter and index adds are atomic and sum in any order,
    so two runs agree to rounding (amplified by the solver's iterations), not bit for bit: there
    the check is ``assert_close`` at ``rtol``/``atol`` (a leak between items or a changed step
    would be far larger)."""
    if a.device.type == "cpu" and b.device.type == "cpu":
        assert a.dtype == b.dtype and torch.equal(a, b)
    else:
        torch.testing.assert_close(a, b, rtol=rtol, atol=atol)


# ----------------------------------------------------------------------------- reference geometry


def ref_bary64(tri: Sequence[Sequence[float]], p: Sequence[float]) -> List[float]:
    """Barycentric coordinates by solving the 3x3 system of eq. 2.2 with Cramer's rule (float64)."""
    (x0, y0), (x1, y1), (x2, y2) = [(float(a), float(b)) for a, b in tri]
    px, py = float(p[0]), float(p[1])
    det = x0 * (y1 - y2) + x1 * (y2 - y0) + x2 * (y0 - y1)
    l0 = (px * (y1 - y2) + x1 * (y2 - py) + x2 * (py - y1)) / det
    l1 = (x0 * (py - y2) + px * (y2 - y0) + x2 * (y0 - py)) / det
    l2 = (x0 * (y1 - py) + x1 * (py - y0) + px * (y0 - y1)) / det
    return [l0, l1, l2]


def ref_bary_exact(tri, p) -> List[Fraction]:
    """Exact barycentric coordinates (inputs converted exactly from float to Fraction)."""
    (x0, y0), (x1, y1), (x2, y2) = [(Fraction(float(a)), Fraction(float(b))) for a, b in tri]
    px, py = Fraction(float(p[0])), Fraction(float(p[1]))
    det = x0 * (y1 - y2) + x1 * (y2 - y0) + x2 * (y0 - y1)
    l0 = (px * (y1 - y2) + x1 * (y2 - py) + x2 * (py - y1)) / det
    l1 = (x0 * (py - y2) + px * (y2 - y0) + x2 * (y0 - py)) / det
    l2 = (x0 * (y1 - py) + x1 * (py - y0) + px * (y0 - y1)) / det
    return [l0, l1, l2]


def brute_locate(verts: torch.Tensor, faces: torch.Tensor, face_item: Sequence[int],
                 points: torch.Tensor, point_item: Sequence[int], exact: bool = False,
                 candidates: Optional[Callable[[int], Sequence[int]]] = None,
                 inside_tol: float = 0.0):
    """Loop over every triangle of the point's item (or ``candidates(p)``).

    Returns, per point, ``(best_face, best_score, scores_dict)`` where the score is the
    smallest barycentric coordinate, ``best_face`` is the face with the largest score, ties to
    the lowest index, or -1 when the best score is below ``-inside_tol``.
    """
    V = verts.detach().cpu().double().tolist()
    F = faces.detach().cpu().tolist()
    P = points.detach().cpu().double().tolist()
    fi = list(face_item)
    out = []
    for n, (p, b) in enumerate(zip(P, point_item)):
        cand = candidates(n) if candidates is not None else [t for t in range(len(F)) if fi[t] == b]
        scores = {}
        for t in cand:
            if t < 0:
                continue
            scores[t] = min(ref_bary64([V[i] for i in F[t]], p))
        if exact and scores:
            # float64 errors are far below 1e-9 here: only near-best faces can tie or win
            top = max(scores.values())
            for t in [t for t, s in scores.items() if s >= top - 1e-9]:
                scores[t] = min(ref_bary_exact([V[i] for i in F[t]], p))
            top = max(scores.values())
            assert all(isinstance(s, Fraction) or s < top - 1e-10 for s in scores.values())
        if not scores:
            out.append((-1, None, scores))
            continue
        best = max(scores.values())
        face = min(t for t, s in scores.items() if s == best)
        if best < -inside_tol:
            face = -1
        out.append((face, best, scores))
    return out


# ----------------------------------------------------------------------------- polylines


def polygon_signed_area(pts: torch.Tensor) -> float:
    p = pts.detach().cpu().double()
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float((x * torch.roll(y, -1) - torch.roll(x, -1) * y).sum())


def winding_number(poly: torch.Tensor, q: Sequence[float]) -> int:
    """Winding number of the closed polygon ``poly`` around the point ``q`` (naive loop)."""
    p = poly.detach().cpu().double().tolist()
    total = 0.0
    n = len(p)
    for i in range(n):
        ax, ay = p[i][0] - q[0], p[i][1] - q[1]
        bx, by = p[(i + 1) % n][0] - q[0], p[(i + 1) % n][1] - q[1]
        total += math.atan2(ax * by - ay * bx, ax * bx + ay * by)
    return int(round(total / (2 * math.pi)))


def _orient(a, b, c) -> float:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def _on_segment(a, b, c) -> bool:
    return min(a[0], b[0]) <= c[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= c[1] <= max(a[1], b[1])


def segments_intersect(a, b, c, d) -> bool:
    """Closed segments ``ab`` and ``cd`` share a point (touching counts)."""
    o1, o2, o3, o4 = _orient(a, b, c), _orient(a, b, d), _orient(c, d, a), _orient(c, d, b)
    if ((o1 > 0 and o2 < 0) or (o1 < 0 and o2 > 0)) and ((o3 > 0 and o4 < 0) or (o3 < 0 and o4 > 0)):
        return True
    if o1 == 0 and _on_segment(a, b, c):
        return True
    if o2 == 0 and _on_segment(a, b, d):
        return True
    if o3 == 0 and _on_segment(c, d, a):
        return True
    if o4 == 0 and _on_segment(c, d, b):
        return True
    return False


def find_intersections(polylines: Sequence[Tuple[torch.Tensor, bool]]) -> List[tuple]:
    """Naive O(n^2) check of a list of ``(points, closed)``: every pair of segments that
    meet, except consecutive segments of one polyline (which share their common point)."""
    segs = []   # (poly, index, n_segments, closed, a, b)
    for k, (pts, closed) in enumerate(polylines):
        p = pts.detach().cpu().double().tolist()
        n = len(p)
        ns = n if closed else n - 1
        if closed and n < 3:
            raise AssertionError(f"closed polyline {k} has only {n} points")
        for i in range(ns):
            segs.append((k, i, ns, closed, p[i], p[(i + 1) % n]))
    bad = []
    for x in range(len(segs)):
        k1, i1, n1, c1, a, b = segs[x]
        for y in range(x + 1, len(segs)):
            k2, i2, n2, c2, c, d = segs[y]
            if k1 == k2:
                if abs(i1 - i2) == 1 or (c1 and abs(i1 - i2) == n1 - 1):
                    continue
            if segments_intersect(a, b, c, d):
                bad.append((k1, i1, k2, i2))
    return bad


def components_by_bfs(V, edges, join):
    """Connected components of the graph on ``V`` vertices whose edges ``(E, 2)`` have ``join``
    set, by plain breadth-first search: each vertex's label is its component's smallest index."""
    nb = [[] for _ in range(V)]
    for (a, b), j in zip(edges.tolist(), join.tolist()):
        if j:
            nb[a].append(b)
            nb[b].append(a)
    lab = [-1] * V
    for v in range(V):
        if lab[v] >= 0:
            continue
        comp, todo = [v], [v]
        lab[v] = v
        while todo:
            u = todo.pop()
            for w in nb[u]:
                if lab[w] < 0:
                    lab[w] = v
                    comp.append(w)
                    todo.append(w)
    return lab                                   # v is the smallest index of its component


def gpu_floor_counter():
    """``gpu_floor.OpCounter`` from ``../shared/tools`` beside the repository, or None where that
    folder is absent (the launch and sync counts are then not checked)."""
    import sys
    from pathlib import Path
    tools = Path(__file__).resolve().parents[2] / "shared" / "tools"
    if not (tools / "gpu_floor.py").exists():
        return None
    if str(tools) not in sys.path:
        sys.path.insert(0, str(tools))
    from gpu_floor import OpCounter
    return OpCounter
