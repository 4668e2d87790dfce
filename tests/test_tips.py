"""pipeline/tips.py: the unsupported-tip rule of the band stage, each piece against a hand value
or a brute-force route."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_isc.core.locate import locate_grid
from torch_isc.core.mesh import MeshBatch, hexagon_mesh
from torch_isc.pipeline.tips import (MIN_REGION, crossing_places, crossing_support, region_sizes,
                                     surrounded_vertices, unsupported_tips)


def _hex(res=4):
    return hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), res)


def test_crossing_places_by_hand():
    # one triangle (0,0) (2,0) (0,1): values 1, -3, 0.5
    m = MeshBatch(torch.tensor([[0.0, 0], [2, 0], [0, 1]], dtype=torch.float64), torch.tensor([[0, 1, 2]]),
                  torch.tensor([3]), torch.tensor([1]))
    x = crossing_places(m, torch.tensor([1.0, -3.0, 0.5], dtype=torch.float64))
    want = {(0, 1): [0.5, 0.0],            # |1| / (1 + 3) of the way from (0,0) to (2,0)
            (0, 2): [0.0, 2 / 3],          # 1 / 1.5 of the way to (0,1)
            (1, 2): [2 - 2 * 6 / 7, 6 / 7]}  # 3 / 3.5 of the way from (2,0) to (0,1)
    for k, (a, b) in enumerate(m.edges.tolist()):
        assert x[k].tolist() == pytest.approx(want[(a, b)])


def test_crossing_support_against_brute_force():
    m = _hex(5)
    g = torch.Generator().manual_seed(3)
    values = torch.randn(m.verts.shape[0], generator=g, dtype=torch.float64)
    pts = (torch.rand(60, 2, generator=g, dtype=torch.float64) - 0.5) * 1.6
    reach = 0.02 + 0.1 * torch.rand(60, generator=g, dtype=torch.float64)       # per point
    face, _ = locate_grid(m, pts, torch.zeros(60, dtype=torch.long))
    got = crossing_support(m, values, pts, face, reach)
    x = crossing_places(m, values).numpy()
    FE, NB = m.face_edges.numpy(), m.face_neighbors.numpy()
    want = np.zeros(m.edges.shape[0], bool)
    for p, f, r in zip(pts.numpy(), face.tolist(), reach.tolist()):
        if f < 0:
            continue
        for t in [f] + [n for n in NB[f] if n >= 0]:          # its triangle and the ones next to it
            for e in FE[t]:
                want[e] |= float(np.hypot(*(x[e] - p))) <= r
    assert (got.numpy() == want).all() and want.any() and not want.all()


def test_a_tongue_vertex_flips_and_nothing_else():
    # the inside is the disc of the centre and the first ring (r < 0.3), plus one corner of the
    # second ring (r = 0.5): a one-vertex tongue with one inside neighbour and five outside;
    # every crossing is supported except the tongue's own
    m = _hex(4)
    r = m.verts.norm(dim=1)
    signs = torch.where(r < 0.3, -1.0, 1.0).to(torch.float64)
    tip = int(((r - 0.5).abs() < 1e-9).nonzero()[0])
    signs[tip] = -1.0
    e = m.edges
    at_tip = (e[:, 0] == tip) | (e[:, 1] == tip)
    inner = signs[e[:, 0]] == signs[e[:, 1]]
    supported = ~at_tip | inner             # the edge to the disc: the crossing after the flip
    pinned = m.is_boundary_vert
    nb = _neighbours(m)[tip]
    assert sorted(int(signs[u] < 0) for u in nb) == [0, 0, 0, 0, 0, 1]          # by construction
    assert unsupported_tips(m, signs, supported, pinned).nonzero().squeeze(1).tolist() == [tip]
    # pinned, or a flip that would make an unsupported crossing: it stays
    assert not unsupported_tips(m, signs, supported, pinned | (torch.arange(len(signs)) == tip)).any()
    assert not unsupported_tips(m, signs, ~at_tip, pinned).any()
    # every crossing supported: nothing flips; half of the tip's five crossings unsupported: not
    # enough (2 of 5), three of five: it flips
    assert not unsupported_tips(m, signs, torch.ones_like(supported), pinned).any()
    crossing = at_tip & ~inner
    k = crossing.nonzero().squeeze(1)
    for n_bad, flips in ((2, False), (3, True)):
        sup = torch.ones_like(supported)
        sup[k[:n_bad]] = False
        assert bool(unsupported_tips(m, signs, sup, pinned)[tip]) is flips


def _neighbours(m):
    nb = {v: [] for v in range(m.verts.shape[0])}
    for a, b in m.edges.tolist():
        nb[a].append(b)
        nb[b].append(a)
    return nb


def _link_changes(m, signs, v):
    """Sign changes around the link of ``v`` (a walk over its triangles' opposite edges)."""
    n = 0
    for f in m.faces.tolist():
        if v in f:
            k = f.index(v)
            a, b = f[(k + 1) % 3], f[(k + 2) % 3]
            n += int((signs[a] < 0) != (signs[b] < 0))
    return n


@pytest.mark.parametrize("seed", range(4))
def test_flips_are_an_independent_set_of_the_rule_s_candidates(seed):
    m = _hex(10)
    g = torch.Generator().manual_seed(seed)
    V = m.verts.shape[0]
    r = m.verts.norm(dim=1)
    signs = torch.where(r + 0.25 * torch.rand(V, generator=g, dtype=torch.float64) < 0.55, -1.0, 1.0).to(torch.float64)
    supported = torch.rand(m.edges.shape[0], generator=g) < 0.6
    pinned = m.is_boundary_vert
    flip = unsupported_tips(m, signs, supported, pinned)
    nb = _neighbours(m)
    eid = {tuple(ab): k for k, ab in enumerate(m.edges.tolist())}
    cand = []
    for v in range(V):
        es = [eid[(min(v, u), max(v, u))] for u in nb[v]]
        cross = [signs[u] != signs[v] for u in nb[v]]
        n_old = sum(cross)
        bad_old = sum(c and not bool(supported[k]) for c, k in zip(cross, es))
        bad_new = sum((not c) and not bool(supported[k]) for c, k in zip(cross, es))
        ok = (not bool(pinned[v]) and _link_changes(m, signs, v) == 2 and len(nb[v]) - n_old < n_old
              and 2 * bad_old >= n_old and bad_old > 0 and bad_new == 0)
        cand.append(ok)
    cand = torch.tensor(cand)
    assert cand.any()
    assert not (flip & ~cand).any()                                     # only candidates flip
    assert not any(bool(flip[a] and flip[b]) for a, b in m.edges.tolist())   # never two neighbours
    # a candidate left out has a flipped neighbour, or a candidate neighbour that outranks it
    for v in cand.nonzero().squeeze(1).tolist():
        if not flip[v]:
            assert any(bool(cand[u]) for u in nb[v])


def test_region_sizes_against_a_search():
    m = _hex(5)
    g = torch.Generator().manual_seed(1)
    signs = torch.where(torch.rand(m.verts.shape[0], generator=g) < 0.5, -1.0, 1.0)
    got = region_sizes(m, signs).tolist()
    nb = _neighbours(m)
    for v0 in range(len(signs)):
        seen, stack = {v0}, [v0]
        while stack:
            u = stack.pop()
            for w in nb[u]:
                if w not in seen and signs[w] == signs[v0]:
                    seen.add(w)
                    stack.append(w)
        assert got[v0] == len(seen)
    assert MIN_REGION > 1


def test_surrounded_vertices_by_sectors():
    m = _hex(3)
    centre = int(m.verts.norm(dim=1).argmin())
    h = float((m.verts - m.verts[centre]).norm(dim=1).sort().values[1])        # an edge's length
    ang = torch.arange(8, dtype=torch.float64) * (2 * math.pi / 8) + 0.2
    ring = 0.4 * h * torch.stack([ang.cos(), ang.sin()], 1) + m.verts[centre]
    side = ring[ring[:, 0] > m.verts[centre, 0]]                                # 4 of 8 directions
    for pts, want in ((ring, True), (side, False)):
        face, _ = locate_grid(m, pts, torch.zeros(len(pts), dtype=torch.long))
        assert bool(surrounded_vertices(m, pts, face)[centre]) is want


def test_the_band_keeps_an_oracle_s_signs(monkeypatch):
    # a sign oracle gives every vertex its true sign: no tip flips for lack of data there
    import torch_isc
    from torch_isc.pipeline import tips
    calls = []
    real = tips.unsupported_tips

    def spy(*a, **k):
        calls.append(1)
        return real(*a, **k)
    monkeypatch.setattr(tips, "unsupported_tips", spy)
    t = torch.linspace(0, 2 * math.pi, 81, dtype=torch.float64)[:-1]
    pts = torch.stack([t.cos(), t.sin()], 1) + 0.01 * torch.randn(80, 2, generator=torch.Generator().manual_seed(0),
                                                                  dtype=torch.float64)
    r = torch_isc.reconstruct(pts, sign_oracle=lambda x: x.norm(dim=1) < 1)
    assert r.num_closed == 1 and not calls
    torch_isc.reconstruct(pts)
    assert calls                                        # the same points without the oracle: it runs


def test_the_spacing_reach_follows_noise_neighbours(monkeypatch):
    # the frames' column 2 is the reach of noise_neighbours points (about k/2 spacings along a
    # clean curve); the rule's reach is one spacing whatever k: the same for 8 and 16 neighbours
    import torch_isc
    from torch_isc.pipeline import tips
    seen = []
    real = tips.crossing_support

    def spy(mesh, values, points, face, reach):
        seen.append(reach.median().item())
        return real(mesh, values, points, face, reach)
    monkeypatch.setattr(tips, "crossing_support", spy)
    t = torch.linspace(0, 2 * math.pi, 81, dtype=torch.float64)[:-1]
    pts = torch.stack([t.cos(), t.sin()], 1)               # spacing 0.079, far above the tolerance
    medians = []
    for k in (8, 16):
        seen.clear()
        torch_isc.reconstruct(pts, torch_isc.ReconstructConfig().replace(noise_neighbours=k))
        medians.append(seen[0])
    assert medians[1] / medians[0] == pytest.approx(1.0, abs=0.05), medians
