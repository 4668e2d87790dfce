"""Small isolated clusters of points (pipeline/blobs.py) against a brute-force reference and
hand-built meshes, and end to end: satellites of 8 noisy points each get their own loop."""
import math

import numpy as np
import pytest
import torch

from conftest import components_by_bfs, gpu_floor_counter
from torch_isc.core.locate import locate_grid
from torch_isc.core.mesh import hexagon_mesh
from torch_isc.pipeline import blobs as bl


def blobs_by_brute_force(x, k, lo, hi, noise, gap_widths, tangents=None):
    """find_blobs by plain loops: exact neighbours, breadth-first components, the criteria
    written out point by point (one item)."""
    x = np.asarray(x, dtype=float)
    P = len(x)
    D = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(D, np.inf)
    pairs = set()
    order = np.argsort(D, axis=1)
    for i in range(P):
        for r, j in enumerate(order[i, :k]):
            # the nearest always; a farther one only when i is among j's 2k nearest
            if r == 0 or i in order[j, :2 * k]:
                pairs.add((i, int(j)))
        for j in range(P):
            if noise is not None and D[i, j] <= gap_widths * noise:
                pairs.add((i, j))
    edges = torch.tensor(sorted(pairs), dtype=torch.long).reshape(-1, 2)
    lab = components_by_bfs(P, edges, torch.ones(len(edges), dtype=torch.bool))
    out = [-1] * P
    for root in set(lab):
        m = [i for i in range(P) if lab[i] == root]
        if not lo <= len(m) <= hi:
            continue
        c = x[m].mean(0)
        rad = np.linalg.norm(x[m] - c, axis=1).mean()
        cov = np.cov((x[m] - c).T, bias=True)
        ev = np.linalg.eigvalsh(cov)
        others = [i for i in range(P) if lab[i] != root]
        gap = D[np.ix_(m, others)].min() if others else np.inf
        if noise is None:
            need = bl.GAP_RADII * rad
        else:
            # the radius less the noise's part (mean squared distance r² + 2σ²), the gap less
            # the noise of its two sides
            rms2 = (np.linalg.norm(x[m] - c, axis=1) ** 2).mean()
            r_eff = min(rad, np.sqrt(max(rms2 - 2 * noise ** 2, 0.0)))
            need = max(bl.GAP_RADII * r_eff - 2 * bl.GAP_NOISE * noise, gap_widths * noise)
            if r_eff < bl.MIN_RADIUS * noise:          # no ring the noise would not explain
                continue
        # one-sided: unit directions from the centroid to each point's nearest other point
        dirs = []
        for i in m:
            j = min(others, key=lambda o: D[i, o]) if others else None
            if j is not None:
                dirs.append((x[j] - c) / np.linalg.norm(x[j] - c))
        side = not dirs or np.linalg.norm(np.mean(dirs, 0)) >= bl.ONE_SIDED
        if tangents is not None and others:
            # not on the continuation of the curve next to it: for both tangent estimates at
            # each point's nearest outside point o (the given one; the major axis of o's
            # max(k, hi + 8) nearest others outside the blob), the mean |cos| to o -> point
            kk = max(k, hi + 8)
            means = []
            for est in range(2):
                cs = []
                for i in m:
                    o = min(others, key=lambda j: D[i, j])
                    u = (x[i] - x[o]) / np.linalg.norm(x[i] - x[o])
                    if est == 0:
                        t = np.asarray(tangents[o], dtype=float)
                    else:
                        nb = [j for j in order[o, :kk] if j not in m]
                        q = x[nb] - x[o]
                        w, v = np.linalg.eigh(np.cov(q.T, bias=True))
                        t = v[:, 1]
                    cs.append(abs(float(t @ u)) / np.linalg.norm(t))
                means.append(np.mean(cs))
            side = side and min(means) < bl.CONTINUES
        if ev[0] >= bl.ROUNDNESS * ev[1] and gap >= need and side:
            for i in m:
                out[i] = root
    return out


