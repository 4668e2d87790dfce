"""Tests of torch_isc.core.extract against a naive dictionary-based tracer.

The reference builds one directed segment per mixed triangle, orients it with a determinant
of the actual crossing points against a negative vertex (negative side on the left), chains
the segments through a dict and canonicalizes loops to start at their smallest edge id.
"""
from __future__ import annotations

import math

import pytest
import torch

from torch_isc.core.extract import Polylines, extract_zero_set
from torch_isc.core.mesh import MeshBatch, hexagon_mesh, square_mesh

from conftest import find_intersections, polygon_signed_area


# ----------------------------------------------------------------------------- reference


def naive_trace(mesh: MeshBatch, values: torch.Tensor):
    V = mesh.verts.detach().double().cpu().tolist()
    F = mesh.faces.cpu().tolist()
    val = values.detach().double().cpu().tolist()
    eid = {tuple(e): k for k, e in enumerate(mesh.edges.cpu().tolist())}
    item_of_edge = mesh.edge_item.cpu().tolist()

    def cross_pt(a, b):
        t = val[a] / (val[a] - val[b])
        return (V[a][0] + t * (V[b][0] - V[a][0]), V[a][1] + t * (V[b][1] - V[a][1]))

    succ, nodes, n_mixed = {}, set(), 0
    for tri in F:
        neg = [val[i] < 0 for i in tri]
        if all(neg) or not any(neg):
            continue
        n_mixed += 1
        crossed = []
        for c in range(3):
            a, b = tri[c], tri[(c + 1) % 3]
            if (val[a] < 0) != (val[b] < 0):
                crossed.append((eid[(min(a, b), max(a, b))], cross_pt(a, b)))
        assert len(crossed) == 2
        (e1, p), (e2, q) = crossed
        nv = V[tri[neg.index(True)]]
        o = (q[0] - p[0]) * (nv[1] - p[1]) - (q[1] - p[1]) * (nv[0] - p[0])
        assert o != 0
        if o < 0:
            e1, e2 = e2, e1
        assert e1 not in succ
        succ[e1] = e2
        nodes.update((e1, e2))
    has_pred = set(succ.values())
    out, seen = [], set()
    for h in sorted(nodes):
        if h in has_pred:
            continue
        seq = [h]
        while seq[-1] in succ:
            seq.append(succ[seq[-1]])
        seen.update(seq)
        out.append((tuple(seq), False, item_of_edge[h]))
    for s in sorted(nodes):
        if s in seen:
            continue
        seq = [s]
        while succ[seq[-1]] != s:
            seq.append(succ[seq[-1]])
        seen.update(seq)
        out.append((tuple(seq), True, item_of_edge[s]))
    return out, n_mixed


def canonical(pl: Polylines):
    out = []
    for e, c, b in zip(torch.split(pl.edge.cpu(), pl.counts.tolist()), pl.closed.tolist(), pl.item.tolist()):
        seq = e.tolist()
        if c:
            k = seq.index(min(seq))
            seq = seq[k:] + seq[:k]
        out.append((tuple(seq), bool(c), b))
    return out


