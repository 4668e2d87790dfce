"""Tests of torch_isc.core.mesh: packed batches, initial meshes, adjacency and validation.

Every expected value is counted or computed here by hand or by a naive Python loop over
the faces; nothing is taken from the library's own tables.
"""
from __future__ import annotations

import math
from collections import defaultdict

import pytest
import torch

from torch_isc.core.mesh import InvalidMeshError, MeshBatch, hexagon_mesh, square_mesh

SQ3 = math.sqrt(3.0)


def hex_batch(r, device, dtype):
    centers = torch.tensor([[0.0, 0.0], [3.5, -1.25], [-20.0, 7.0]], device=device, dtype=dtype)
    radii = torch.tensor([1.0, 0.5, 4.0], device=device, dtype=dtype)
    return hexagon_mesh(centers, radii, r), centers, radii


def square_batch(n, device, dtype):
    centers = torch.tensor([[0.0, 0.0], [10.0, 2.0]], device=device, dtype=dtype)
    hw = torch.tensor([1.0, 0.25], device=device, dtype=dtype)
    return square_mesh(centers, hw, n), centers, hw


def mixed_batch(device, dtype):
    """Items of different kinds, sizes and positions."""
    a = hexagon_mesh(torch.tensor([[0.0, 0.0]], device=device, dtype=dtype),
                     torch.tensor([1.0], device=device, dtype=dtype), 2)
    b = square_mesh(torch.tensor([[5.0, -3.0]], device=device, dtype=dtype),
                    torch.tensor([2.0], device=device, dtype=dtype), 3)
    c = hexagon_mesh(torch.tensor([[-4.0, 4.0]], device=device, dtype=dtype),
                     torch.tensor([0.5], device=device, dtype=dtype), 3)
    d = square_mesh(torch.tensor([[0.0, 0.0]], device=device, dtype=dtype),
                    torch.tensor([1.0], device=device, dtype=dtype), 1)
    return [a, b, c, d]


# ----------------------------------------------------------------------------- naive tables


def naive_edges(faces_local):
    """Undirected edge -> list of (face, corner opposite) from a Python loop."""
    occ = defaultdict(list)
    for t, (i, j, k) in enumerate(faces_local):
        tri = (i, j, k)
        for c in range(3):
            a, b = tri[(c + 1) % 3], tri[(c + 2) % 3]
            occ[(min(a, b), max(a, b))].append((t, c))
    return occ


def per_item_local_faces(mesh, b):
    v0 = int(mesh.verts_first_idx[b])
    f0, nf = int(mesh.faces_first_idx[b]), int(mesh.faces_per_item[b])
    return (mesh.faces[f0:f0 + nf] - v0).cpu().tolist()


# ----------------------------------------------------------------------------- initial meshes