def scene(rng, noise=0.0, n_main=120, n_sat=8, outliers=5):
    """A unit circle, two satellites of radius 0.15 at distance 1.5 and a few scattered outliers,
    scaled to about unit diagonal; returns points and each point's group (0 main, 1-2
    satellites, 3 outliers)."""
    t = np.linspace(0, 2 * np.pi, n_main, endpoint=False)
    parts = [np.stack([np.cos(t), np.sin(t)], 1)]
    s = np.linspace(0, 2 * np.pi, n_sat, endpoint=False) + 0.3
    for cx in (1.5, -1.5):
        parts.append(np.stack([cx + 0.15 * np.cos(s), 0.15 * np.sin(s)], 1))
    parts.append(rng.uniform(-1.2, 1.2, (outliers, 2)))
    grp = np.concatenate([np.full(len(p), g) for g, p in enumerate(parts)])
    x = np.concatenate(parts) / 3.4
    x = x + rng.normal(0, noise, x.shape)
    return x, grp


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_find_blobs_against_brute_force(seed):
    rng = np.random.default_rng(seed)
    x, _ = scene(rng, noise=0.002 * seed)
    sig = 0.002 * seed if seed else None
    pts = torch.as_tensor(x)
    item = torch.zeros(len(x), dtype=torch.long)
    got = bl.find_blobs(pts, item, 3, 6, 16, None if sig is None else torch.tensor([sig], dtype=torch.float64), 3.0)
    ref = blobs_by_brute_force(x, 3, 6, 16, sig, 3.0)
    assert got.tolist() == ref


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_find_blobs_on_the_denoising_neighbours_against_brute_force(seed):
    """The loop hands the denoising's neighbour search to the blob search (one search, not two):
    the blobs are still those of the exact neighbours; a search narrower than the blobs need is
    not used (the blob search runs its own: the same labels as without one)."""
    from torch_isc.pipeline.denoise import denoise_knn
    from torch_isc.pipeline.noise import NoiseConfig
    rng = np.random.default_rng(seed)
    x, _ = scene(rng, noise=0.002 * seed)
    sig = None if seed == 0 else torch.tensor([0.002 * seed], dtype=torch.float64)
    pts = torch.as_tensor(x)
    item = torch.zeros(len(x), dtype=torch.long)
    knn = denoise_knn(pts, item, NoiseConfig())
    assert knn[0].shape[1] >= 16 + 8
    got = bl.find_blobs(pts, item, 3, 6, 16, sig, 3.0, knn=knn)
    assert got.tolist() == blobs_by_brute_force(x, 3, 6, 16, None if sig is None else float(sig), 3.0)
    narrow = denoise_knn(pts, item, NoiseConfig(denoise_neighbours=12))
    assert torch.equal(bl.find_blobs(pts, item, 3, 6, 16, sig, 3.0, knn=narrow),
                       bl.find_blobs(pts, item, 3, 6, 16, sig, 3.0))


def test_find_blobs_finds_the_satellites_not_the_outliers():
    rng = np.random.default_rng(5)
    x, grp = scene(rng)
    got = bl.find_blobs(torch.as_tensor(x), torch.zeros(len(x), dtype=torch.long), 3, 6, 16)
    for g in (1, 2):                             # each satellite: one blob of its 8 points
        assert len(set(got[grp == g].tolist())) == 1 and int(got[grp == g][0]) >= 0
    assert int(got[grp == 1][0]) != int(got[grp == 2][0])
    assert (got[(grp == 0) | (grp == 3)] == -1).all()
    # too few points per blob (7 < 9): none; a two-item batch gives each item its own answer
    assert (bl.find_blobs(torch.as_tensor(x), torch.zeros(len(x), dtype=torch.long), 3, 9, 16) == -1).all()
    # (the loop's points are normalized per item: the second item is the same set, mirrored)
    both = bl.find_blobs(torch.as_tensor(np.concatenate([x, -x])),
                         torch.cat([torch.zeros(len(x)), torch.ones(len(x))]).long(), 3, 6, 16)
    assert ((both[:len(x)] >= 0) == (got >= 0)).all() and ((both[len(x):] >= 0) == (got >= 0)).all()
    # an elongated group (8 points on a short segment) is a piece of a curve, not a blob
    seg = np.concatenate([x[grp == 0], np.stack([np.linspace(0.6, 0.7, 8), np.zeros(8)], 1)])
    assert (bl.find_blobs(torch.as_tensor(seg), torch.zeros(len(seg), dtype=torch.long), 3, 6, 16) == -1).all()


