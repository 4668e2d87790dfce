"""Tests of torch_isc.core.locate against a brute-force loop over all triangles.

On meshes whose coordinates are small dyadic numbers (squares) the reference uses exact
rational arithmetic, so points exactly on shared edges and vertices test the tie rule
exactly: the face with the largest smallest-barycentric coordinate, ties to the lowest index.
"""
from __future__ import annotations

import pytest
import torch

import torch_isc.core.locate as L
from torch_isc.core.locate import barycentric, inside_tolerance, locate_children, locate_grid, locate_walk
from torch_isc.core.mesh import MeshBatch, hexagon_mesh, square_mesh

from conftest import brute_locate, ref_bary_exact


def exact_batch(device, dtype):
    """Square meshes with dyadic coordinates (exact in float32): different sizes and places."""
    return MeshBatch.cat([
        square_mesh(torch.tensor([[0.0, 0.0]], device=device, dtype=dtype), torch.tensor([1.0], device=device, dtype=dtype), 4),
        square_mesh(torch.tensor([[10.0, -6.0]], device=device, dtype=dtype), torch.tensor([2.0], device=device, dtype=dtype), 2),
        square_mesh(torch.tensor([[-3.0, 5.0]], device=device, dtype=dtype), torch.tensor([0.5], device=device, dtype=dtype), 1),
        square_mesh(torch.tensor([[0.0, 0.0]], device=device, dtype=dtype), torch.tensor([2.0], device=device, dtype=dtype), 4),
    ])


def hex_batch(device, dtype):
    return MeshBatch.cat([
        hexagon_mesh(torch.tensor([[0.0, 0.0]], device=device, dtype=dtype), torch.tensor([1.0], device=device, dtype=dtype), 3),
        hexagon_mesh(torch.tensor([[4.0, 1.0]], device=device, dtype=dtype), torch.tensor([0.3], device=device, dtype=dtype), 1),
        hexagon_mesh(torch.tensor([[0.2, 0.1]], device=device, dtype=dtype), torch.tensor([1.5], device=device, dtype=dtype), 5),
    ])


def sample_points(mesh: MeshBatch, gen: torch.Generator, n_random=20, n_box=20, quarter=True):
    """Per item: all vertices, all edge midpoints (and quarter points), random interior
    points, random points of the enlarged bounding box, a far point. Shuffled."""
    dt, dev = mesh.dtype, mesh.device
    v = mesh.verts.detach()
    pts, items = [v], [mesh.vert_item]
    e = mesh.edges
    pts.append(0.5 * (v[e[:, 0]] + v[e[:, 1]]))
    items.append(mesh.edge_item)
    if quarter:
        pts.append(0.75 * v[e[:, 0]] + 0.25 * v[e[:, 1]])
        items.append(mesh.edge_item)
    for b in range(mesh.num_items):
        f0, nf = int(mesh.faces_first_idx[b]), int(mesh.faces_per_item[b])
        t = f0 + torch.randint(0, nf, (n_random,), generator=gen)
        w = torch.rand(n_random, 3, generator=gen, dtype=torch.float64)
        w = (w / w.sum(1, keepdim=True)).to(dt)
        pts.append((v[mesh.faces[t.to(dev)]] * w.to(dev)[..., None]).sum(1))
        bb = mesh.item_bbox()[b]
        lo, hi = bb[:2], bb[2:]
        u = torch.rand(n_box, 2, generator=gen, dtype=torch.float64).to(dev, dt)
        pts.append(lo - 0.25 * (hi - lo) + 1.5 * (hi - lo) * u)
        pts.append((hi + 10 * (hi - lo))[None])
        items.append(torch.full((n_random + n_box + 1,), b, device=dev, dtype=torch.long))
    pts = torch.cat(pts)
    items = torch.cat(items)
    perm = torch.randperm(pts.shape[0], generator=gen).to(dev)
    return pts[perm], items[perm]


