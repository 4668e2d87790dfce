"""Cluster moves on the Ising energy (pipeline/simplify.py) and the curve-to-data coupling
(pipeline/support.py), against brute force and hand values."""
import math

import pytest
import torch

from torch_isc.core.mesh import hexagon_mesh
from torch_isc.core.segments import edge_components
from torch_isc.pipeline.simplify import cluster_flip_change, descend_clusters
from torch_isc.pipeline.support import edge_data_gap, unsupported_coupling


def mesh_of(r=5, B=1):
    c = torch.zeros(B, 2, dtype=torch.float64)
    c[:, 0] = torch.arange(B, dtype=torch.float64) * 3.0
    return hexagon_mesh(c, torch.ones(B, dtype=torch.float64), r)


def components_by_bfs(V, edges, join):
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


def energy(edges, H, s):
    return sum(h * s[a] * s[b] for (a, b), h in zip(edges.tolist(), H.tolist()))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_edge_components_and_flip_change_against_brute_force(seed):
    mesh = mesh_of(4)
    g = torch.Generator().manual_seed(seed)
    V, E = mesh.verts.shape[0], mesh.edges.shape[0]
    join = torch.rand(E, generator=g) < 0.55
    lab = edge_components(V, mesh.edges, join)
    assert lab.tolist() == components_by_bfs(V, mesh.edges, join)
    H = torch.randn(E, generator=g, dtype=torch.float64)
    s = torch.where(torch.rand(V, generator=g) < 0.5, -1.0, 1.0).double()
    dE = cluster_flip_change(mesh.edges, H, s, lab)
    e0 = energy(mesh.edges, H, s.tolist())
    for c in set(lab.tolist()):
        t = s.clone()
        t[lab == c] *= -1
        assert math.isclose(float(dE[c]), energy(mesh.edges, H, t.tolist()) - e0, abs_tol=1e-9)


@pytest.mark.parametrize("seed", [0, 3])
def test_descend_clusters_lowers_the_energy_to_a_cluster_local_minimum(seed):
    mesh = mesh_of(5)
    g = torch.Generator().manual_seed(seed)
    V, E = mesh.verts.shape[0], mesh.edges.shape[0]
    e = mesh.edges
    H = torch.randn(E, generator=g, dtype=torch.float64) - 0.3
    s0 = torch.where(torch.rand(V, generator=g) < 0.4, -1.0, 1.0).double()
    pinned = mesh.is_boundary_vert
    s0[pinned] = 1.0
    far = torch.rand(V, generator=g) < 0.5
    s = descend_clusters(mesh, H, s0, pinned, far, rounds=50)
    assert energy(e, H, s.tolist()) < energy(e, H, s0.tolist()) - 1e-9          # the rule fired
    assert torch.equal(s[pinned], s0[pinned])
    # no cluster of either family (unpinned) lowers the energy any more, by brute force
    e0 = energy(e, H, s.tolist())
    for use_far in (False, True):
        for sgn in (-1.0, 1.0):
            mine = (s == sgn) & (far if use_far else torch.ones_like(far))
            lab = torch.tensor(components_by_bfs(V, e, mine[e[:, 0]] & mine[e[:, 1]]))
            for c in set(lab[mine].tolist()):
                if bool(pinned[lab == c].any()):
                    continue
                t = s.clone()
                t[lab == c] *= -1
                assert energy(e, H, t.tolist()) >= e0 - 1e-9


def test_descend_clusters_removes_a_channel_single_flips_cannot():
    # all couplings ferromagnetic except across a line: a two-vertex cluster of the wrong sign
    # is a local minimum for single flips when its own bond is strong
    mesh = mesh_of(4)
    V, e = mesh.verts.shape[0], mesh.edges
    d = mesh.verts.norm(dim=1)
    inner = torch.argsort(d)[:2]                  # the centre and a neighbour (adjacent)
    H = torch.full((e.shape[0],), -0.1, dtype=torch.float64)
    pair = ((e[:, 0] == inner[0]) & (e[:, 1] == inner[1])) | ((e[:, 0] == inner[1]) & (e[:, 1] == inner[0]))
    assert int(pair.sum()) == 1
    H[pair] = -5.0
    s = torch.ones(V, dtype=torch.float64)
    s[inner] = -1.0
    for v in inner.tolist():                      # single flips raise the energy...
        t = s.clone()
        t[v] = 1.0
        assert energy(e, H, t.tolist()) > energy(e, H, s.tolist())
    out = descend_clusters(mesh, H, s, mesh.is_boundary_vert, torch.zeros(V, dtype=torch.bool), rounds=1)
    assert torch.equal(out, torch.ones_like(s))   # ...the pair flipped whole removes the speck


def test_edge_data_gap_is_a_lower_bound_and_tight_on_the_line():
    mesh = mesh_of(3)
    g = torch.Generator().manual_seed(5)
    pts = (torch.rand(40, 2, generator=g, dtype=torch.float64) - 0.5) * 1.6
    v = mesh.verts
    d = torch.cdist(v, pts).amin(1)               # exact vertex-to-data distances
    gap = edge_data_gap(mesh, d)
    a, b = v[mesh.edges[:, 0]], v[mesh.edges[:, 1]]
    ab = b - a
    t = (((pts[None] - a[:, None]) * ab[:, None]).sum(-1) / (ab * ab).sum(-1)[:, None]).clamp(0, 1)
    exact = (a[:, None] + t[..., None] * ab[:, None] - pts[None]).norm(dim=-1).amin(1)
    assert bool((gap <= exact + 1e-12).all()) and bool((gap > 0).any())
    # hand case: a point on the edge's line beyond an end, (d_i + d_j - l)/2 = distance
    m = mesh_of(1)
    e0 = m.edges[0]
    p, q = m.verts[e0[0]], m.verts[e0[1]]
    x = p + 0.5 * (p - q)                         # half an edge length beyond p
    dd = (m.verts - x).norm(dim=1)
    assert math.isclose(float(edge_data_gap(m, dd)[0]), 0.5 * float((p - q).norm()), rel_tol=1e-12)


def test_unsupported_coupling_by_hand():
    gap = torch.tensor([0.0, 1.0, 1.5, 2.0, 3.0, math.inf], dtype=torch.float64)
    got = unsupported_coupling(gap, torch.ones(6, dtype=torch.float64), 2.0)
    assert got.tolist() == [0.0, 0.0, -1.0, -2.0, -2.0, -2.0]
