"""Cluster moves on the Ising energy (pipeline/simplify.py) and the curve-to-data coupling
(pipeline/support.py), against brute force and hand values."""
import math

import pytest
import torch

from conftest import components_by_bfs
from torch_isc.core.mesh import hexagon_mesh
from torch_isc.core.segments import edge_components
from torch_isc.pipeline.simplify import ENCLOSE_UNEVEN, cluster_flip_change, descend_clusters
from torch_isc.pipeline.support import edge_data_gap, unsupported_coupling


def mesh_of(r=5, B=1):
    c = torch.zeros(B, 2, dtype=torch.float64)
    c[:, 0] = torch.arange(B, dtype=torch.float64) * 3.0
    return hexagon_mesh(c, torch.ones(B, dtype=torch.float64), r)


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


# ----------------------------------------------------------------------------- opening (open_signs)
from torch_isc.pipeline.simplify import ball_cover, open_signs, zero_set_distance  # noqa: E402


def dijkstra_within_regions(mesh, s):
    """Distances to the zero set along same-sign edge paths, from ℓ/2 at crossing edges (heapq)."""
    import heapq
    V = s.shape[0]
    v = mesh.verts.tolist()
    nb = [[] for _ in range(V)]
    d = [math.inf] * V
    for a, b in mesh.edges.tolist():
        ell = math.dist(v[a], v[b])
        if s[a] == s[b]:
            nb[a].append((b, ell))
            nb[b].append((a, ell))
        else:
            d[a] = min(d[a], ell / 2)
            d[b] = min(d[b], ell / 2)
    h = [(x, i) for i, x in enumerate(d) if x < math.inf]
    heapq.heapify(h)
    while h:
        x, i = heapq.heappop(h)
        if x > d[i]:
            continue
        for j, w in nb[i]:
            if x + w < d[j]:
                d[j] = x + w
                heapq.heappush(h, (d[j], j))
    return d, nb


def disc_signs(mesh, discs):
    v = mesh.verts
    inside = torch.zeros(v.shape[0], dtype=torch.bool)
    for cx, cy, r in discs:
        inside |= ((v[:, 0] - cx) ** 2 + (v[:, 1] - cy) ** 2) < r * r
    return torch.where(inside, -1.0, 1.0).double()


def test_zero_set_distance_and_ball_cover_against_dijkstra():
    mesh = mesh_of(12)
    s = disc_signs(mesh, [(0.1, 0.0, 0.45), (-0.55, 0.3, 0.12)])
    V = s.shape[0]
    cap = torch.full((V,), 10.0, dtype=torch.float64)
    d = zero_set_distance(mesh, s, cap, 64)
    ref, nb = dijkstra_within_regions(mesh, s)
    ref = [min(x, 10.0) for x in ref]
    assert torch.allclose(d, torch.tensor(ref, dtype=torch.float64), atol=1e-12)
    # ball cover by brute force: covered iff some core vertex c (d_c >= r) has path(c, v) <= d_c
    r = 0.12
    rad = torch.full((V,), r, dtype=torch.float64)
    cov = ball_cover(mesh, s, d, rad, 64).tolist()
    import heapq
    want = [False] * V
    for c in range(V):
        if ref[c] < r:
            continue
        dist = {c: 0.0}
        h = [(0.0, c)]
        while h:
            x, i = heapq.heappop(h)
            if x > dist[i] or x > ref[c]:
                continue
            want[i] = True
            for j, w in nb[i]:
                if x + w < dist.get(j, math.inf):
                    dist[j] = x + w
                    heapq.heappush(h, (x + w, j))
    assert cov == want
    assert 0 < sum(want) < V


