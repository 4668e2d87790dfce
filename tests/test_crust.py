"""pipeline/crust.py (the crust parity coupling) against hand-known crusts, brute-force
segment/edge intersections and point-in-polygon parity."""
import math
from types import SimpleNamespace

import numpy as np
import torch

import torch_isc
from torch_isc.core.locate import locate_grid
from torch_isc.core.mesh import square_mesh
from torch_isc.pipeline.config import ReconstructConfig
from torch_isc.pipeline.crust import crossing_counts, crust_coupling, crust_segments


def _circle(n, r=0.3, cx=0.0, cy=0.0, phase=0.1):
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n) + phase
    return torch.stack([cx + r * t.cos(), cy + r * t.sin()], 1)


def _mesh(res=9):
    return square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.full((1,), 0.55, dtype=torch.float64), res)


def test_crust_of_an_evenly_sampled_circle_is_its_polygon():
    p = _circle(40)
    seg, _ = crust_segments(p, torch.zeros(40, dtype=torch.long), 1, 3.0)
    got = sorted(map(tuple, seg.tolist()))
    want = sorted(tuple(sorted((i, (i + 1) % 40))) for i in range(40))
    assert got == want


def test_crust_drops_an_outliers_long_link_and_keeps_items_apart():
    p = torch.cat([_circle(40), torch.tensor([[0.0, 0.0]], dtype=torch.float64), _circle(30, cx=5.0)])
    item = torch.cat([torch.zeros(41, dtype=torch.long), torch.ones(30, dtype=torch.long)])
    seg, _ = crust_segments(p, item, 2, 3.0)
    assert not (seg == 40).any()                       # the centre point is 0.3 away: ~6 spacings
    assert (item[seg[:, 0]] == item[seg[:, 1]]).all()
    assert seg.shape[0] == 40 + 30


def test_crust_keeps_a_sparse_components_chain_and_drops_outlier_pairs():
    """A dense circle (200 samples, spacing 0.0094) with an 8-sample circle of radius 0.1 beside
    it (spacing 0.077: 8 spacings of the item) and two outliers 0.05 apart: the small circle's
    chain is kept whole (each segment about 1x both ends' neighbour distances, two segments at
    each end), the outliers' link is not (each has one segment), nor any link to them."""
    big = _circle(200, 0.3)
    small = _circle(8, 0.1, cx=0.8, phase=0.2)
    pair = torch.tensor([[-0.8, 0.5], [-0.75, 0.5]], dtype=torch.float64)
    p = torch.cat([big, small, pair])
    seg, sp = crust_segments(p, torch.zeros(p.shape[0], dtype=torch.long), 1, 3.0)
    got = set(map(tuple, seg.tolist()))
    ring = {tuple(sorted((200 + i, 200 + (i + 1) % 8))) for i in range(8)}
    assert ring <= got
    assert not (seg >= 208).any()
    assert seg.shape[0] == 200 + 8
    assert abs(float(sp[0]) - 2 * 0.3 * math.sin(math.pi / 200)) < 1e-9


def _satellites(a0, rs, n_small, n_big=300):
    t = torch.arange(n_big, dtype=torch.float64) * 2 * math.pi / n_big
    pts = [torch.stack([t.cos(), t.sin()], 1)]
    for k in range(6):
        c = (1.5 * math.cos(a0 + k * math.pi / 3), 1.5 * math.sin(a0 + k * math.pi / 3))
        pts.append(_circle(n_small, rs, c[0], c[1], 0.3 * k))
    return torch.cat(pts)


def test_sparse_satellites_are_each_one_loop(monkeypatch):
    """Noise-free: a unit circle of 300 samples and six circles of radius 0.12-0.18 with 7-9
    samples at distance 1.5 (issue 13's satellites). The small circles' chains now count in the
    crust (their segments are 8-12 of the item's spacings, over its limit of 3), so their signs
    follow the samples: 7 loops each. Without them (``CHAIN_RATIO`` 0) satellites were cut in
    two or lost (9, 10, 12 loops on these sets)."""
    import torch_isc.pipeline.crust as crust
    sets = [_satellites(0.5, 0.12, 9), _satellites(0.5, 0.18, 7), _satellites(0.5, 0.18, 9), _satellites(0.1, 0.12, 7)]
    for r in torch_isc.reconstruct_batch(sets, ReconstructConfig()):
        assert r.num_closed == 7 and r.num_open == 0
    monkeypatch.setattr(crust, "CHAIN_RATIO", 0.0)
    assert sum(r.num_closed != 7 for r in torch_isc.reconstruct_batch(sets, ReconstructConfig())) >= 2