@pytest.mark.parametrize("r", [1, 2, 3, 5])
def test_hexagon_counts_and_geometry(r, device, dtype, tol):
    m, centers, radii = hex_batch(r, device, dtype)
    assert m.verts.device.type == device.type and m.verts.dtype == dtype
    assert m.faces.dtype == torch.long
    B = 3
    assert m.num_items == len(m) == B
    assert m.verts_per_item.tolist() == [3 * r * r + 3 * r + 1] * B
    assert m.faces_per_item.tolist() == [6 * r * r] * B
    assert m.verts.shape == (B * (3 * r * r + 3 * r + 1), 2)
    m.validate()
    assert m.is_valid()
    rtol, atol = tol

    # every triangle equilateral with side R/r: det = (R/r)^2 * sqrt(3)/2, positive
    det = m.signed_areas()
    expected = (radii[m.face_item] / r) ** 2 * SQ3 / 2
    torch.testing.assert_close(det, expected, rtol=rtol * 10, atol=0)
    torch.testing.assert_close(m.quality(), torch.ones_like(det), rtol=1e-4, atol=1e-4)
    # total area = area of the hexagon
    area = torch.zeros(B, dtype=torch.float64).index_add_(0, m.face_item.cpu(), det.double().cpu() / 2)
    torch.testing.assert_close(area, 1.5 * SQ3 * radii.double().cpu() ** 2, rtol=1e-5, atol=0)

    for b in range(B):
        faces = per_item_local_faces(m, b)
        occ = naive_edges(faces)
        n_boundary = sum(1 for v in occ.values() if len(v) == 1)
        assert n_boundary == 6 * r
        assert all(len(v) in (1, 2) for v in occ.values())
        V, E, F = 3 * r * r + 3 * r + 1, len(occ), 6 * r * r
        assert V - E + F == 1
        assert int(m.edges_per_item[b]) == E
        sel = m.edge_item == b
        assert int(m.is_boundary_edge[sel].sum()) == 6 * r

        verts = m.verts[m.vert_item == b].double().cpu()
        c, R = centers[b].double().cpu(), float(radii[b])
        # hexagon with corners at angles 0, 60, ..: the support function in the apothem
        # directions 30 + 60k is R*sqrt(3)/2 on the boundary, less inside
        ang = torch.tensor([math.radians(30 + 60 * k) for k in range(6)], dtype=torch.float64)
        nrm = torch.stack([ang.cos(), ang.sin()], 1)
        supp = ((verts - c) @ nrm.T).max(1).values / (R * SQ3 / 2)
        on_bnd = (supp - 1).abs() < 1e-5
        assert bool((supp < 1 + 1e-5).all())
        assert on_bnd.tolist() == m.is_boundary_vert[m.vert_item == b].cpu().tolist()
        assert int(on_bnd.sum()) == 6 * r
        # corners: exactly the six points c + R (cos 60k, sin 60k)
        corners = verts[m.is_corner_vert[m.vert_item == b].cpu()]
        assert corners.shape[0] == 6
        want = torch.stack([torch.tensor([c[0] + R * math.cos(math.radians(60 * k)),
                                          c[1] + R * math.sin(math.radians(60 * k))]) for k in range(6)])
        d = torch.cdist(want, corners)
        assert float(d.min(1).values.max()) < 1e-5 * max(1.0, R)
        # the centre is a vertex
        assert float((verts - c).norm(dim=1).min()) < 1e-5


@pytest.mark.parametrize("n", [1, 2, 3, 6])
def test_square_counts_and_geometry(n, device, dtype, tol):
    m, centers, hw = square_batch(n, device, dtype)
    B = 2
    assert m.verts_per_item.tolist() == [(n + 1) ** 2] * B
    assert m.faces_per_item.tolist() == [2 * n * n] * B
    m.validate()
    det = m.signed_areas()
    # right isosceles triangles with legs 2h/n: det = (2h/n)^2
    expected = (2 * hw[m.face_item] / n) ** 2
    torch.testing.assert_close(det, expected, rtol=1e-5, atol=0)
    torch.testing.assert_close(m.quality(), torch.full_like(det, SQ3 / 2), rtol=1e-5, atol=1e-5)
    for b in range(B):
        occ = naive_edges(per_item_local_faces(m, b))
        assert sum(1 for v in occ.values() if len(v) == 1) == 4 * n
        assert int(m.is_boundary_edge[m.edge_item == b].sum()) == 4 * n
        V, E, F = (n + 1) ** 2, len(occ), 2 * n * n
        assert V - E + F == 1
        assert int(m.edges_per_item[b]) == E
        verts = m.verts[m.vert_item == b].double().cpu()
        c, h = centers[b].double().cpu(), float(hw[b])
        corners = verts[m.is_corner_vert[m.vert_item == b].cpu()]
        want = torch.tensor([[c[0] + sx * h, c[1] + sy * h] for sx in (-1, 1) for sy in (-1, 1)],
                            dtype=torch.float64)
        assert corners.shape[0] == 4
        assert float(torch.cdist(want, corners).min(1).values.max()) < 1e-5
        on_bnd = ((verts - c).abs().max(1).values - h).abs() < 1e-5 * h
        assert on_bnd.tolist() == m.is_boundary_vert[m.vert_item == b].cpu().tolist()
        assert int(on_bnd.sum()) == 4 * n