def check_against_brute(mesh, pts, items, face, bary, exact):
    dt = mesh.dtype
    ref = brute_locate(mesh.verts, mesh.faces, mesh.face_item.tolist(), pts, items.tolist(), exact=exact,
                       inside_tol=inside_tolerance(dt))
    V = mesh.verts.double().cpu()
    F = mesh.faces.cpu()
    fi = mesh.face_item.cpu()
    P = pts.double().cpu()
    face, bary = face.cpu(), bary.double().cpu()
    n_on_edges = 0
    for n, (rf, best, scores) in enumerate(ref):
        f = int(face[n])
        if exact:
            assert f == rf, (n, P[n].tolist(), f, rf, best)
        else:
            if abs(best) > 1e-4:                                    # decisively inside / outside
                assert (f >= 0) == (best > 0), (n, f, best)
            srt = sorted(scores.values(), reverse=True)
            if len(srt) > 1 and srt[0] - srt[1] > 1e-4 and best > 1e-4:
                assert f == rf, (n, f, rf)
            if f >= 0:
                assert scores[f] >= best - 1e-5                      # (nearly) the best face
        if f >= 0:
            assert int(fi[f]) == int(items[n]), "point located in another item's triangle"
            assert scores[f] >= -1e-5, "the triangle does not contain the point"
            if exact and sum(1 for s in scores.values() if s == best) > 1:
                n_on_edges += 1
            torch.testing.assert_close(bary[n].sum(), torch.tensor(1.0, dtype=torch.float64),
                                       rtol=0, atol=1e-5 if dt == torch.float32 else 1e-12)
            rec = (bary[n][:, None] * V[F[f]]).sum(0)
            scale = max(1.0, float(P[n].abs().max()))
            torch.testing.assert_close(rec, P[n], rtol=0, atol=(1e-5 if dt == torch.float32 else 1e-12) * scale)
        else:
            assert bool(torch.isnan(bary[n]).all())
    return n_on_edges


def test_locate_grid_exact_ties(device, dtype):
    mesh = exact_batch(device, dtype)
    gen = torch.Generator().manual_seed(1)
    pts, items = sample_points(mesh, gen)
    face, bary = locate_grid(mesh, pts, items)
    assert face.shape == (pts.shape[0],) and face.dtype == torch.long and bary.shape == (pts.shape[0], 3)
    assert face.device.type == device.type and bary.dtype == dtype
    n_ties = check_against_brute(mesh, pts, items, face, bary, exact=True)
    assert n_ties > 100                                              # the tie rule was exercised


def test_locate_grid_vertices_lowest_incident_face(device, dtype):
    # on a vertex all incident faces score exactly 0: the lowest incident index wins
    for mesh in (exact_batch(device, dtype), hex_batch(device, dtype)):
        face, bary = locate_grid(mesh, mesh.verts, mesh.vert_item)
        F = mesh.faces.cpu().tolist()
        want = [min(t for t, f in enumerate(F) if v in f) for v in range(mesh.verts.shape[0])]
        assert face.cpu().tolist() == want
        # the barycentric coordinates of a vertex are a unit vector
        assert bool((bary.max(1).values - 1).abs().max() < 1e-5)


def test_locate_grid_hexagons(device, dtype):
    mesh = hex_batch(device, dtype)
    gen = torch.Generator().manual_seed(2)
    pts, items = sample_points(mesh, gen)
    face, bary = locate_grid(mesh, pts, items)
    check_against_brute(mesh, pts, items, face, bary, exact=False)


def test_locate_grid_outside_points(device, dtype):
    mesh = exact_batch(device, dtype)
    pts = torch.tensor([[1.0 + 1e-3, 0.0], [0.0, -1.5], [100.0, 100.0], [-1.0, -1.0 - 1e-3], [9.0, -6.0]],
                       device=device, dtype=dtype)
    items = torch.tensor([0, 0, 0, 0, 0], device=device)
    face, bary = locate_grid(mesh, pts, items)
    assert face.tolist() == [-1] * 5
    assert bool(torch.isnan(bary).all())
    # (9, -6) is inside item 1 (centre (10,-6), half width 2) and (0.5, 0.5) inside items 0 and 3
    face, _ = locate_grid(mesh, pts[4:].repeat(2, 1), torch.tensor([1, 2], device=device))
    assert face[1] == -1 and face[0] >= 0 and int(mesh.face_item[face[0]]) == 1
    p = torch.tensor([[0.5, 0.5], [0.5, 0.5], [0.5, 0.5]], device=device, dtype=dtype)
    face, _ = locate_grid(mesh, p, torch.tensor([0, 3, 1], device=device))
    assert mesh.face_item[face[:2]].tolist() == [0, 3] and face[2] == -1
    # points exactly on the outer boundary are inside
    p = torch.tensor([[1.0, 0.3], [-1.0, -1.0], [0.0, 1.0]], device=device, dtype=dtype)
    face, _ = locate_grid(mesh, p, torch.zeros(3, dtype=torch.long, device=device))
    assert bool((face >= 0).all())