def _brute_counts(mesh, p, q):
    """Crossings per edge by exact orientation tests over every (segment, edge) pair, in Python."""
    v = mesh.verts.tolist()
    out = []

    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    for a, b in mesh.edges.tolist():
        A, B = v[a], v[b]
        k = 0
        for P, Q in zip(p.tolist(), q.tolist()):
            if orient(P, Q, A) * orient(P, Q, B) < 0 and orient(A, B, P) * orient(A, B, Q) < 0:
                k += 1
        out.append(k)
    return torch.tensor(out)


def test_crossing_counts_match_brute_force():
    """The walk through the mesh follows every segment that stays inside it, however many
    triangles it passes (the earlier four-probe sampling dropped those that skipped one), and its
    counts are the brute-force intersections; where each edge is crossed is returned too."""
    mesh = _mesh(7)
    g = torch.Generator().manual_seed(3)
    p = (torch.rand(80, 2, generator=g, dtype=torch.float64) - 0.5) * 0.9
    ang = torch.rand(80, generator=g, dtype=torch.float64) * 2 * math.pi
    # segments up to about three cells long
    length = 0.45 * torch.rand(80, generator=g, dtype=torch.float64)
    q = p + length[:, None] * torch.stack([ang.cos(), ang.sin()], 1)
    item = torch.zeros(80, dtype=torch.long)
    fp, _ = locate_grid(mesh, p, item)
    fq, _ = locate_grid(mesh, q, item)
    inside = (fp >= 0) & (fq >= 0)
    assert (~inside).any() and inside.sum() > 60
    got, followed, span = crossing_counts(mesh, p, q, item, fp, fq, extent=True)
    assert torch.equal(followed, inside)                     # every segment inside the mesh
    assert torch.equal(got, _brute_counts(mesh, p[inside], q[inside]))
    assert got.max() >= 2 and got.sum() > 60
    # the crossing of a once-crossed edge, by hand: where the segment meets the edge's line
    v = mesh.verts
    one = (got == 1).nonzero().squeeze(1)
    for ei in one[:20].tolist():
        a, b = v[mesh.edges[ei, 0]], v[mesh.edges[ei, 1]]
        hits = []
        for P, Q in zip(p[inside], q[inside]):
            d, e, w = Q - P, b - a, a - P
            den = d[0] * e[1] - d[1] * e[0]
            t = (w[0] * e[1] - w[1] * e[0]) / den
            u = (w[0] * d[1] - w[1] * d[0]) / den
            if 0 < t < 1 and 0 < u < 1:
                hits.append(float(u))
        assert len(hits) == 1
        assert abs(float(span[ei, 0]) - hits[0]) < 1e-9 and abs(float(span[ei, 1]) - hits[0]) < 1e-9
    # a segment that leaves the mesh counts for nothing
    far = torch.tensor([[0.0, 0.0]], dtype=torch.float64), torch.tensor([[2.0, 0.0]], dtype=torch.float64)
    f0, _ = locate_grid(mesh, far[0], item[:1])
    cnt, fol = crossing_counts(mesh, far[0], far[1], item[:1], f0, torch.full_like(f0, -1))
    assert not fol.any() and cnt.sum() == 0


def _ws(points, noise, tol=0.004, res=12):
    mesh = _mesh(res)
    item = torch.zeros(points.shape[0], dtype=torch.long)
    face, _ = locate_grid(mesh, points, item)
    return SimpleNamespace(mesh=mesh, points=points, point_item=item, face=face, num_items=1,
                           noise=torch.tensor([noise], dtype=torch.float64),
                           tol=torch.tensor([tol], dtype=torch.float64))