def test_square_diagonals_alternate():
    # n=2 with checkerboard diagonals: all four diagonals meet at the centre (an "X"), so the
    # centre has degree 8 (it would be 6 with all diagonals parallel); corners and side
    # midpoints have degree 3
    m = square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), 2)
    deg = {tuple(v): int(d) for v, d in zip(m.verts.tolist(), m.degrees.tolist())}
    assert deg[(0.0, 0.0)] == 8
    for c in [(-1.0, -1.0), (1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (0.0, -1.0), (-1.0, 0.0), (1.0, 0.0), (0.0, 1.0)]:
        assert deg[c] == 3, c


def test_initial_mesh_bad_resolution():
    with pytest.raises(ValueError):
        hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 0)
    with pytest.raises(ValueError):
        square_mesh(torch.zeros(1, 2), torch.ones(1), 0)


# ----------------------------------------------------------------------------- signed areas, gradients


def test_signed_areas_hand_computed():
    verts = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, 3.0], [2.0, 3.0], [5.0, 1.0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [1, 3, 2], [0, 2, 1], [1, 4, 3]])
    m = MeshBatch(verts, faces, torch.tensor([5]), torch.tensor([4]))
    # det [[1,1,1],[xi,xj,xk],[yi,yj,yk]] by hand:
    # (0,1,2): 2*3 - 0 = 6 ; (1,3,2): (0)(3) - (3)(-2) = 6 ; (0,2,1): -6
    # (1,4,3): (3)(3) - (1)(0) = 9
    assert m.signed_areas().tolist() == [6.0, 6.0, -6.0, 9.0]
    with pytest.raises(InvalidMeshError, match="orient"):
        m.validate()


def test_signed_areas_eq22_determinant_random(device, dtype):
    g = torch.Generator().manual_seed(3)
    verts = torch.randn(30, 2, generator=g, dtype=torch.float64)
    faces = torch.randint(0, 30, (40, 3), generator=g)
    m = MeshBatch(verts.to(device, dtype), faces.to(device), torch.tensor([30]), torch.tensor([40]))
    A = torch.ones(40, 3, 3, dtype=torch.float64)
    A[:, 1, :] = verts[faces][:, :, 0]
    A[:, 2, :] = verts[faces][:, :, 1]
    ref = torch.linalg.det(A)
    torch.testing.assert_close(m.signed_areas().double().cpu(), ref,
                               rtol=1e-4 if dtype == torch.float32 else 1e-10, atol=1e-5 if dtype == torch.float32 else 1e-12)
    # explicit verts argument overrides the stored positions
    torch.testing.assert_close(m.signed_areas(2 * m.verts).double().cpu(), 4 * ref,
                               rtol=1e-4 if dtype == torch.float32 else 1e-10, atol=1e-4 if dtype == torch.float32 else 1e-12)


def test_signed_areas_gradcheck():
    m = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), 2)
    v = (m.verts + 0.01 * torch.randn_like(m.verts)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: m.signed_areas(x), (v,))
    assert torch.autograd.gradcheck(lambda x: m.bary_gradients(x), (v,))


def test_bary_gradients_against_inverse(device, dtype):
    m = hexagon_mesh(torch.tensor([[0.3, -0.2]], device=device, dtype=dtype),
                     torch.tensor([1.7], device=device, dtype=dtype), 3)
    # jiggle interior vertices so triangles are not all alike
    v = m.verts.clone()
    inner = ~m.is_boundary_vert
    v[inner] += 0.05 * torch.randn(int(inner.sum()), 2, device=device, dtype=dtype)
    m2 = m.with_verts(v)
    m2.validate()
    G = m2.bary_gradients().double().cpu()
    tri = v.double().cpu()[m.faces.cpu()]                        # (T,3,2)
    A = torch.ones(tri.shape[0], 3, 3, dtype=torch.float64)
    A[:, 1, :] = tri[:, :, 0]
    A[:, 2, :] = tri[:, :, 1]
    # lambda = A^{-1} [1, x, y]^T, so d lambda_k / d(x, y) = A^{-1}[k, 1:]
    ref = torch.linalg.inv(A)[:, :, 1:]
    rtol = 1e-4 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(G, ref, rtol=rtol, atol=rtol)
    torch.testing.assert_close(G.sum(1), torch.zeros(G.shape[0], 2, dtype=torch.float64), rtol=0, atol=rtol * 100)