def test_locate_grid_overlapping_items(device, dtype):
    # two items over the same region: each point must land in its own item's mesh
    mesh = MeshBatch.cat([
        hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 4),
        square_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.full((1,), 0.6, device=device, dtype=dtype), 3),
    ])
    gen = torch.Generator().manual_seed(5)
    pts = (torch.rand(300, 2, generator=gen, dtype=torch.float64) * 2 - 1).to(device, dtype)
    items = torch.randint(0, 2, (300,), generator=gen).to(device)
    face, bary = locate_grid(mesh, pts, items)
    check_against_brute(mesh, pts, items, face, bary, exact=False)
    inside_sq = (pts.abs().max(1).values < 0.59)
    assert bool((face[(items == 1) & inside_sq] >= 0).all())
    assert bool((face[(items == 1) & (pts.abs().max(1).values > 0.61)] == -1).all())


@pytest.mark.parametrize("cells_per_face", [0.05, 0.5, 1.0, 7.0])
def test_locate_grid_independent_of_grid_size(cells_per_face, device, dtype):
    mesh = exact_batch(device, dtype)
    gen = torch.Generator().manual_seed(3)
    pts, items = sample_points(mesh, gen, n_random=10, n_box=10)
    f_ref, b_ref = locate_grid(mesh, pts, items)
    f, b = locate_grid(mesh, pts, items, cells_per_face=cells_per_face)
    assert torch.equal(f, f_ref)
    torch.testing.assert_close(b, b_ref, equal_nan=True)


def test_locate_grid_chunking(monkeypatch, device, dtype):
    mesh = hex_batch(device, dtype)
    gen = torch.Generator().manual_seed(4)
    pts, items = sample_points(mesh, gen, n_random=10, n_box=10, quarter=False)
    pts, items = pts[:150], items[:150]
    f_ref, b_ref = locate_grid(mesh, pts, items)
    monkeypatch.setattr(L, "_MAX_CANDIDATES", 7)
    f, b = locate_grid(mesh, pts, items, cells_per_face=0.1)          # many candidates per point
    assert torch.equal(f, f_ref)
    torch.testing.assert_close(b, b_ref, equal_nan=True)


def test_locate_grid_empty_and_batch_independent(device, dtype):
    mesh = exact_batch(device, dtype)
    f, b = locate_grid(mesh, torch.zeros(0, 2, device=device, dtype=dtype), torch.zeros(0, dtype=torch.long, device=device))
    assert f.shape == (0,) and b.shape == (0, 3)
    gen = torch.Generator().manual_seed(6)
    pts, items = sample_points(mesh, gen, n_random=10, n_box=10, quarter=False)
    f_all, b_all = locate_grid(mesh, pts, items)
    for k in range(mesh.num_items):
        sel = items == k
        alone = mesh[k]
        f, b = locate_grid(alone, pts[sel], torch.zeros(int(sel.sum()), dtype=torch.long, device=device))
        fa = f_all[sel]
        assert torch.equal(torch.where(fa >= 0, fa - mesh.faces_first_idx[k], fa), f)
        torch.testing.assert_close(b_all[sel], b, equal_nan=True)


# ----------------------------------------------------------------------------- barycentric


def test_barycentric_hand_values(device, dtype):
    v = torch.tensor([[0.0, 0.0], [4.0, 0.0], [0.0, 2.0], [4.0, 2.0]], device=device, dtype=dtype)
    f = torch.tensor([[0, 1, 2], [1, 3, 2]], device=device)
    p = torch.tensor([[1.0, 0.5], [3.0, 1.5], [2.0, 1.0], [8.0, 0.0]], device=device, dtype=dtype)
    b = barycentric(v, f, torch.tensor([0, 1, 0, 0], device=device), p)
    # (1, .5) in (0,0),(4,0),(0,2): x = 4 l1, y = 2 l2 -> l1 = .25, l2 = .25
    # (3, 1.5) in (4,0),(4,2),(0,2): l2 = (4-x)/4 = .25, y = 2 (l1 + l2) -> l1 = .5
    # (8, 0) in face 0: l1 = 2, l2 = 0 -> l0 = -1
    want = torch.tensor([[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.0, 0.5, 0.5], [-1.0, 2.0, 0.0]],
                        device=device, dtype=dtype)
    torch.testing.assert_close(b, want)
    b = barycentric(v, f, torch.tensor([-1, 1], device=device), p[:2])
    assert bool(torch.isnan(b[0]).all()) and not bool(torch.isnan(b[1]).any())