def test_coupling_follows_point_in_polygon_parity():
    # a thin ring: two circles 0.06 apart, 120 and 100 samples (spacing 0.016-0.015)
    pts = torch.cat([_circle(120, 0.3), _circle(100, 0.24)])
    ws = _ws(pts, noise=0.0)
    H = crust_coupling(ws, 2.0, 0.1, 3.0)
    v = ws.mesh.verts
    r = v.norm(dim=1)
    # inside the ring of polygons: the true curves' polygons are within 0.3*(1-cos(pi/120)) of the circles
    side = ((r < 0.3) & (r > 0.24)).long()
    e = ws.mesh.edges
    nz = H != 0
    assert nz.sum() > 30
    differ = side[e[:, 0]] != side[e[:, 1]]
    # no mesh vertex lies between a circle and its polygon (checked), so parity = ring membership
    gap = ((r - 0.3).abs() < 0.3 * (1 - math.cos(math.pi / 120)) + 1e-9) | ((r - 0.24).abs() < 0.01)
    assert not gap.any()
    assert torch.equal(H[nz] > 0, differ[nz])
    assert (H[nz].abs() == 2.0).all()


def test_noisy_items_get_no_coupling():
    pts = _circle(120, 0.3)
    ws = _ws(pts, noise=0.001)                          # noise 0.25 tolerances > 0.1
    assert (crust_coupling(ws, 2.0, 0.1, 3.0) == 0).all()
    ws = _ws(pts, noise=0.0003)
    assert (crust_coupling(ws, 2.0, 0.1, 3.0) != 0).any()
    # a large tolerance: now the spacing (0.0157) gates, at 0.1 spacings
    ws = _ws(pts, noise=0.003, tol=0.1)
    assert (crust_coupling(ws, 2.0, 0.1, 3.0, 0.1) == 0).all()
    ws = _ws(pts, noise=0.001, tol=0.1)
    assert (crust_coupling(ws, 2.0, 0.1, 3.0, 0.1) != 0).any()


def test_two_circles_three_spacings_apart_stay_two():
    """Noise-free close curves (the issue's close2): the gap's line fits see both walls; the
    crust's parity keeps the vertices in the gap outside."""
    m = 160
    h = 2 * math.pi / m
    pts = torch.cat([_circle(m, 1.0, -1 - 1.5 * h, 0.0, 0.0), _circle(m, 1.0, 1 + 1.5 * h, 0.0, 0.0)])
    a = 0.4
    R = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=torch.float64)
    pts = pts @ R.T
    on = torch_isc.reconstruct(pts, ReconstructConfig().replace(crust_weight=2.0))
    assert on.num_closed == 2 and on.num_open == 0
    for pl in on.polylines:
        c = pl["points"].mean(0)
        d = (pl["points"] - c).norm(dim=1)
        assert (d - 1.0).abs().max() < 0.05


def _close2(m, a):
    h = 2 * math.pi / m
    pts = torch.cat([_circle(m, 1.0, -1 - 1.5 * h, 0.0, 0.0), _circle(m, 1.0, 1 + 1.5 * h, 0.0, 0.0)])
    R = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=torch.float64)
    return pts @ R.T


def test_dense_close_circles_are_refined_apart():
    """Noise-free close2 with dense samples (the gap, 3 spacings, is 0.7-1.3% of the diagonal:
    below 4 tolerances): the signs contradicted the crust where the island rule flipped the gap's
    one vertex, and edges across both walls joined the circles. ``crust_refine`` splits there
    (on the default): two circles at every angle; without it they merge at most angles."""
    sets = [_close2(300, a) for a in (0.1, 0.7, 1.0)] + [_close2(540, 0.1)]
    off = torch_isc.reconstruct_batch(sets, ReconstructConfig().replace(crust_refine=0.0))
    assert sum(r.num_closed == 1 for r in off) >= 2
    for r in torch_isc.reconstruct_batch(sets, ReconstructConfig()):
        assert r.num_closed == 2 and r.num_open == 0 and r.limit is None
        for pl in r.polylines:
            P = pl["points"]
            c = 0.5 * (P.max(0).values + P.min(0).values)          # the vertices crowd at the gap
            assert ((P - c).norm(dim=1) - 1.0).abs().max() < 0.05      # 1% of the diagonal