# ----------------------------------------------------------------------------- adjacency


def check_adjacency(m: MeshBatch):
    F = m.faces.cpu().tolist()
    E = m.edges.cpu()
    fe = m.face_edges.cpu()
    ef = m.edge_faces.cpu()
    fn = m.face_neighbors.cpu()
    T = len(F)
    occ = naive_edges(F)
    # edges: each undirected edge exactly once, (lo, hi), sorted lexicographically
    assert E.shape == (len(occ), 2)
    assert bool((E[:, 0] < E[:, 1]).all())
    assert [tuple(e) for e in E.tolist()] == sorted(occ.keys())
    eid = {tuple(e): k for k, e in enumerate(E.tolist())}
    # edge k of a face is opposite vertex k
    for t in range(T):
        for k in range(3):
            a, b = F[t][(k + 1) % 3], F[t][(k + 2) % 3]
            assert int(fe[t, k]) == eid[(min(a, b), max(a, b))]
            assert F[t][k] not in E[fe[t, k]].tolist()
    # edge_faces: slot 0 = the face running lo->hi, slot 1 = hi->lo, -1 if none
    for (lo, hi), lst in occ.items():
        e = eid[(lo, hi)]
        want = [-1, -1]
        for t, c in lst:
            a = F[t][(c + 1) % 3]
            want[0 if a == lo else 1] = t
        assert ef[e].tolist() == want
        assert bool(m.is_boundary_edge[e]) == (len(lst) == 1)
    # face_neighbors from the naive table
    for t in range(T):
        for k in range(3):
            a, b = F[t][(k + 1) % 3], F[t][(k + 2) % 3]
            others = [u for u, _ in occ[(min(a, b), max(a, b))] if u != t]
            assert int(fn[t, k]) == (others[0] if others else -1)
            if others:
                assert t in fn[others[0]].tolist()
    # degrees, neighbours, boundary vertices
    nb = defaultdict(set)
    for a, b in occ:
        nb[a].add(b)
        nb[b].add(a)
    bverts = {v for (a, b), lst in occ.items() if len(lst) == 1 for v in (a, b)}
    V = m.verts.shape[0]
    assert m.degrees.cpu().tolist() == [len(nb[v]) for v in range(V)]
    assert m.is_boundary_vert.cpu().tolist() == [v in bverts for v in range(V)]
    first, nbrs = m.vert_neighbors
    first, nbrs = first.cpu().tolist(), nbrs.cpu().tolist()
    assert first[0] == 0 and first[-1] == 2 * len(occ)
    for v in range(V):
        assert nbrs[first[v]:first[v + 1]] == sorted(nb[v])


@pytest.mark.parametrize("kind,res", [("hex", 1), ("hex", 2), ("hex", 4), ("square", 1), ("square", 3)])
def test_adjacency_matches_naive(kind, res, device, dtype):
    m = (hex_batch if kind == "hex" else square_batch)(res, device, dtype)[0]
    check_adjacency(m)


def test_adjacency_of_mixed_batch(device, dtype):
    m = MeshBatch.cat(mixed_batch(device, dtype))
    check_adjacency(m)
    m.validate()


def test_degrees_hexagon_by_hand(device):
    r = 3
    m = hexagon_mesh(torch.zeros(1, 2, device=device), torch.ones(1, device=device), r)
    deg = m.degrees.cpu()
    bv, cv = m.is_boundary_vert.cpu(), m.is_corner_vert.cpu()
    assert bool((deg[~bv] == 6).all())
    assert bool((deg[cv] == 3).all())
    assert bool((deg[bv & ~cv] == 4).all())
    assert int(deg.sum()) == 2 * int(m.edges.shape[0])