def test_barycentric_random_against_cramer(device, dtype):
    g = torch.Generator().manual_seed(7)
    v = torch.randn(20, 2, generator=g, dtype=torch.float64)
    f = torch.stack([torch.randperm(20, generator=g)[:3] for _ in range(15)])
    det = torch.stack([torch.linalg.det(torch.cat([torch.ones(3, 1, dtype=torch.float64), v[t]], 1)) for t in f])
    f = f[det.abs() > 0.2]
    fi = torch.randint(0, f.shape[0], (50,), generator=g)
    p = torch.randn(50, 2, generator=g, dtype=torch.float64)
    b = barycentric(v.to(device, dtype), f.to(device), fi.to(device), p.to(device, dtype)).double().cpu()
    ref = torch.tensor([[float(x) for x in ref_bary_exact(v[f[t]].tolist(), q.tolist())] for t, q in zip(fi, p)],
                       dtype=torch.float64)
    tol = 1e-3 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(b, ref, rtol=tol, atol=tol)


def test_barycentric_gradcheck():
    g = torch.Generator().manual_seed(8)
    m = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), 2)
    v = m.verts.clone().requires_grad_(True)
    fi = torch.randint(0, m.faces.shape[0], (10,), generator=g)
    p = torch.randn(10, 2, generator=g, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda vv, pp: barycentric(vv, m.faces, fi, pp), (v, p))


# ----------------------------------------------------------------------------- children


def split_mesh(verts, faces, plan, gen):
    """Split the faces of one item by hand. ``plan[t]`` is 4 (midpoints of all edges) or
    ``(2, k)`` (through the midpoint of the edge opposite corner ``k``). New faces are put in
    a random order; returns new verts, new faces, children (T_old, 4) ascending -1 padded."""
    V = [tuple(p) for p in verts.tolist()]
    mid = {}

    def m(a, b):
        key = (min(a, b), max(a, b))
        if key not in mid:
            pa, pb = V[a], V[b]
            V.append(((pa[0] + pb[0]) / 2, (pa[1] + pb[1]) / 2))
            mid[key] = len(V) - 1
        return mid[key]

    new, owner = [], []
    for t, (a, b, c) in enumerate(faces.tolist()):
        p = plan.get(t)
        if p == 4:
            ab, bc, ca = m(a, b), m(b, c), m(c, a)
            kids = [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]
        elif p is not None:
            k = p[1]
            x, y, z = [(a, b, c)[(k + i) % 3] for i in range(3)]
            mm = m(y, z)
            kids = [(x, y, mm), (x, mm, z)]
        else:
            kids = [(a, b, c)]
        new += kids
        owner += [t] * len(kids)
    perm = torch.randperm(len(new), generator=gen).tolist()
    new = [new[i] for i in perm]
    owner = [owner[i] for i in perm]
    children = torch.full((faces.shape[0], 4), -1, dtype=torch.long)
    for t in range(faces.shape[0]):
        ks = sorted(i for i, o in enumerate(owner) if o == t)
        children[t, :len(ks)] = torch.tensor(ks)
    return torch.tensor(V, dtype=verts.dtype), torch.tensor(new), children