def check_structure(pl: Polylines, mesh: MeshBatch, values: torch.Tensor):
    K = len(pl)
    assert pl.first.shape == pl.counts.shape == pl.closed.shape == pl.item.shape == (K,)
    Q = int(pl.counts.sum()) if K else 0
    assert pl.points.shape == (Q, 2) and pl.edge.shape == (Q,)
    if K:
        assert torch.equal(pl.first, torch.cumsum(pl.counts, 0) - pl.counts)
        assert bool((pl.item[1:] >= pl.item[:-1]).all())
        assert bool((pl.counts[pl.closed] >= 3).all())
        assert bool((pl.counts >= 2).all())
    assert pl.num_items == mesh.num_items
    assert torch.equal(pl.per_item_counts().cpu(), torch.bincount(pl.item.cpu(), minlength=mesh.num_items))
    assert torch.equal((pl.num_closed() + pl.num_open()).cpu(), pl.per_item_counts().cpu())
    # crossing points by the hand formula, on the edge they name
    e = mesh.edges[pl.edge].cpu()
    V = mesh.verts.detach().double().cpu()
    f = values.detach().double().cpu()
    fa, fb = f[e[:, 0]], f[e[:, 1]]
    assert bool(((fa < 0) != (fb < 0)).all())
    t = fa / (fa - fb)
    want = V[e[:, 0]] + t[:, None] * (V[e[:, 1]] - V[e[:, 0]])
    tol = 1e-5 if pl.points.dtype == torch.float32 else 1e-12
    torch.testing.assert_close(pl.points.double().cpu(), want, rtol=tol, atol=tol)
    # open chains start and end on boundary edges, loops never touch the boundary
    bnd = mesh.is_boundary_edge.cpu()
    for seq, closed in zip(torch.split(pl.edge.cpu(), pl.counts.tolist()), pl.closed.tolist()):
        if closed:
            assert not bool(bnd[seq].any())
        else:
            assert bool(bnd[seq[0]]) and bool(bnd[seq[-1]])
            assert not bool(bnd[seq[1:-1]].any())


def random_batch(gen, device, dtype, jiggle=0.3):
    items = [
        hexagon_mesh(torch.tensor([[0.0, 0.0]]), torch.tensor([1.0]), 5),
        square_mesh(torch.tensor([[3.0, -2.0]]), torch.tensor([0.7]), 6),
        hexagon_mesh(torch.tensor([[-5.0, 1.0]]), torch.tensor([2.0]), 2),
        hexagon_mesh(torch.tensor([[0.0, 0.0]]), torch.tensor([1.0]), 1),
    ]
    m = MeshBatch.cat(items)
    v = m.verts.double()
    el = (v[m.edges[:, 0]] - v[m.edges[:, 1]]).norm(dim=1).min()
    d = (torch.rand(v.shape, generator=gen, dtype=torch.float64) * 2 - 1) * jiggle * el
    d[m.is_boundary_vert] = 0
    while not bool((m.signed_areas(v + d) > 0).all()):
        d = d / 2
    return m.with_verts((v + d).to(dtype)).to(device=device)


# ----------------------------------------------------------------------------- tests


def test_single_triangle_by_hand(device, dtype):
    v = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]], device=device, dtype=dtype)
    m = MeshBatch(v, torch.tensor([[0, 1, 2]], device=device), torch.tensor([3]), torch.tensor([1]))
    pl = extract_zero_set(m, torch.tensor([-1.0, 1.0, 1.0], device=device, dtype=dtype))
    # crossings at the midpoints (1,0) and (0,1); the negative corner (origin) on the left
    assert len(pl) == 1 and not bool(pl.closed[0])
    torch.testing.assert_close(pl.points, torch.tensor([[1.0, 0.0], [0.0, 1.0]], device=device, dtype=dtype))
    pl = extract_zero_set(m, torch.tensor([1.0, -1.0, -1.0], device=device, dtype=dtype))
    torch.testing.assert_close(pl.points, torch.tensor([[0.0, 1.0], [1.0, 0.0]], device=device, dtype=dtype))
    # t = -1 / (-1 - 3) = 1/4 on (0,1): (0.5, 0); t = 1/2 on (0,2): (0, 1)
    pl = extract_zero_set(m, torch.tensor([-1.0, 3.0, 1.0], device=device, dtype=dtype))
    torch.testing.assert_close(pl.points, torch.tensor([[0.5, 0.0], [0.0, 1.0]], device=device, dtype=dtype))
    # lone positive vertex 1: crossings on (0,1) at t=3/4 -> (1.5,0) and on (1,2) at t=1/2 -> (1,1);
    # the negative corners 0 and 2 must be on the left: (1.5,0) -> (1,1)
    pl = extract_zero_set(m, torch.tensor([-3.0, 1.0, -1.0], device=device, dtype=dtype))
    torch.testing.assert_close(pl.points, torch.tensor([[1.5, 0.0], [1.0, 1.0]], device=device, dtype=dtype))
    assert pl.item.tolist() == [0] and pl.per_item_counts().tolist() == [1]
    assert pl.num_open().tolist() == [1] and pl.num_closed().tolist() == [0]