class _WS:
    """The fields of a working set the blob stages read."""

    def __init__(self, mesh, pts, blob, signs):
        self.mesh, self.points, self.blob, self.signs = mesh, pts, blob, signs
        self.point_item = torch.zeros(len(pts), dtype=torch.long)
        self.face, self.bary = locate_grid(mesh, pts, self.point_item)
        self.num_items = 1

    def replace(self, **kw):
        out = _WS.__new__(_WS)
        out.__dict__.update(self.__dict__)
        out.__dict__.update(kw)
        return out


def test_snap_moves_a_corner_onto_the_centroid_and_the_stage_flips_it():
    mesh = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), 4)
    V = mesh.verts.shape[0]
    cen = torch.tensor([0.31, 0.17], dtype=torch.float64)         # inside a triangle, off its corners
    t = torch.arange(8, dtype=torch.float64) * (2 * math.pi / 8)
    ring = cen + 0.06 * torch.stack([torch.cos(t), torch.sin(t)], 1)
    blob = torch.zeros(8, dtype=torch.long)
    assert not (mesh.verts - cen).norm(dim=1).lt(1e-9).any()
    ws = _WS(mesh, ring, blob, torch.ones(V, dtype=torch.float64))
    out = bl.snap_blobs(ws)
    moved = (out.mesh.verts - mesh.verts).norm(dim=1) > 0
    assert int(moved.sum()) == 1                                   # one vertex moved...
    vc = int(moved.nonzero())
    assert torch.allclose(out.mesh.verts[vc], cen)                 # ...onto the centroid
    assert (out.mesh.signed_areas() > 0).all() and (out.mesh.quality() >= bl.SNAP_MIN_QUALITY).all()
    f2, _ = locate_grid(out.mesh, ring, out.point_item)
    assert out.face.tolist() == f2.tolist()                        # the points re-located
    # no curve near: the vertex at the centroid takes the other sign
    hit = bl.blob_vertices(out.mesh, out.signs, out.points, out.point_item, out.face, out.blob)
    assert hit.nonzero().squeeze(1).tolist() == [vc]
    # a curve through the blob's triangles already (vc negative): nothing to do
    s = out.signs.clone()
    s[vc] = -1
    assert not bl.blob_vertices(out.mesh, s, out.points, out.point_item, out.face, out.blob).any()
    # signs crossing elsewhere only: the snap still moves (the blob is unexplained); a blob the
    # signs explain (a point in a crossed triangle) is left where it is
    far = int((mesh.verts - torch.tensor([-0.5, -0.3], dtype=torch.float64)).norm(dim=1).argmin())
    s = torch.ones(V, dtype=torch.float64)
    s[far] = -1
    assert (bl.snap_blobs(ws.replace(signs=s)).mesh.verts - mesh.verts).norm(dim=1).gt(0).sum() == 1
    s = torch.ones(V, dtype=torch.float64)
    s[mesh.faces[ws.face[0]][0]] = -1
    assert bl.snap_blobs(ws.replace(signs=s)).mesh is mesh or torch.equal(bl.snap_blobs(ws.replace(signs=s)).mesh.verts, mesh.verts)


def test_satellites_get_their_loops_end_to_end():
    """A unit circle and six satellites of 8 points (radius 0.15) at 0.5% noise: 7 closed curves
    with the blob rule, fewer without it (the line fits cannot describe 8 points)."""
    import torch_isc
    rng = np.random.default_rng(3)
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    parts = [np.stack([np.cos(t), np.sin(t)], 1)]
    s = np.linspace(0, 2 * np.pi, 8, endpoint=False) + 0.2
    for k in range(6):
        a = k * np.pi / 3 + 0.1
        parts.append(np.stack([1.5 * np.cos(a) + 0.15 * np.cos(s), 1.5 * np.sin(a) + 0.15 * np.sin(s)], 1))
    x = np.concatenate(parts)
    x = x + rng.normal(0, 0.005 * 4.7, x.shape)
    pts = torch.as_tensor(x)
    on = torch_isc.reconstruct_batch([pts], torch_isc.load_config(None, {}))[0]
    off = torch_isc.reconstruct_batch([pts], torch_isc.load_config(None, {"blob_min_points": 0}))[0]
    assert on.num_components == 7
    assert off.num_components < 7