def test_locate_children_against_brute(device, dtype):
    gen = torch.Generator().manual_seed(9)
    old = exact_batch(device, dtype)
    olds = [old[b] for b in range(old.num_items)]
    # item 0: all faces into 4 (conforming); item 1: two pairs of neighbours into 2 across
    # their shared edge, the rest unsplit; item 2: untouched; item 3: a mix of 4- and 2-splits
    plans = [{t: 4 for t in range(olds[0].faces.shape[0])}, {}, {}, {}]
    for b, sel in ((1, [0, 5]), (3, [2, 7, 11])):
        x = olds[b]
        for t in sel:
            for k in range(3):
                n = int(x.face_neighbors[t, k])
                if n >= 0 and n not in plans[b] and t not in plans[b]:
                    kk = int((x.face_neighbors[n] == t).nonzero()[0])
                    plans[b][t], plans[b][n] = (2, k), (2, kk)
    # a conforming 4-split of a face in item 3 needs its neighbours split as well: split one
    # face into 4 and each neighbour into 2 toward it
    x = olds[3]
    t4 = next(t for t in range(x.faces.shape[0]) if t not in plans[3]
              and all(int(n) < 0 or int(n) not in plans[3] for n in x.face_neighbors[t]))
    plans[3][t4] = 4
    for k in range(3):
        n = int(x.face_neighbors[t4, k])
        if n >= 0:
            plans[3][n] = (2, int((x.face_neighbors[n] == t4).nonzero()[0]))
    vs, fs, chs = [], [], []
    f_off = 0
    for b, x in enumerate(olds):
        v, f, ch = split_mesh(x.verts.cpu(), x.faces.cpu(), plans[b], gen)
        vs.append(v.to(device, dtype))
        fs.append(f.to(device))
        chs.append(torch.where(ch >= 0, ch + f_off, ch))
        f_off += f.shape[0]
    new = MeshBatch.from_list(vs, fs)
    new.validate()                                                   # conforming and positive
    children = torch.cat(chs).to(device)
    assert torch.equal(new.face_item[children[:, 0]], old.face_item)

    # points: old vertices, old edge midpoints (new vertices), new edge midpoints, random
    pts, items = sample_points(new, gen, n_random=30, n_box=0, quarter=False)
    parent, _ = locate_grid(old, pts, items)
    pts, items, parent = pts[parent >= 0], items[parent >= 0], parent[parent >= 0]   # drop far points
    assert pts.shape[0] > 300
    face, bary = locate_children(new, pts, parent, children)

    # reference 1: exact brute force among the parent's children
    ch = children.cpu()
    ref_c = brute_locate(new.verts, new.faces, new.face_item.tolist(), pts, items.tolist(), exact=True,
                         candidates=lambda n: ch[int(parent[n])].tolist(), inside_tol=inside_tolerance(dtype))
    assert face.cpu().tolist() == [r[0] for r in ref_c]
    # reference 2: exact brute force over the whole new item, for points that are not on the
    # parent's outline (where the parent's neighbours' children tie with its own)
    ref_g = brute_locate(new.verts, new.faces, new.face_item.tolist(), pts, items.tolist(), exact=True)
    old_ref = brute_locate(old.verts, old.faces, old.face_item.tolist(), pts, items.tolist(), exact=True)
    n_checked = 0
    for n in range(pts.shape[0]):
        if old_ref[n][2][int(parent[n])] > 0:                        # strictly inside the parent
            assert int(face[n]) == ref_g[n][0], (n, pts[n].tolist(), int(parent[n]), ref_g[n][2], face[n], bary[n])
            n_checked += 1
        else:                                                        # near its outline
            assert ref_g[n][2][int(face[n])] >= -inside_tolerance(dtype)
    assert n_checked > 50
    # barycentrics reconstruct the points
    rec = (bary[..., None] * new.verts[new.faces[face]]).sum(1)
    torch.testing.assert_close(rec, pts)
    # a point without a parent stays unlocated
    f2, b2 = locate_children(new, pts[:3], torch.tensor([-1, int(parent[1]), -1], device=device), children)
    assert f2[0] == -1 and f2[2] == -1 and f2[1] == face[1]
    assert bool(torch.isnan(b2[0]).all())
    assert torch.equal(children.cpu(), ch)                            # the table was not modified


# ----------------------------------------------------------------------------- walk


def jiggle(mesh: MeshBatch, amount: float, gen: torch.Generator) -> torch.Tensor:
    """Move interior vertices by random amounts (a fraction of the shortest edge of the
    item), halving the whole move until every triangle stays positively oriented."""
    v = mesh.verts.detach()
    el = (v[mesh.edges[:, 0]] - v[mesh.edges[:, 1]]).norm(dim=1)
    h = torch.full((mesh.num_items,), float("inf"), dtype=v.dtype, device=v.device)
    h = h.scatter_reduce(0, mesh.edge_item, el, "amin")[mesh.vert_item]
    d = (torch.rand(v.shape, generator=gen, dtype=torch.float64) * 2 - 1).to(v.device, v.dtype)
    d = d * amount * h[:, None]
    d[mesh.is_boundary_vert] = 0
    s = 1.0
    for _ in range(60):
        nv = v + s * d
        if bool((mesh.signed_areas(nv) > 0).all()):
            return nv
        s *= 0.5
    return v