def test_boundary_edge_dir(device, dtype):
    m, centers, radii = hex_batch(3, device, dtype)
    d = m.boundary_edge_dir.double().cpu()
    bv, cv = m.is_boundary_vert.cpu(), m.is_corner_vert.cpu()
    side = bv & ~cv
    assert bool((d[~side] == 0).all())
    torch.testing.assert_close(d[side].norm(dim=1), torch.ones(int(side.sum()), dtype=torch.float64), rtol=1e-5, atol=1e-5)
    # parallel to the hexagon side through the vertex: perpendicular to the radial apothem
    v = (m.verts.double().cpu() - centers.double().cpu()[m.vert_item.cpu()])[side]
    ang = torch.atan2(v[:, 1], v[:, 0])
    k = torch.floor(ang / (math.pi / 3))                           # sector of the side
    mid = (k + 0.5) * math.pi / 3
    apothem = torch.stack([mid.cos(), mid.sin()], 1)
    assert float((d[side] * apothem).sum(1).abs().max()) < 1e-5


# ----------------------------------------------------------------------------- validate


def _tri_pair(dtype=torch.float64):
    verts = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.5, 1.0], [0.5, -1.0], [0.5, 2.0]], dtype=dtype)
    return verts


def test_validate_accepts_valid_hand_mesh():
    v = _tri_pair()
    MeshBatch(v, torch.tensor([[0, 1, 2], [1, 0, 3]]), torch.tensor([5]), torch.tensor([2])).validate()


def test_validate_rejects_inverted_triangle(device, dtype):
    m = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 2)
    f = m.faces.clone()
    f[5] = f[5, [0, 2, 1]]
    bad = MeshBatch(m.verts, f, m.verts_per_item, m.faces_per_item)
    with pytest.raises(InvalidMeshError, match="positively oriented"):
        bad.validate()
    assert not bad.is_valid()
    # a degenerate (zero-area) triangle is rejected too
    v = m.verts.clone()
    a, b, c = m.faces[7].tolist()
    inner = [x for x in (a, b, c) if not bool(m.is_boundary_vert[x])]
    assert inner
    o = [x for x in (a, b, c) if x != inner[0]]
    v[inner[0]] = 0.5 * (v[o[0]] + v[o[1]])
    with pytest.raises(InvalidMeshError):
        m.with_verts(v).validate()
    # min_det threshold
    det_min = float(m.signed_areas().min())
    m.validate(min_det=0.5 * det_min)
    with pytest.raises(InvalidMeshError):
        m.validate(min_det=2 * det_min)


def test_validate_rejects_non_manifold_edge():
    v = _tri_pair()
    # three triangles on edge (0,1); all positively oriented
    f = torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    m = MeshBatch(v, f, torch.tensor([5]), torch.tensor([3]))
    assert bool((m.signed_areas() > 0).all())
    with pytest.raises(InvalidMeshError, match="more than two"):
        m.validate()


def test_validate_rejects_inconsistent_orientation():
    v = _tri_pair()
    # both triangles positive, but both run 0->1 (they overlap: a fold)
    f = torch.tensor([[0, 1, 2], [0, 1, 4]])
    m = MeshBatch(v, f, torch.tensor([5]), torch.tensor([2]))
    assert bool((m.signed_areas() > 0).all())
    with pytest.raises(InvalidMeshError, match="same direction"):
        m.validate()