def test_contradictions_mark_odd_edges_with_equal_signs_and_edges_across_a_gap():
    """By hand on a square mesh of cells 0.275 wide. One vertical chain of samples: an edge
    crossing it is marked when its ends have equal signs, not when they differ. Two chains 0.1
    apart inside one column of cells (a gap of 3 spacings): an edge crossing both is marked
    whatever its signs. Nothing is marked below the size floor."""
    from torch_isc.pipeline.crust import crust_contradictions
    ys = torch.linspace(-0.5, 0.5, 31, dtype=torch.float64)             # spacing 1/30

    def chain(x0):
        return torch.stack([torch.full_like(ys, x0), ys], 1)
    ws = _ws(chain(0.1), noise=0.0, res=4)
    x = ws.mesh.verts[:, 0]
    e, fe = ws.mesh.edges, ws.mesh.face_edges
    xa, xb = x[e[:, 0]], x[e[:, 1]]
    crosses = (xa - 0.1) * (xb - 0.1) < 0
    assert crosses.sum() >= 8
    right = torch.where(x > 0.1, -1.0, 1.0).to(torch.float64)
    assert not crust_contradictions(ws, right, 1.0, 0.1, 3.0, 0.1).any()
    flat = torch.ones_like(right)
    assert torch.equal(crust_contradictions(ws, flat, 1.0, 0.1, 3.0, 0.1), crosses[fe].any(1))
    assert not crust_contradictions(ws, flat, 100.0, 0.1, 3.0, 0.1).any()   # the floor
    # two chains at x = 0.09 and 0.19: no vertex in the gap; the column's edges cross both
    ws = _ws(torch.cat([chain(0.09), chain(0.19)]), noise=0.0, res=4)
    both = (torch.minimum(xa, xb) < 0.09) & (torch.maximum(xa, xb) > 0.19)
    assert both.sum() >= 4
    for signs in (flat, -flat):
        assert torch.equal(crust_contradictions(ws, signs, 1.0, 0.1, 3.0, 0.1), both[fe].any(1))


def test_coupling_of_an_item_does_not_depend_on_its_batch():
    a, b = _circle(120, 0.3), _circle(90, 0.2, 0.05, -0.1)
    one = [_ws(a, 0.0), _ws(b, 0.0)]
    mesh = square_mesh(torch.zeros(2, 2, dtype=torch.float64), torch.full((2,), 0.55, dtype=torch.float64), 12)
    pts = torch.cat([a, b])
    item = torch.cat([torch.zeros(120, dtype=torch.long), torch.ones(90, dtype=torch.long)])
    face, _ = locate_grid(mesh, pts, item)
    both = SimpleNamespace(mesh=mesh, points=pts, point_item=item, face=face, num_items=2,
                           noise=torch.zeros(2, dtype=torch.float64), tol=torch.full((2,), 0.004, dtype=torch.float64))
    H = crust_coupling(both, 2.0, 0.1, 3.0)
    E0 = one[0].mesh.edges.shape[0]
    assert torch.equal(H[:E0], crust_coupling(one[0], 2.0, 0.1, 3.0))
    assert torch.equal(H[E0:], crust_coupling(one[1], 2.0, 0.1, 3.0))


def _batch_ws(sets, noise, items, res):
    B = len(sets)
    mesh = square_mesh(torch.zeros(B, 2, dtype=torch.float64), torch.full((B,), 0.55, dtype=torch.float64), res)
    pts = torch.cat(sets)
    item = torch.cat([torch.full((s.shape[0],), i, dtype=torch.long) for i, s in enumerate(sets)])
    face, _ = locate_grid(mesh, pts, item)
    return SimpleNamespace(mesh=mesh, points=pts, point_item=item, face=face, num_items=B, device=pts.device,
                           items=torch.tensor(items), noise=torch.tensor(noise, dtype=torch.float64),
                           tol=torch.full((B,), 0.004, dtype=torch.float64))