def test_open_signs_removes_a_speck_and_a_neck_and_keeps_thick_discs():
    mesh = mesh_of(24)                                # edges 1/24 of the unit hexagon
    h = 1.0 / 24
    # two discs of radius 0.25 (6 edges) joined by a neck of width ~1.5 edges, and a speck of radius 1.2 edges
    v = mesh.verts
    inside = (((v[:, 0] + 0.45) ** 2 + v[:, 1] ** 2) < 0.25 ** 2) | (((v[:, 0] - 0.45) ** 2 + v[:, 1] ** 2) < 0.25 ** 2)
    inside |= (v[:, 1].abs() < 0.8 * h) & (v[:, 0].abs() < 0.3)
    speck = ((v[:, 0] - 0.0) ** 2 + (v[:, 1] - 0.6) ** 2) < (1.2 * h) ** 2
    s = torch.where(inside | speck, -1.0, 1.0).double()
    pinned = mesh.is_boundary_vert
    rad = torch.full((s.shape[0],), 2.5 * h, dtype=torch.float64)
    out = open_signs(mesh, s, pinned, rad, 32)
    # the speck and the neck are gone: two negative regions, each holding a disc centre
    neg = out < 0
    lab = edge_components(s.shape[0], mesh.edges, neg[mesh.edges[:, 0]] & neg[mesh.edges[:, 1]])
    regions = set(lab[neg].tolist())
    assert len(regions) == 2
    assert not (neg & speck).any()
    assert not (neg & (v[:, 0].abs() < 0.02)).any()                      # the neck's middle
    # the discs keep their vertices deeper than a radius inside (nothing thick is eroded)
    deep = (((v[:, 0] + 0.45) ** 2 + v[:, 1] ** 2) < 0.15 ** 2) | (((v[:, 0] - 0.45) ** 2 + v[:, 1] ** 2) < 0.15 ** 2)
    assert neg[deep].all()
    # whole regions only: the speck goes, the neck stays (it is part of a deep region)
    out2 = open_signs(mesh, s, pinned, rad, 32, whole_regions=True)
    assert not (out2[speck] < 0).any()
    assert torch.equal(out2[~speck], s[~speck])
    # a radius below the mesh's resolution changes nothing
    assert torch.equal(open_signs(mesh, s, pinned, torch.full_like(rad, 0.2 * h), 32), s)


def test_open_signs_merge_joins_a_cut_off_tip_and_removes_a_lone_speck():
    mesh = mesh_of(24)
    h = 1.0 / 24
    v = mesh.verts
    V = v.shape[0]
    body = ((v[:, 0] + 0.2) ** 2 + v[:, 1] ** 2) < 0.3 ** 2
    # a tip: the vertices on the row y = 0 from one edge past the body's rim, 3 edges long
    row = v[:, 1].abs() < 0.1 * h
    tip = row & (v[:, 0] > 0.1 + 1.5 * h) & (v[:, 0] < 0.1 + 4.5 * h)
    gap = row & (v[:, 0] > 0.1) & (v[:, 0] < 0.1 + 1.5 * h) & ~body       # the wall vertex
    lone = ((v[:, 0] + 0.2) ** 2 + (v[:, 1] - 0.65) ** 2) < (1.2 * h) ** 2
    assert int(gap.sum()) == 1 and int(tip.sum()) >= 2 and int(lone.sum()) >= 1
    s = torch.where(body | tip | lone, -1.0, 1.0).double()
    pinned = mesh.is_boundary_vert
    rad = torch.full((V,), 2.5 * h, dtype=torch.float64)
    # by hand: without merging both specks go; with it the tip joins the body through the
    # wall vertex, the lone speck (no region of its sign one vertex away) goes
    out = open_signs(mesh, s, pinned, rad, 32, whole_regions=True)
    assert torch.equal(out < 0, body)
    out = open_signs(mesh, s, pinned, rad, 32, whole_regions=True, merge=True)
    assert torch.equal(out < 0, body | tip | gap)


def _faces_by_brute_force(mesh, pts):
    """``(P,)`` the triangle holding each point (barycentric coordinates all >= 0), −1 if none."""
    p = mesh.verts[mesh.faces]                                    # (T,3,2)
    out = []
    for q in pts.tolist():
        hit = -1
        for t in range(p.shape[0]):
            a, b, c = p[t].tolist()
            den = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1])
            l1 = ((b[1] - c[1]) * (q[0] - c[0]) + (c[0] - b[0]) * (q[1] - c[1])) / den
            l2 = ((c[1] - a[1]) * (q[0] - c[0]) + (a[0] - c[0]) * (q[1] - c[1])) / den
            if min(l1, l2, 1 - l1 - l2) >= -1e-12:
                hit = t
                break
        out.append(hit)
    return torch.tensor(out)