def test_centre_loop_hexagon_r1(device, dtype):
    m = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 1)
    c = int(m.verts.norm(dim=1).argmin())
    vals = torch.ones(7, device=device, dtype=dtype)
    vals[c] = -1
    pl = extract_zero_set(m, vals)
    assert len(pl) == 1 and bool(pl.closed[0]) and pl.points.shape == (6, 2)
    # the six spoke midpoints, counter-clockwise
    ang = torch.atan2(pl.points[:, 1], pl.points[:, 0]).double().cpu()
    steps = torch.remainder(torch.roll(ang, -1) - ang, 2 * math.pi)
    torch.testing.assert_close(steps, torch.full((6,), math.pi / 3, dtype=torch.float64), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(pl.points.norm(dim=1).double().cpu(), torch.full((6,), 0.5, dtype=torch.float64),
                               rtol=1e-5, atol=1e-5)
    assert polygon_signed_area(pl.points) > 0


def test_empty_zero_set(device, dtype):
    m = MeshBatch.cat([hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 2),
                       square_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 2)])
    for vals in (torch.ones(m.verts.shape[0], device=device, dtype=dtype),
                 -torch.rand(m.verts.shape[0], device=device, dtype=dtype) - 0.1):
        pl = extract_zero_set(m, vals)
        assert len(pl) == 0
        assert pl.points.shape == (0, 2) and pl.points.dtype == dtype
        assert pl.per_item_counts().tolist() == [0, 0]
        assert pl.polyline_list() == [] and pl.item_lists() == [[], []]


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("boundary_positive", [False, True])
def test_random_signs_match_naive_tracer(seed, boundary_positive, device, dtype):
    gen = torch.Generator().manual_seed(seed)
    m = random_batch(gen, device, dtype)
    vals = (torch.rand(m.verts.shape[0], generator=gen, dtype=torch.float64) * 0.9 + 0.1)
    vals = vals * torch.where(torch.rand(m.verts.shape[0], generator=gen) < 0.45, -1.0, 1.0).double()
    if boundary_positive:
        vals[m.is_boundary_vert.cpu()] = vals[m.is_boundary_vert.cpu()].abs()
    vals = vals.to(device, dtype)
    pl = extract_zero_set(m, vals)
    check_structure(pl, m, vals)
    ref, n_mixed = naive_trace(m, vals)
    got = canonical(pl)
    assert sorted(got) == sorted(ref)
    # one segment per mixed triangle
    n_seg = int((pl.counts - (~pl.closed).long()).sum())
    assert n_seg == n_mixed
    if boundary_positive:
        assert bool(pl.closed.all())
    # no self-intersections / crossings between the polylines of one item
    for lst in pl.item_lists():
        assert find_intersections([(d["points"], d["closed"]) for d in lst]) == []


def test_segments_have_negative_side_on_left(device, dtype):
    gen = torch.Generator().manual_seed(21)
    m = random_batch(gen, device, dtype)
    vals = torch.randn(m.verts.shape[0], generator=gen, dtype=torch.float64)
    vals = (vals + 0.1 * vals.sign()).to(device, dtype)
    pl = extract_zero_set(m, vals)
    assert len(pl) > 3
    # for each segment, the triangle holding it (common face of its two edges) and the
    # gradient of f there from a 2x2 solve: the left normal must point down the gradient
    ef = m.edge_faces.cpu().tolist()
    V = m.verts.double().cpu()
    F = m.faces.cpu()
    f = vals.double().cpu()
    n = 0
    for pts, edges, closed in zip(pl.polyline_list(), torch.split(pl.edge.cpu(), pl.counts.tolist()), pl.closed.tolist()):
        k = len(edges)
        for i in range(k if closed else k - 1):
            e1, e2 = int(edges[i]), int(edges[(i + 1) % k])
            common = (set(ef[e1]) & set(ef[e2])) - {-1}
            assert len(common) == 1
            t = common.pop()
            a, b, c = F[t].tolist()
            A = torch.stack([V[b] - V[a], V[c] - V[a]])
            g = torch.linalg.solve(A, torch.stack([f[b] - f[a], f[c] - f[a]]))
            d = (pts[(i + 1) % k] - pts[i]).double().cpu()
            left = torch.stack([-d[1], d[0]])
            assert float(left @ g) < 0
            n += 1
    assert n > 20