def test_an_item_without_blobs_does_not_depend_on_a_blob_item_in_its_batch():
    import torch_isc
    t = np.linspace(0, 2 * np.pi, 150, endpoint=False)
    circle = torch.as_tensor(np.stack([np.cos(t), 0.6 * np.sin(t)], 1))
    x, grp = scene(np.random.default_rng(5))
    assert (bl.find_blobs(torch.as_tensor(x), torch.zeros(len(x), dtype=torch.long), 3, 6, 16) >= 0).any()
    cfg = torch_isc.load_config(None, {})
    alone = torch_isc.reconstruct_batch([circle], cfg)[0]
    both = torch_isc.reconstruct_batch([torch.as_tensor(x), circle], cfg)
    assert torch.equal(alone.curve.values, both[1].curve.values)
    assert torch.equal(alone.curve.mesh.verts, both[1].curve.mesh.verts)


def test_a_ring_beside_a_line_is_a_blob_only_under_noise():
    """An exact octagon of radius 1 and a dense line 1.2 from its nearest vertex. That vertex's
    third nearest neighbour is on the line (1.2 < 2 sin(pi/4) = 1.414) but the line's points
    have their 6 nearest along the line: the ring is a component of its own. Its gap 1.2 is
    below 1.5 radii, so noise-free it is no blob; under noise 0.1 the radius the noise leaves is
    sqrt(1 - 2 * 0.01) = 0.99 and the gap needed 1.5 * 0.99 - 4 * 0.1 = 1.08 < 1.2: a blob."""
    a = np.arange(8) * np.pi / 4
    ring = np.stack([np.cos(a), np.sin(a)], 1)
    y = np.arange(-60, 61) * 0.05
    line = np.stack([np.full_like(y, 2.2), y], 1)
    x = np.concatenate([ring, line]) / 7          # the loop's points are normalized (unit diagonal)
    item = torch.zeros(len(x), dtype=torch.long)
    quiet = bl.find_blobs(torch.as_tensor(x), item, 3, 6, 16)
    assert (quiet == -1).all()
    sig = 0.1 / 7
    noisy = bl.find_blobs(torch.as_tensor(x), item, 3, 6, 16, torch.tensor([sig], dtype=torch.float64), 3.0)
    assert (noisy[:8] == noisy[0]).all() and int(noisy[0]) >= 0 and (noisy[8:] == -1).all()
    assert noisy.tolist() == blobs_by_brute_force(x, 3, 6, 16, sig, 3.0)
    # the line 2.0 away: a ring of radius under MIN_RADIUS noise widths once the noise's part
    # is taken off is no blob: noise 0.45 leaves sqrt(1 - 2 * 0.45²) = 0.77 < 0.9; noise 0.3
    # leaves 0.91 >= 0.6 (and 3 noise widths stay below the gap: the ring stays apart)
    far = np.concatenate([ring, line + [0.8, 0.0]]) / 7
    for sig, want in ((0.45, False), (0.3, True)):
        got = bl.find_blobs(torch.as_tensor(far), item, 3, 6, 16, torch.tensor([sig / 7], dtype=torch.float64), 3.0)
        assert bool((got[:8] >= 0).all()) == want and (got[8:] == -1).all()
        assert got.tolist() == blobs_by_brute_force(far, 3, 6, 16, sig / 7, 3.0)
    # the point's third neighbour joining as before (any of the k nearest): one component
    D = np.sqrt(((x[:, None] - x[None]) ** 2).sum(-1))
    np.fill_diagonal(D, np.inf)
    assert np.argsort(D[0])[2] >= 8