def test_a_speck_its_own_data_surround_is_kept():
    from torch_isc.pipeline.simplify import surrounded_regions
    mesh = mesh_of(24)
    h = 1.0 / 24
    v = mesh.verts
    speck = ((v[:, 0] - 0.0) ** 2 + (v[:, 1] - 0.6) ** 2) < (1.2 * h) ** 2
    s = torch.where(speck, -1.0, 1.0).double()
    pinned = mesh.is_boundary_vert
    rad = torch.full((s.shape[0],), 2.5 * h, dtype=torch.float64)
    # a small closed curve: 12 points on a circle of radius 0.9 h about the speck's centre
    t = torch.arange(12, dtype=torch.float64) * (2 * math.pi / 12) + 0.1
    ring = torch.stack([0.9 * h * torch.cos(t), 0.6 + 0.9 * h * torch.sin(t)], 1)
    # data on one side only: 12 points on a line 1 h below it
    line = torch.stack([torch.linspace(-3 * h, 3 * h, 12, dtype=torch.float64),
                        torch.full((12,), 0.6 - 1.0 * h, dtype=torch.float64)], 1)
    for pts, kept in ((ring, True), (line, False)):
        face = _faces_by_brute_force(mesh, pts)
        assert (face >= 0).all()
        sur = surrounded_regions(mesh, speck, pts, face)
        assert bool(sur[speck].all()) == kept and not sur[~speck].any()
        out = open_signs(mesh, s, pinned, rad, 32, whole_regions=True, merge=True, data=(pts, face))
        assert bool((out[speck] < 0).all()) == kept
        # without the data the speck goes whatever surrounds it
        assert not (open_signs(mesh, s, pinned, rad, 32, whole_regions=True, merge=True)[speck] < 0).any()
    # the sector count by hand: points at 4 distinct sectors about the centre are not enough, 5 are
    ang = torch.tensor([0.2, 1.0, 2.0, 3.0, 4.0], dtype=torch.float64)   # sectors of pi/4: 0, 1, 2, 3, 5
    pts = torch.stack([0.9 * h * torch.cos(ang), 0.6 + 0.9 * h * torch.sin(ang)], 1)
    cen = v[speck].mean(0)
    assert torch.allclose(cen, torch.tensor([0.0, 0.6], dtype=torch.float64), atol=0.2 * h)
    face = _faces_by_brute_force(mesh, pts)
    assert surrounded_regions(mesh, speck, pts, face)[speck].all()
    assert not surrounded_regions(mesh, speck, pts[:4], face[:4])[speck].any()
    # a point in no triangle (face −1) counts for nothing
    assert not surrounded_regions(mesh, speck, pts, torch.where(torch.arange(5) == 4, -1, face))[speck].any()