def test_cached_crust_of_later_levels_is_the_crust_of_their_items():
    """The cache made at a solve's first level serves its later levels (items gone, finer mesh)
    with the coupling an uncached call computes from their points."""
    from torch_isc.pipeline.crust import CrustCache
    a, b, c = _circle(120, 0.3), _circle(90, 0.2, 0.05, -0.1), _circle(100, 0.25, phase=0.3)
    d = torch.cat([_circle(60, 0.3), _circle(50, 0.22)])
    first = _batch_ws([a, b, c, d], [0.0, 0.0, 0.01, 0.0], [0, 1, 2, 3], 12)
    cache = CrustCache()
    assert torch.equal(crust_coupling(first, 2.0, 0.1, 3.0, cache=cache), crust_coupling(first, 2.0, 0.1, 3.0))
    # items 0 and 2 have left; the others are on a finer mesh, points renumbered
    later = _batch_ws([b, c, d], [0.0, 0.01, 0.0], [1, 2, 3], 17)
    H = crust_coupling(later, 2.0, 0.1, 3.0, cache=cache)
    assert (H != 0).sum() > 30
    assert torch.equal(H, crust_coupling(later, 2.0, 0.1, 3.0))
    # only the noisy item left: no coupling
    last = _batch_ws([c], [0.01], [2], 9)
    assert (crust_coupling(last, 2.0, 0.1, 3.0, cache=cache) == 0).all()


def _even_odd(v, polygons):
    """``(V,)`` +1 outside / -1 inside every polygon by a naive ray cast (+x) per vertex."""
    inside = np.zeros(v.shape[0], dtype=bool)
    for poly in polygons:
        p = np.asarray(poly)
        q = np.roll(p, -1, 0)
        for a, b in zip(p, q):
            cross = (a[1] > v[:, 1]) != (b[1] > v[:, 1])
            x = a[0] + (v[:, 1] - a[1]) * (b[0] - a[0]) / np.where(b[1] == a[1], 1.0, b[1] - a[1])
            inside ^= cross & (v[:, 0] < x)
    return np.where(inside, -1.0, 1.0)


def test_crust_sides_follow_the_even_odd_rule_and_need_closed_chains():
    """Three nested circles (samples 0.02-0.03 apart, circles 0.08 apart), then the same with
    a gap cut out of the middle circle (an open chain), in one batch of three items with a
    noisy copy. Each vertex of the closed item gets its even-odd side of the three sample
    polygons (a ray cast per vertex); the open item and the noisy item get none."""
    from torch_isc.pipeline.crust import crust_parity, crust_sides
    closed = torch.cat([_circle(100, 0.4), _circle(80, 0.32, phase=0.3), _circle(60, 0.24, phase=0.5)])
    keep = torch.ones(closed.shape[0], dtype=torch.bool)
    keep[100:112] = False                               # 12 samples (0.3 of the circle's radius) gone
    ws = _batch_ws([closed, closed[keep], closed], [0.0, 0.0, 0.01], [0, 1, 2], 24)
    par, spacing, _ = crust_parity(ws, 0.1, 3.0, 0.1)
    side = crust_sides(ws.mesh, par, spacing)
    vi = ws.mesh.vert_item
    v = ws.mesh.verts.numpy()
    polys = [closed[:100].numpy(), closed[100:180].numpy(), closed[180:].numpy()]
    want = _even_odd(v[(vi == 0).numpy()], polys)
    assert (want < 0).sum() > 100 and (want > 0).sum() > 100
    assert np.array_equal(side[vi == 0].numpy(), want)
    assert (side[vi == 1] == 0).all() and (side[vi == 2] == 0).all()
    # the sides of an item do not depend on its batch
    one = _batch_ws([closed], [0.0], [0], 24)
    p1, s1, _ = crust_parity(one, 0.1, 3.0, 0.1)
    assert torch.equal(crust_sides(one.mesh, p1, s1), side[vi == 0])