def test_rows_made_once_give_what_the_labels_give():
    """The loop's blob rows (made once per solve, ``WorkingSet.blob_count``; a row whose item has
    left is empty) against the labels counted on each call: three rings of 8 points in one mesh
    labelled by their first point, and the same rings as rows 1, 3, 4 of 6 (rows 0, 2, 5 empty):
    the same centroids, the same snap, the same vertices to flip; the rows' path reads nothing
    on the host in blobs.py (gpu_floor's count, when present)."""
    mesh = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), 4)
    V = mesh.verts.shape[0]
    t = torch.arange(8, dtype=torch.float64) * (2 * math.pi / 8)
    ring = 0.05 * torch.stack([torch.cos(t), torch.sin(t)], 1)
    cens = torch.tensor([[0.31, 0.17], [-0.33, 0.21], [0.05, -0.4]], dtype=torch.float64)
    pts = torch.cat([torch.tensor([[0.6, 0.6], [-0.6, -0.55]], dtype=torch.float64)] + [c + ring for c in cens])
    labels = torch.cat([torch.tensor([-1, -1]), torch.full((8,), 2), torch.full((8,), 10), torch.full((8,), 18)])
    rows = torch.cat([torch.tensor([-1, -1]), torch.full((8,), 1), torch.full((8,), 3), torch.full((8,), 4)])
    ws = _WS(mesh, pts, labels, torch.ones(V, dtype=torch.float64))
    c0, i0, r0, row0, has0 = bl.blob_centroids(pts, ws.point_item, labels)
    c1, i1, r1, row1, has1 = bl.blob_centroids(pts, ws.point_item, rows, 6)
    assert has0.tolist() == [True] * 3 and has1.tolist() == [False, True, False, True, True, False]
    assert torch.equal(c1[has1], c0) and torch.equal(r1[has1], r0) and torch.allclose(c0, cens, atol=1e-15)
    a = bl.snap_blobs(ws)
    b = bl.snap_blobs(ws.replace(blob=rows, blob_count=6))
    assert int(((a.mesh.verts - mesh.verts).norm(dim=1) > 0).sum()) == 3
    assert torch.equal(a.mesh.verts, b.mesh.verts) and torch.equal(a.face, b.face)
    hit = bl.blob_vertices(a.mesh, a.signs, pts, a.point_item, a.face, labels)
    assert int(hit.sum()) == 3
    assert torch.equal(hit, bl.blob_vertices(b.mesh, b.signs, pts, b.point_item, b.face, rows, 6))
    OpCounter = gpu_floor_counter()
    if OpCounter is None:
        return
    with OpCounter() as cnt:
        bl.blob_centroids(pts, ws.point_item, rows, 6)
        bl.blob_vertices(b.mesh, b.signs, pts, b.point_item, b.face, rows, 6)
    # (the point location of the centroids reads its own sizes: core/locate.py)
    assert sum(n for (site, kind), n in cnt.sites.items() if kind == "sync" and "blobs.py" in site) == 0


@pytest.mark.parametrize("seed", range(4))
def test_small_components_are_bfs_components_up_to_the_size(seed):
    """``small_components`` against breadth-first search on random graphs of many small parts and
    one long path (a dense curve, far longer than the rounds): each vertex of a component of at
    most ``max_size`` vertices gets its smallest vertex, every other vertex −1."""
    g = torch.Generator().manual_seed(seed)
    V = 400
    E = int(torch.randint(150, 260, (1,), generator=g))
    a = torch.randint(0, 300, (E,), generator=g)
    b = (a + torch.randint(1, 4, (E,), generator=g)).clamp_max(299)
    path = torch.stack([torch.arange(300, 399), torch.arange(301, 400)], 1)    # 100 vertices in a row
    edges = torch.cat([torch.stack([a, b], 1), path])
    edges = edges[torch.randperm(edges.shape[0], generator=g)]
    bfs = torch.tensor(components_by_bfs(V, edges, torch.ones(edges.shape[0], dtype=torch.bool)))
    size = torch.zeros(V, dtype=torch.long).index_add_(0, bfs, torch.ones(V, dtype=torch.long))[bfs]
    for max_size in (1, 3, 8, 16):
        want = torch.where(size <= max_size, bfs, torch.full_like(bfs, -1))
        assert torch.equal(bl.small_components(V, edges, max_size), want)
        assert (want[300:] == -1).all() and (want >= 0).any()