@pytest.mark.parametrize("idx", [5, 99, -1])
def test_validate_rejects_out_of_range(idx):
    v = _tri_pair()
    f = torch.tensor([[0, 1, 2], [1, 0, idx]])
    m = MeshBatch(v, f, torch.tensor([5]), torch.tensor([2]))
    with pytest.raises(InvalidMeshError, match="does not exist"):
        m.validate()


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_validate_rejects_non_finite(bad, dtype):
    v = _tri_pair(dtype)
    v[2, 1] = bad
    m = MeshBatch(v, torch.tensor([[0, 1, 2], [1, 0, 3]]), torch.tensor([5]), torch.tensor([2]))
    with pytest.raises(InvalidMeshError, match="NaN or Inf"):
        m.validate()
    # also when the bad vertex is not used by any triangle
    v = _tri_pair(dtype)
    v[4, 0] = bad
    m = MeshBatch(v, torch.tensor([[0, 1, 2], [1, 0, 3]]), torch.tensor([5]), torch.tensor([2]))
    with pytest.raises(InvalidMeshError):
        m.validate()


def test_validate_rejects_repeated_vertex_and_cross_item():
    v = _tri_pair()
    m = MeshBatch(v, torch.tensor([[0, 1, 1]]), torch.tensor([5]), torch.tensor([1]))
    with pytest.raises(InvalidMeshError, match="repeats"):
        m.validate()
    # item 0 has vertices 0..2, item 1 vertices 3..4; the second face borrows vertex 0
    m = MeshBatch(torch.cat([v, torch.tensor([[0.0, 1.0]], dtype=v.dtype)]),
                  torch.tensor([[0, 1, 2], [3, 4, 0]]), torch.tensor([3, 3]), torch.tensor([1, 1]))
    with pytest.raises(InvalidMeshError, match="another item"):
        m.validate()


def test_constructor_rejects_bad_shapes():
    with pytest.raises(InvalidMeshError):
        MeshBatch(torch.zeros(3, 3), torch.zeros(1, 3, dtype=torch.long), torch.tensor([3]), torch.tensor([1]))
    with pytest.raises(InvalidMeshError):
        MeshBatch(torch.zeros(3, 2), torch.zeros(1, 4, dtype=torch.long), torch.tensor([3]), torch.tensor([1]))
    with pytest.raises(InvalidMeshError):
        MeshBatch(torch.zeros(3, 2), torch.zeros(1, 3, dtype=torch.long), torch.tensor([2]), torch.tensor([1]))
    with pytest.raises(InvalidMeshError):
        MeshBatch(torch.zeros(3, 2), torch.zeros(1, 3, dtype=torch.long), torch.tensor([3]), torch.tensor([2]))
    m = hexagon_mesh(torch.zeros(1, 2), torch.ones(1), 1)
    with pytest.raises(InvalidMeshError):
        m.with_verts(torch.zeros(6, 2))


# ----------------------------------------------------------------------------- list / packed views


def assert_mesh_equal(a: MeshBatch, b: MeshBatch):
    assert torch.equal(a.verts, b.verts)
    assert torch.equal(a.faces, b.faces)
    assert a.verts_per_item.tolist() == b.verts_per_item.tolist()
    assert a.faces_per_item.tolist() == b.faces_per_item.tolist()


def test_list_packed_round_trip(device, dtype):
    items = mixed_batch(device, dtype)
    m = MeshBatch.cat(items)
    assert m.num_items == 4
    nv = [int(x.verts.shape[0]) for x in items]
    nf = [int(x.faces.shape[0]) for x in items]
    assert m.verts_per_item.tolist() == nv and m.faces_per_item.tolist() == nf
    assert m.verts_first_idx.tolist() == [sum(nv[:i]) for i in range(4)]
    assert m.faces_first_idx.tolist() == [sum(nf[:i]) for i in range(4)]
    assert m.vert_item.tolist() == sum([[i] * n for i, n in enumerate(nv)], [])
    assert m.face_item.tolist() == sum([[i] * n for i, n in enumerate(nf)], [])
    vl, fl = m.verts_list(), m.faces_list()
    for i, x in enumerate(items):
        assert torch.equal(vl[i], x.verts)
        assert torch.equal(fl[i], x.faces)                        # local indices
        assert_mesh_equal(m[i], x)
    assert_mesh_equal(MeshBatch.from_list(vl, fl), m)
    assert_mesh_equal(MeshBatch.cat([m[i] for i in range(4)]), m)
    # negative indexing like a Python sequence
    assert_mesh_equal(m[-1], items[-1])
    assert_mesh_equal(m[-4], items[0])
    with pytest.raises(IndexError):
        m[4]
    with pytest.raises(IndexError):
        m[-5]
    with pytest.raises(InvalidMeshError):
        MeshBatch.from_list(vl, fl[:-1])
    with pytest.raises(InvalidMeshError):
        MeshBatch.from_list([], [])