@pytest.mark.parametrize("amount", [0.1, 0.45, 1.5])
def test_locate_walk_agrees_with_grid(amount, device, dtype):
    gen = torch.Generator().manual_seed(10)
    mesh = MeshBatch.cat([exact_batch(device, dtype), hex_batch(device, dtype)])
    pts, items = sample_points(mesh, gen, n_random=20, n_box=10, quarter=False)
    old_face, _ = locate_grid(mesh, pts, items)
    moved = mesh.with_verts(jiggle(mesh, amount, gen))
    moved.validate()
    # also points on the moved vertices and edges (exact ties after the move)
    v = moved.verts
    e = moved.edges
    extra = torch.cat([v, 0.5 * (v[e[:, 0]] + v[e[:, 1]])])
    extra_items = torch.cat([moved.vert_item, moved.edge_item])
    extra_start, _ = locate_grid(mesh, extra, extra_items)
    P = torch.cat([pts, extra])
    I = torch.cat([items, extra_items])
    S = torch.cat([old_face, extra_start])
    f_grid, b_grid = locate_grid(moved, P, I)
    for steps in (16, 1, 0):
        f_walk, b_walk = locate_walk(moved, P, I, S, max_steps=steps)
        assert torch.equal(f_walk, f_grid), (steps, int((f_walk != f_grid).sum()))
        torch.testing.assert_close(b_walk, b_grid, equal_nan=True)
    # the walk really moved points to other triangles
    assert bool((f_grid != S).any())


def test_locate_walk_outside_and_walking_off(device, dtype):
    gen = torch.Generator().manual_seed(11)
    mesh = exact_batch(device, dtype)
    moved = mesh.with_verts(jiggle(mesh, 0.4, gen))
    # outside points with a (wrong) start face inside, and with start -1
    pts = torch.tensor([[1.5, 0.0], [0.0, -3.0], [0.2, 0.1]], device=device, dtype=dtype)
    items = torch.zeros(3, dtype=torch.long, device=device)
    start = torch.tensor([0, -1, -1], device=device)
    f, b = locate_walk(moved, pts, items, start)
    fg, _ = locate_grid(moved, pts, items)
    assert f[:2].tolist() == [-1, -1] and f[2] == fg[2] and f[2] >= 0
    assert bool(torch.isnan(b[:2]).all())


def dense_locate(mesh: MeshBatch, pts: torch.Tensor, items: torch.Tensor) -> torch.Tensor:
    """Every (point, triangle of its item) pair scored in the same arithmetic: the largest
    smallest-barycentric coordinate, ties to the lowest index, -1 below the tolerance."""
    T = mesh.faces.shape[0]
    pair = mesh.face_item[None, :] == items[:, None]                       # (P,T)
    p_idx, f_idx = pair.nonzero(as_tuple=True)
    s = barycentric(mesh.verts, mesh.faces, f_idx, pts[p_idx]).min(1).values
    score = torch.full(pair.shape, float("-inf"), dtype=s.dtype, device=s.device)
    score[p_idx, f_idx] = s
    best = score.max(1).values
    first = torch.where(score == best[:, None], torch.arange(T, device=s.device), T).min(1).values
    return torch.where(best >= -inside_tolerance(mesh.dtype), first, torch.full_like(first, -1))