def _jittered_ellipses(seed, k, gap):
    """``scripts/evaluate_nested_rings.py``'s ``ellipse_rings`` (jittered sampling) of the
    generator ``default_rng(100 + seed)``."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    from evaluate_nested_rings import ellipse_rings

    return torch.tensor(ellipse_rings(np.random.default_rng(100 + seed), k, gap))


def test_nested_curves_a_few_spacings_apart_keep_their_alternation():
    """Clean concentric ellipses 3-6 sample spacings apart along their major axes (1.8-6 along
    the minor ones), jittered samples: the loop's coarse levels see one band, and the annealer,
    warm-started from them, leaves arcs of an annulus with the wrong sign, walled off across
    it. The crust's sides hold the vertices to their side: one loop per curve. With
    ``crust_sides=0`` at least two of the four come back with another count. The first set (3
    spacings apart) is a coin toss at the last bit: right on an AVX2 CPU, its inner pair joined
    on an AVX-512 one (the vectorized sums round differently), so only the three wider sets must be."""
    sets = [_jittered_ellipses(0, 3, 3.0), _jittered_ellipses(0, 3, 4.0), _jittered_ellipses(2, 3, 4.0),
            _jittered_ellipses(2, 3, 6.0)]
    on = torch_isc.reconstruct_batch(sets, ReconstructConfig())
    assert all(r.num_open == 0 for r in on)
    assert all(r.num_closed == 3 for r in on[1:])
    off = torch_isc.reconstruct_batch(sets, ReconstructConfig().replace(crust_sides=0.0))
    assert sum(r.num_closed != 3 for r in off) >= 2


def test_crust_gate_reads_the_noise_against_the_spacing():
    """Two noise-free sets of the broad suite (seed 1) whose noise estimate reads a thin feature
    as a little noise: a dumbbell whose neck came back as two loops and a DejaVuSerif 9 with an
    extra loop. The old gate (0.1 of the configured tolerance, 0.1 spacings) kept the crust off;
    the new one (10 tolerances, 0.3 spacings) lets its coupling on, and both get their number of
    loops (the 9's is still off by more than 10% of the diagonal in the broad suite's scoring:
    the contradiction splits stay at the old gate, ``crust.REFINE_NOISE``). The 9's noise is
    estimated at 1.05 tolerances, so ``relax_noisy`` (0.5) leaves its mesh unrelaxed and it comes
    back with 3 loops; the gate is compared with every item relaxed and no transverse coverage
    split (on for items noisier than half their tolerance, it resolves the 9 with either gate), and
    with the test's noise factors of the time (``noise_factor`` 3, ``thin_feature_factor`` 3; with
    session 26's 2.5 and 1.0 this old noise estimate splits the 9 into 3 loops under either gate), as
    when it was set."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    import evaluate_synthetic as es
    suite = es.SUITES["broad"]
    kinds = suite["kinds"].split(",")
    noises = tuple(float(x) for x in suite["noises"].split(","))
    rng = np.random.default_rng(1)
    cases = [es.make_case(i, kinds, rng, es.GLYPHS, noises, es.FONT_GLYPHS) for i in range(108)]
    cases = [c for c in cases if c["name"] in ("dumbbell_7", "font_107")]
    assert [c["noise"] for c in cases] == ["n0", "n0"]
    pts = [torch.as_tensor(c["points"], dtype=torch.float64) for c in cases]
    want = [len(c["truth"]["curves"]) for c in cases]
    assert want == [1, 2]
    cfg = ReconstructConfig().replace(relax_noisy=1e6, coverage_transverse=0.0, noise_factor=3.0,
                                      thin_feature_factor=3.0)
    import torch_isc.pipeline.noise as noise_mod
    keep = noise_mod.MISFIT_RATIOS
    try:
        # the noise estimate of the time (eight neighbours): since session 24 four neighbours
        # read the 9's curvature for what it is, and both gates then give its two loops
        noise_mod.MISFIT_RATIOS = (0.003, 0.01)
        now = torch_isc.reconstruct_batch(pts, cfg)
        assert [r.num_closed for r in now] == want and all(r.num_open == 0 for r in now)
        old = torch_isc.reconstruct_batch(pts, cfg.replace(crust_noise_tolerances=0.1, crust_noise_spacings=0.1))
        assert all(r.num_closed != w for r, w in zip(old, want))
    finally:
        noise_mod.MISFIT_RATIOS = keep