def line_and_rings():
    """Two items: a line of 151 points (y = 0, x from -3 to 0) and an exact octagon of radius 1,
    on the line's continuation (centre (2.6, 0), 1.6 past its end) in item 0 and beside it
    (centre (-1.5, 2.6), 1.6 above it) in item 1; normalized to about unit size. Returns points,
    items, groups (0 line, 1 ring) and the line's tangent (1, 0) at every point (the rings' own
    are never read)."""
    a = np.arange(8) * np.pi / 4 + 0.2
    ring = np.stack([np.cos(a), np.sin(a)], 1)
    line = np.stack([np.linspace(-3, 0, 151), np.zeros(151)], 1)
    x = np.concatenate([line, ring + [2.6, 0.0], line, ring + [-1.5, 2.6]]) / 7
    item = np.repeat([0, 1], 159)
    grp = np.tile(np.repeat([0, 1], [151, 8]), 2)
    tang = np.tile([1.0, 0.0], (len(x), 1))
    return x, item, grp, tang


def test_a_ring_on_the_continuation_of_a_curve_is_no_blob_one_beside_it_is():
    """Both rings are round, isolated (gap 1.6 > 1.5 radii) and one-sided, so without tangents
    both are blobs. The end ring's points see the line's end point along the line (mean |cos|
    0.96 by hand: (3.6, 0) at angle 0, (2.6, 1) at 90 degrees, ...), above CONTINUES: with
    tangents it is no blob. The side ring's points see the line below them (|cos| near 0)."""
    x, item, grp, tang = line_and_rings()
    it = torch.as_tensor(item)
    end, side = (item == 0) & (grp == 1), (item == 1) & (grp == 1)
    plain = bl.find_blobs(torch.as_tensor(x), it, 3, 6, 16)
    assert (plain[end] >= 0).all() and (plain[side] >= 0).all() and (plain[grp == 0] == -1).all()
    got = bl.find_blobs(torch.as_tensor(x), it, 3, 6, 16, tangents=torch.as_tensor(tang))
    assert (got[end] == -1).all() and (got[side] >= 0).all() and (got[grp == 0] == -1).all()
    # the end ring's alignment by hand: from the line's end (0, 0) to each octagon point
    a = np.arange(8) * np.pi / 4 + 0.2
    d = np.stack([2.6 + np.cos(a), np.sin(a)], 1)
    assert np.mean(np.abs(d[:, 0]) / np.linalg.norm(d, axis=1)) > bl.CONTINUES
    for b in (0, 1):
        m = item == b
        ref = blobs_by_brute_force(x[m], 3, 6, 16, None, 3.0, tang[m])
        mine = got[torch.as_tensor(m)]
        assert ((mine >= 0).numpy() == (np.asarray(ref) >= 0)).all()
    # both estimates must agree for the rule to drop a blob: a tangent turned across the line
    # at its end point alone (the axis of its neighbours still along the line) keeps the blob
    bad = tang.copy()
    bad[150] = [0.0, 1.0]
    kept = bl.find_blobs(torch.as_tensor(x), it, 3, 6, 16, tangents=torch.as_tensor(bad))
    assert (kept[end] >= 0).all()
    assert ((kept[:159] >= 0).numpy() == (np.asarray(blobs_by_brute_force(x[:159], 3, 6, 16, None, 3.0, bad[:159])) >= 0)).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_find_blobs_with_tangents_against_brute_force(seed):
    rng = np.random.default_rng(seed)
    x, _ = scene(rng, noise=0.002)
    t = rng.normal(size=x.shape)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    sig = torch.tensor([0.002], dtype=torch.float64)
    got = bl.find_blobs(torch.as_tensor(x), torch.zeros(len(x), dtype=torch.long), 3, 6, 16, sig, 3.0,
                        tangents=torch.as_tensor(t))
    assert got.tolist() == blobs_by_brute_force(x, 3, 6, 16, 0.002, 3.0, t)