def _enclosed_by_loops(mesh, s, pts, face, clear, chord, rings, min_points):
    """enclosed_vertices by plain loops: breadth-first edge distances from every vertex, the
    points of the triangles with a corner within ``rings`` edges, sorted by angle."""
    V = len(s)
    faces = mesh.faces.tolist()
    verts = mesh.verts.tolist()
    nbr = [set() for _ in range(V)]
    for a, b in mesh.edges.tolist():
        nbr[a].add(b)
        nbr[b].add(a)
    bnd = mesh.is_boundary_vert.tolist()
    crossed = [any(s[u] != s[v] for u in nbr[v]) for v in range(V)]
    cut = [len({s[c] for c in f}) > 1 for f in faces]
    out = []
    for v in range(V):
        if bnd[v] or crossed[v]:
            out.append(False)
            continue
        near_set, front = {v}, {v}
        for _ in range(rings):
            front = {w for u in front for w in nbr[u]} - near_set
            near_set |= front
        got = []
        for p, f in zip(pts.tolist(), face.tolist()):
            if f < 0 or cut[f] or not near_set & set(faces[f]):
                continue
            got.append((math.atan2(p[1] - verts[v][1], p[0] - verts[v][0]) + math.pi, p))
        if len(got) < max(min_points, 3):
            out.append(False)
            continue
        got.sort()
        r = min(math.hypot(p[0] - verts[v][0], p[1] - verts[v][1]) for _, p in got)
        closed = got + [(got[0][0] + 2 * math.pi, got[0][1])]
        big = max(math.hypot(q[1][0] - p[1][0], q[1][1] - p[1][1]) for p, q in zip(closed, closed[1:]))
        gap = max(q[0] - p[0] for p, q in zip(closed, closed[1:]))
        # the chords between neighbours by angle (not the closing one), their lower median
        inner = sorted(math.hypot(q[1][0] - p[1][0], q[1][1] - p[1][1]) for p, q in zip(got, got[1:]))
        med = inner[(len(inner) - 1) // 2]
        out.append(r >= clear and big <= chord * r and gap <= 2 * math.asin(min(chord / 2, 1))
                   and big <= ENCLOSE_UNEVEN * med)
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_enclosed_vertices_against_loops(seed):
    from torch_isc.pipeline.simplify import enclosed_vertices
    mesh = mesh_of(6)
    g = torch.Generator().manual_seed(seed)
    V = mesh.verts.shape[0]
    s = torch.where(torch.rand(V, generator=g) < 0.06, -1.0, 1.0).double()
    # scattered points and small rings of 6-10 points (with jitter)
    parts = [(torch.rand(80, 2, generator=g, dtype=torch.float64) - 0.5) * 1.6]
    for _ in range(8):
        n = int(torch.randint(6, 11, (1,), generator=g))
        t = torch.rand(1, generator=g, dtype=torch.float64) + torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
        r = 0.05 + 0.1 * torch.rand(1, generator=g, dtype=torch.float64)
        ring = torch.stack([torch.cos(t), torch.sin(t)], 1) * r * (1 + 0.2 * torch.rand(n, 1, generator=g, dtype=torch.float64))
        parts.append(ring + (torch.rand(1, 2, generator=g, dtype=torch.float64) - 0.5) * 1.2)
    pts = torch.cat(parts)
    face = _faces_by_brute_force(mesh, pts)
    hits = 0
    for chord, clear, rings, m in ((1.5, 0.0, 0, 3), (1.8, 0.02, 1, 6), (1.2, 0.0, 2, 4), (2.5, 0.0, 1, 8)):
        got = enclosed_vertices(mesh, s, pts, face, torch.full((V,), clear, dtype=torch.float64), chord, rings, m)
        ref = _enclosed_by_loops(mesh, s.tolist(), pts, face, clear, chord, rings, m)
        assert got.tolist() == ref
        hits += sum(ref)
    assert hits > 0                                  # the case is not vacuous


def test_enclose_flips_the_vertex_a_missed_ring_surrounds():
    from torch_isc.pipeline.simplify import enclosed_vertices
    mesh = mesh_of(12)
    h = 1.0 / 12
    v = mesh.verts
    c = int(((v - torch.tensor([0.0, 0.5], dtype=torch.float64)) ** 2).sum(1).argmin())
    V = v.shape[0]
    t = torch.arange(8, dtype=torch.float64) * (2 * math.pi / 8) + 0.2
    ring = v[c] + 0.6 * h * torch.stack([torch.cos(t), torch.sin(t)], 1)   # 8 points about vertex c
    face = _faces_by_brute_force(mesh, ring)
    clear = torch.full((V,), 0.3 * h, dtype=torch.float64)
    plus = torch.ones(V, dtype=torch.float64)
    # chords 2 sin(pi/8) 0.6 h = 0.46 h against the distance 0.6 h: a ring at 1.5, not at 0.7
    hit = enclosed_vertices(mesh, plus, ring, face, clear, 1.5, 2)
    assert hit.nonzero().squeeze(1).tolist() == [c]
    assert not enclosed_vertices(mesh, plus, ring, face, clear, 0.7, 2).any()
    # inside a negative region the same ring is a hole: the vertex is found just the same
    minus = torch.where(((v - v[c]) ** 2).sum(1) < (4 * h) ** 2, -1.0, 1.0).double()
    assert enclosed_vertices(mesh, minus, ring, face, clear, 1.5, 2).nonzero().squeeze(1).tolist() == [c]
    # the zero set nearer than the ring's farthest point (0.6 h): the ring is the curve's noise
    for dep, fires in ((0.5 * h, False), (0.7 * h, True)):
        got = enclosed_vertices(mesh, plus, ring, face, clear, 1.5, 2, 6, torch.full((V,), dep, dtype=torch.float64))
        assert bool(got[c]) == fires
    # four small rings round c (a grid of small curves): all round it, chords within 2.5 times
    # the distance, but the chords between the rings are many times those within them
    import torch_isc.pipeline.simplify as simplify_mod
    u = torch.arange(6, dtype=torch.float64) * (2 * math.pi / 6)
    small = torch.stack([torch.cos(u), torch.sin(u)], 1) * 0.1 * h
    four = torch.cat([v[c] + h * torch.tensor([math.cos(a), math.sin(a)], dtype=torch.float64) + small
                      for a in (0.8, 0.8 + math.pi / 2, 0.8 + math.pi, 0.8 + 3 * math.pi / 2)])
    f4 = _faces_by_brute_force(mesh, four)
    assert not enclosed_vertices(mesh, plus, four, f4, clear, 2.5, 2)[c]
    keep = simplify_mod.ENCLOSE_UNEVEN
    try:
        simplify_mod.ENCLOSE_UNEVEN = float("inf")            # the rule off: c would fire
        assert enclosed_vertices(mesh, plus, four, f4, clear, 2.5, 2)[c]
    finally:
        simplify_mod.ENCLOSE_UNEVEN = keep
    # fewer points than min_points: no ring
    assert not enclosed_vertices(mesh, plus, ring, face, clear, 1.5, 2, 9).any()
    # a curve already there (c negative): nothing to do
    cneg = plus.clone()
    cneg[c] = -1
    assert not enclosed_vertices(mesh, cneg, ring, face, clear, 1.5, 2).any()
    # half a ring: a gap of 5 pi / 4 (short chords, but all on one side)
    assert not enclosed_vertices(mesh, plus, ring[:4], face[:4], clear, 1.5, 2).any()
    # data nearer than the clearance: the vertex sits in the data, not inside a curve
    assert not enclosed_vertices(mesh, plus, ring, face, torch.full((V,), 0.7 * h, dtype=torch.float64), 1.5, 2).any()
    # two walls 0.5 h either side of c, 3 h long: all round it by angle, but the chord that
    # closes each end (h) is twice the distance (0.5 h)
    x = torch.linspace(-3 * h, 3 * h, 25, dtype=torch.float64)
    walls = torch.cat([torch.stack([x, torch.full_like(x, 0.5 * h)], 1),
                       torch.stack([x, torch.full_like(x, -0.5 * h)], 1)]) + v[c]
    wf = _faces_by_brute_force(mesh, walls)
    assert not enclosed_vertices(mesh, plus, walls, wf, clear * 0, 1.8, 2).any()
    # ...which a chord bound above 2 would take for a ring
    assert enclosed_vertices(mesh, plus, walls, wf, clear * 0, 2.01, 2)[c]


def test_reconstruct_finds_satellites_of_eight_points():
    """A unit circle (200 points) and three circles of radius 0.15 at distance 1.5, 8 points
    each: line fits cannot describe an 8-point circle, the enclosure rule finds all three."""
    import torch_isc
    t = 0.3 + torch.arange(200, dtype=torch.float64) * (2 * math.pi / 200)
    parts = [torch.stack([torch.cos(t), torch.sin(t)], 1)]
    for k in range(3):
        u = torch.arange(8, dtype=torch.float64) * (2 * math.pi / 8) + 0.4 * k
        c = 1.5 * torch.tensor([math.cos(1.0 + 2.1 * k), math.sin(1.0 + 2.1 * k)], dtype=torch.float64)
        parts.append(c + 0.15 * torch.stack([torch.cos(u), torch.sin(u)], 1))
    pts = torch.cat(parts)
    loops = torch_isc.reconstruct(pts, config=torch_isc.ReconstructConfig().replace(enclose_chord=1.8)).polylines
    assert len(loops) == 4 and all(pl["closed"] for pl in loops)
    # each satellite's loop lies around its centre, within its points' ring
    for k in range(3):
        c = 1.5 * torch.tensor([math.cos(1.0 + 2.1 * k), math.sin(1.0 + 2.1 * k)], dtype=torch.float64)
        d = [float((torch.as_tensor(pl["points"]) - c).norm(dim=1).max()) for pl in loops]
        assert min(d) < 0.25
    # off: the enclosure rule, the blob rule (pipeline/blobs.py finds these satellites too) and
    # the crust (its sparse chains find them too, pipeline/crust.py)
    off = torch_isc.reconstruct(pts, config=torch_isc.ReconstructConfig().replace(enclose_chord=0.0, blob_min_points=0,
                                                                                crust_weight=0.0))
    assert len(off.polylines) < 4
    crust_only = torch_isc.reconstruct(pts, config=torch_isc.ReconstructConfig().replace(enclose_chord=0.0,
                                                                                       blob_min_points=0))
    assert len(crust_only.polylines) == 4
    blob_only = torch_isc.reconstruct(pts, config=torch_isc.ReconstructConfig().replace(enclose_chord=0.0))
    assert len(blob_only.polylines) == 4