def test_long_loop_and_long_chain(device, dtype):
    # a spiral band: one long loop; a wavy line: one long open chain
    m = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 40)
    v = m.verts.double()
    r, th = v.norm(dim=1), torch.atan2(v[:, 1], v[:, 0])
    # distance-like to the spiral r = 0.1 + 0.12 * (theta + 2 pi k) / (2 pi), band half-width 0.025
    phase = torch.remainder((r - 0.1) / 0.12 - th / (2 * math.pi), 1.0)
    band = (phase - 0.5).abs() * 0.12 - 0.025
    vals = torch.where((r > 0.12) & (r < 0.85), band, 0.05 + 0 * band)
    vals = torch.where(vals.abs() < 1e-4, torch.full_like(vals, 1e-4), vals).to(device, dtype)
    pl = extract_zero_set(m, vals)
    check_structure(pl, m, vals)
    ref, _ = naive_trace(m, vals)
    assert sorted(canonical(pl)) == sorted(ref)
    assert int(pl.counts.max()) > 500
    wavy = (v[:, 1] - 0.3 * torch.sin(12 * v[:, 0]))
    wavy = torch.where(wavy.abs() < 1e-4, torch.full_like(wavy, 1e-4), wavy).to(device, dtype)
    pl = extract_zero_set(m, wavy)
    check_structure(pl, m, wavy)
    ref, _ = naive_trace(m, wavy)
    assert sorted(canonical(pl)) == sorted(ref)
    assert len(pl) == 1 and not bool(pl.closed[0]) and int(pl.counts[0]) > 150


def test_batch_equals_each_alone(device, dtype):
    gen = torch.Generator().manual_seed(4)
    m = random_batch(gen, device, dtype)
    vals = (torch.randn(m.verts.shape[0], generator=gen, dtype=torch.float64) + 0.05).to(device, dtype)
    vals = torch.where(vals.abs() < 0.05, torch.full_like(vals, 0.05), vals)
    pl = extract_zero_set(m, vals)
    lists = pl.item_lists()
    assert len(lists) == m.num_items
    for b in range(m.num_items):
        v0, nv = int(m.verts_first_idx[b]), int(m.verts_per_item[b])
        alone = extract_zero_set(m[b], vals[v0:v0 + nv])
        assert len(alone) == len(lists[b]) == int(pl.per_item_counts()[b])
        for d, (p, c) in zip(lists[b], zip(alone.polyline_list(), alone.closed.tolist())):
            assert d["closed"] == c
            assert torch.equal(d["points"], p)


def test_polylines_transform(device, dtype):
    m = MeshBatch.cat([hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 3)] * 2)
    vals = (m.verts.norm(dim=1) - 0.55).to(dtype)
    pl = extract_zero_set(m, vals)
    assert pl.per_item_counts().tolist() == [1, 1]
    scale = torch.tensor([2.0, 0.5], device=device, dtype=dtype)
    shift = torch.tensor([[1.0, -1.0], [10.0, 20.0]], device=device, dtype=dtype)
    tp = pl.transform(scale, shift)
    n0 = int(pl.counts[0])
    torch.testing.assert_close(tp.points[:n0], pl.points[:n0] * 2 + shift[0])
    torch.testing.assert_close(tp.points[n0:], pl.points[n0:] * 0.5 + shift[1])
    assert torch.equal(tp.edge, pl.edge) and torch.equal(tp.closed, pl.closed)