def dyadic_jiggle(mesh: MeshBatch, gen: torch.Generator) -> torch.Tensor:
    """Interior vertices moved by multiples of 1/16 of the item's shortest edge (dyadic on
    the square meshes, so every coordinate and barycentric stays exact)."""
    v = mesh.verts.detach()
    el = (v[mesh.edges[:, 0]] - v[mesh.edges[:, 1]]).norm(dim=1)
    h = torch.full((mesh.num_items,), float("inf"), dtype=v.dtype, device=v.device)
    h = h.scatter_reduce(0, mesh.edge_item, el, "amin")[mesh.vert_item]
    h = torch.exp2(torch.floor(torch.log2(h)))                              # a power of two
    d = torch.randint(-6, 7, v.shape, generator=gen).to(v.device, v.dtype) / 16 * h[:, None]
    d[mesh.is_boundary_vert] = 0
    for _ in range(8):
        if bool((mesh.signed_areas(v + d) > 0).all()):
            return v + d
        d = d / 2
    return v


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_locate_walk_equals_brute_force(seed, device, dtype):
    """From random start triangles of the point's item (or -1), on randomly moved meshes: the
    walk finds the triangle of a brute-force location, with points on vertices, on edges (exact
    ties on the dyadic meshes) and outside; also when few steps force the grid fallback."""
    gen = torch.Generator().manual_seed(100 + seed)
    squares = exact_batch(device, dtype)
    sq = squares.with_verts(dyadic_jiggle(squares, gen))
    hexes = hex_batch(device, dtype)
    hx = hexes.with_verts(jiggle(hexes, 0.4, gen))
    for mesh, exact in ((sq, True), (hx, False)):
        mesh.validate()
        pts, items = sample_points(mesh, gen, n_random=30, n_box=20)
        first, count = mesh.faces_first_idx[items], mesh.faces_per_item[items]
        start = first + (torch.rand(items.shape, generator=gen).to(device) * count).long()
        start[torch.rand(items.shape, generator=gen).to(device) < 0.1] = -1
        want = dense_locate(mesh, pts, items)
        if exact:                                      # the dense reference itself is exact here
            ref = brute_locate(mesh.verts, mesh.faces, mesh.face_item.tolist(), pts, items.tolist(),
                               exact=True, inside_tol=inside_tolerance(dtype))
            assert want.cpu().tolist() == [r[0] for r in ref]
        assert bool((want == -1).any()) and bool((want >= 0).any())
        # the default buffer, one holding every point, one of 5 rows (the rest by the grid)
        for steps, every, cap in ((16, 2, None), (16, 1, pts.shape[0]), (16, 2, 5), (3, 2, None),
                                  (1, 2, None), (0, 2, None)):
            f, b = locate_walk(mesh, pts, items, start, max_steps=steps, check_every=every, capacity=cap)
            assert torch.equal(f, want), (exact, steps, cap, int((f != want).sum()))
            torch.testing.assert_close(b, barycentric(mesh.verts, mesh.faces, f, pts), equal_nan=True)
            f2, none = locate_walk(mesh, pts, items, start, max_steps=steps, return_bary=False)
            assert none is None and torch.equal(f2, want)
        # the walk did cross triangles
        assert bool((want != start).float().mean() > 0.5)


def test_locate_walk_few_host_reads(device):
    """Fixed-shape steps: after small moves the walk reads the host once (two flags after its
    first 2 steps) and does no boolean indexing, nonzero or scalar read."""
    from torch.overrides import TorchFunctionMode
    from torch.utils._python_dispatch import TorchDispatchMode
    dtype = torch.float64
    gen = torch.Generator().manual_seed(5)
    mesh = hex_batch(device, dtype)
    pts, items = sample_points(mesh, gen, n_random=50, n_box=0, quarter=False)
    start = locate_grid(mesh, pts, items)[0]
    strict = barycentric(mesh.verts, mesh.faces, start, pts).min(1).values > 0.05   # no ties
    pts, items, start = pts[strict], items[strict], start[strict]
    moved = mesh.with_verts(jiggle(mesh, 0.3, gen))
    moved.face_neighbors                                                 # topology built outside
    seen = {"tolist": 0, "sync": 0}

    class Reads(TorchFunctionMode):
        def __torch_function__(self, func, types, args=(), kwargs=None):
            if getattr(func, "__name__", "") == "tolist":
                seen["tolist"] += 1
            return func(*args, **(kwargs or {}))

    class Syncs(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            bool_index = func is torch.ops.aten.index.Tensor and any(
                i is not None and i.dtype == torch.bool for i in args[1])
            if bool_index or func in (torch.ops.aten.nonzero.default, torch.ops.aten._local_scalar_dense.default):
                seen["sync"] += 1
            return func(*args, **(kwargs or {}))

    with Reads(), Syncs():
        f, _ = locate_walk(moved, pts, items, start, return_bary=False)
    assert seen == {"tolist": 1, "sync": 0}
    assert torch.equal(f, dense_locate(moved, pts, items))
    assert bool((f != start).any())                                      # some points did walk