def test_select_items(device, dtype):
    items = mixed_batch(device, dtype)
    m = MeshBatch.cat(items)
    sub, vkeep, fkeep = m.select_items(torch.tensor([3, 1], device=device))
    assert_mesh_equal(sub, MeshBatch.cat([items[1], items[3]]))
    assert torch.equal(m.verts[vkeep], sub.verts)
    # kept faces, renumbered through vkeep, are the sub-batch's faces
    assert torch.equal(vkeep[sub.faces], m.faces[fkeep])
    sub.validate()
    # a boolean mask works too
    mask = torch.tensor([True, False, True, False], device=device)
    sub2, _, _ = m.select_items(mask)
    assert_mesh_equal(sub2, MeshBatch.cat([items[0], items[2]]))


def test_batch_equals_each_alone(device, dtype):
    items = mixed_batch(device, dtype)
    m = MeshBatch.cat(items)
    for b, x in enumerate(items):
        v0, f0 = int(m.verts_first_idx[b]), int(m.faces_first_idx[b])
        nv, nf = x.verts.shape[0], x.faces.shape[0]
        vs, fs = slice(v0, v0 + nv), slice(f0, f0 + nf)
        es = m.edge_item == b
        e0 = int(es.nonzero()[0])
        assert bool(es[e0:e0 + int(es.sum())].all())              # contiguous
        assert torch.equal(m.edges[es] - v0, x.edges)
        assert torch.equal(m.face_edges[fs] - e0, x.face_edges)
        ef = m.edge_faces[es]
        assert torch.equal(torch.where(ef >= 0, ef - f0, ef), x.edge_faces)
        fn = m.face_neighbors[fs]
        assert torch.equal(torch.where(fn >= 0, fn - f0, fn), x.face_neighbors)
        assert torch.equal(m.signed_areas()[fs], x.signed_areas())
        assert torch.equal(m.bary_gradients()[fs], x.bary_gradients())
        assert torch.equal(m.degrees[vs], x.degrees)
        assert torch.equal(m.is_boundary_vert[vs], x.is_boundary_vert)
        assert torch.equal(m.is_corner_vert[vs], x.is_corner_vert)
        assert torch.equal(m.boundary_edge_dir[vs].abs(), x.boundary_edge_dir.abs())
        assert torch.equal(m.item_bbox()[b], x.item_bbox()[0])
        first, nbrs = m.vert_neighbors
        xf, xn = x.vert_neighbors
        assert torch.equal(first[v0:v0 + nv + 1] - first[v0], xf)
        assert torch.equal(nbrs[first[v0]:first[v0 + nv]] - v0, xn)


def test_item_bbox_and_conversions(device, dtype):
    m, centers, radii = square_batch(2, device, dtype)
    bb = m.item_bbox()
    want = torch.cat([centers - radii[:, None], centers + radii[:, None]], 1)
    torch.testing.assert_close(bb, want)
    m64 = m.to(dtype=torch.float64)
    assert m64.dtype == torch.float64 and torch.equal(m64.faces, m.faces)
    # with_verts shares topology but not positions
    v = m.verts * 2
    m2 = m.with_verts(v)
    assert m2.verts is v
    assert torch.equal(m2.edges, m.edges)
    torch.testing.assert_close(m2.signed_areas(), 4 * m.signed_areas())
    # detach drops autograd
    vv = m.verts.clone().requires_grad_(True)
    assert not m.with_verts(vv).detach().verts.requires_grad
    assert "MeshBatch(items=2" in repr(m)
