"""The split rules for small components and close curves (pipeline.tolerance): far clusters
(``far_clusters`` and its marks) against hand configurations and a brute-force reference of
the definition (numpy, all pairs); the transverse coverage rule against hand values."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_isc.core.locate import locate_grid
from torch_isc.core.mesh import hexagon_mesh
from torch_isc.pipeline.tolerance import TestConfig, curve_coverage_excess, far_clusters, mark_triangles


def brute_force(pts, item, d, eff, k, far_factor, ratio):
    """The definition, by all pairs: far, and the distance to the (k-1)-th nearest far point
    of the same item within ratio x d."""
    pts, item, d = np.asarray(pts, float), np.asarray(item), np.asarray(d, float)
    far = d > far_factor * np.asarray(eff, float)[item]
    member = np.zeros(len(pts), bool)
    radius = np.full(len(pts), np.inf)
    for i in np.flatnonzero(far):
        others = [np.hypot(*(pts[j] - pts[i])) for j in np.flatnonzero(far) if j != i and item[j] == item[i]]
        if len(others) >= k - 1:
            radius[i] = sorted(others)[k - 2]
            member[i] = radius[i] <= ratio * d[i]
    return member, radius


def ring(cx, cy, r, n):
    a = 2 * math.pi * np.arange(n) / n + 0.1
    return np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], 1)


def run(pts, item, d, eff, k=6, far_factor=1.5, ratio=0.75, device="cpu", dtype=torch.float64, reach=None):
    t = torch.as_tensor(np.asarray(pts), dtype=dtype, device=device)
    it = torch.as_tensor(np.asarray(item), device=device)
    res = torch.as_tensor(np.asarray(d, float) ** 2, dtype=dtype, device=device)
    rc = torch.zeros_like(res) if reach is None else torch.as_tensor(reach, dtype=dtype, device=device)
    m, r = far_clusters(t, it, res, rc, torch.as_tensor(eff, dtype=dtype, device=device), k, far_factor, ratio)
    return m.cpu().numpy(), r.double().cpu().numpy()


def test_far_clusters_hand_configuration(device, dtype):
    """The curve is the line y = 0 (d = |y|), tolerance 0.01 (far: beyond 0.015). An 8-point
    ring of radius 0.02 at height 0.2 is a cluster (its 5th neighbour lies 2 r sin(3 pi / 8)
    = 0.037 away, below 0.75 x 0.18); a lone outlier and a group of 3 points are not, nor is a
    dense run of points 0.005 off the curve (not far)."""
    sat = ring(0.3, 0.2, 0.02, 8)
    outlier = np.array([[-0.3, 0.3]])
    three = np.array([[0.0, -0.3], [0.01, -0.3], [0.02, -0.3]])
    onc = np.stack([np.linspace(-0.4, 0.4, 20), np.full(20, 0.005)], 1)
    pts = np.concatenate([sat, outlier, three, onc])
    d = np.abs(pts[:, 1])
    member, radius = run(pts, np.zeros(len(pts), int), d, [0.01], device=device, dtype=dtype)
    assert member.tolist() == [True] * 8 + [False] * 24
    np.testing.assert_allclose(radius[:8], 2 * 0.02 * math.sin(3 * math.pi / 8), rtol=1e-5)
    assert np.isinf(radius[12:]).all()                         # not far: no radius
    want_m, want_r = brute_force(pts, np.zeros(len(pts), int), d, [0.01], 6, 1.5, 0.75)
    assert member.tolist() == want_m.tolist()
    np.testing.assert_allclose(radius, want_r, rtol=1e-5)
    # 5 points of the ring are too few for a cluster of 6
    m5, _ = run(np.concatenate([sat[:5], outlier]), np.zeros(6, int), np.abs(np.concatenate([sat[:5], outlier])[:, 1]),
                [0.01], device=device, dtype=dtype)
    assert not m5.any()
    # the rule off
    m0, r0 = run(pts, np.zeros(len(pts), int), d, [0.01], k=0, device=device, dtype=dtype)
    assert not m0.any() and np.isinf(r0).all()


def test_far_clusters_radius_against_distance(device, dtype):
    """A ring nearer the curve: only its points farther than radius / ratio are members
    (brute force decides which), and a larger ratio admits them all."""
    sat = ring(0.0, 0.055, 0.02, 8)
    d = np.abs(sat[:, 1])
    item = np.zeros(8, int)
    member, _ = run(sat, item, d, [0.01], device=device, dtype=dtype)
    want, _ = brute_force(sat, item, d, [0.01], 6, 1.5, 0.75)
    assert member.tolist() == want.tolist()
    assert 0 < want.sum() < 8                                   # the case is mixed
    m2, _ = run(sat, item, d, [0.01], ratio=3.0, device=device, dtype=dtype)
    assert m2.all()


def test_far_clusters_items_apart_and_reach_for_no_curve(device, dtype):
    """Far points of another item are no neighbours: 4 points in item 0 and 4 at the same
    place in item 1 make no cluster of 6. A point with no curve near (inf) is as far as its
    reach says."""
    four = ring(0.0, 0.3, 0.02, 4)
    pts = np.concatenate([four, four + 1e-3])
    item = np.array([0] * 4 + [1] * 4)
    member, _ = run(pts, item, np.full(8, 0.3), [0.01, 0.01], device=device, dtype=dtype)
    assert not member.any()
    merged, _ = run(pts, np.zeros(8, int), np.full(8, 0.3), [0.01], device=device, dtype=dtype)
    assert merged.all()
    sat = ring(0.0, 0.0, 0.02, 8)
    inf = np.full(8, np.inf)
    near, _ = run(sat, np.zeros(8, int), inf, [0.01], reach=np.full(8, 0.01), device=device, dtype=dtype)
    assert not near.any()                                      # reach 0.01: not even far
    big, _ = run(sat, np.zeros(8, int), inf, [0.01], reach=np.full(8, 0.2), device=device, dtype=dtype)
    assert big.all()


def test_far_clusters_morton_neighbours_match_brute_force_on_a_random_set(device, dtype):
    """Few far points (all within the Morton windows): the approximate neighbours are exact."""
    rng = np.random.default_rng(3)
    pts = np.concatenate([ring(0.2, 0.2, 0.03, 7), rng.uniform(-0.5, 0.5, (9, 2))])
    d = rng.uniform(0.0, 0.4, len(pts))
    item = np.zeros(len(pts), int)
    member, radius = run(pts, item, d, [0.02], device=device, dtype=dtype)
    want_m, want_r = brute_force(pts, item, d, [0.02], 6, 1.5, 0.75)
    assert member.tolist() == want_m.tolist()
    np.testing.assert_allclose(radius, want_r, rtol=1e-5)


def test_mark_triangles_splits_a_far_cluster_while_larger_than_it(device, dtype):
    """A triangle holding a cluster member is marked with one point or more, while its longest
    edge (1 in the unit hexagon) exceeds the member's radius."""
    mesh = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 1)
    pts = torch.tensor([[0.5, 0.3], [-0.5, 0.3], [0.0, -0.5]], device=device, dtype=dtype)
    face, _ = locate_grid(mesh, pts, torch.zeros(3, dtype=torch.long, device=device))
    T = mesh.faces.shape[0]
    z = torch.zeros(T, device=device, dtype=dtype)
    count = torch.bincount(face, minlength=T).to(dtype)
    res = torch.zeros(3, device=device, dtype=dtype)           # every point on the curve: no other rule fires
    tol = torch.tensor([0.004], device=device, dtype=dtype)
    noise = torch.zeros(1, device=device, dtype=dtype)
    member = torch.tensor([True, True, False], device=device)
    radius = torch.tensor([0.5, 2.0, 0.1], device=device, dtype=dtype)
    cfg = TestConfig(min_split_size=0.0)
    marked, _, _ = mark_triangles(mesh, res, face, count, z, tol, noise, cfg, 3, clusters=(member, radius))
    assert marked.tolist() == [t == int(face[0]) for t in range(T)]
    assert not mark_triangles(mesh, res, face, count, z, tol, noise, cfg, 3)[0].any()
    # the cluster's own size guard: the edge (1) against cluster_split_size tolerances (0.004 each),
    # whatever min_split_size (300 tolerances: 1.2) says; at or above min_split_size, the latter
    def split(**kw):
        return mark_triangles(mesh, res, face, count, z, tol, noise, TestConfig(min_split_size=300.0, **kw), 3,
                              clusters=(member, radius))[0]
    assert split().tolist() == marked.tolist()                        # the default: 2 tolerances, 0.008
    assert split(cluster_split_size=240.0).tolist() == marked.tolist()  # 0.96 < 1
    assert not split(cluster_split_size=260.0).any()                    # 1.04 > 1
    assert not split(cluster_split_size=1e6).any()                      # capped at min_split_size (1.2)
    assert not mark_triangles(mesh, res, face, count, z, tol, noise, TestConfig(min_split_size=300.0), 3)[0].any()


def unit_hexagon_line(device, dtype):
    """Unit hexagon (6 triangles, every edge 1 long) with f = y - 0.1: the zero set is y = 0.1."""
    mesh = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 1)
    return mesh, mesh.verts[:, 1] - 0.1


def test_coverage_alignment_hand_values(device, dtype):
    """The upper-right triangle's piece is horizontal (y = 0.1, midpoint (0.5, 0.1)). Data
    running vertically at x = 0.45 (tangent (0, 1)) see it 0.05 across and at right angles:
    alignment 0; data running along it (tangent (1, 0)) give alignment 1."""
    mesh, values = unit_hexagon_line(device, dtype)
    pts = torch.tensor([[0.45, 0.1]], device=device, dtype=dtype)
    face, _ = locate_grid(mesh, pts, torch.zeros(1, dtype=torch.long, device=device))
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    up = torch.tensor([[0.0, 1.0, 0.05]], device=device, dtype=dtype)
    ex, reach, align = curve_coverage_excess(mesh, values, pts, face, up, alignment=True)
    t = int(face[0])
    assert float(ex[t]) == pytest.approx(0.05, abs=tol) and float(reach[t]) == pytest.approx(0.05, abs=tol)
    assert float(align[t]) == pytest.approx(0.0, abs=tol)
    ex2, reach2 = curve_coverage_excess(mesh, values, pts, face, up)          # without: as before
    assert torch.equal(ex2, ex) and torch.equal(reach2, reach)
    diag = torch.tensor([[math.sqrt(0.5), math.sqrt(0.5), 0.2]], device=device, dtype=dtype)
    _, _, a45 = curve_coverage_excess(mesh, values, pts, face, diag, alignment=True)
    assert float(a45[t]) == pytest.approx(math.sqrt(0.5), abs=tol)
    along = torch.tensor([[1.0, 0.0, 0.1]], device=device, dtype=dtype)
    _, _, a1 = curve_coverage_excess(mesh, values, pts, face, along, alignment=True)
    assert float(a1[t]) == pytest.approx(1.0, abs=tol)


def test_mark_triangles_transverse_coverage(device, dtype):
    """Every triangle's piece is 0.1 off the data (0.001 for the fifth) and smaller than twice
    the reach (1 < 1.2), so the plain coverage rule splits none; a piece across the data
    (alignment below 0.7) is split, down to transverse_split_size tolerances, past
    min_split_size; with transverse_noisy 0.5, only where the noise exceeds 0.002 (half the
    tolerance 0.004)."""
    mesh, _ = unit_hexagon_line(device, dtype)
    T = mesh.faces.shape[0]
    z = torch.zeros(T, device=device, dtype=dtype)
    f0 = torch.zeros(0, dtype=torch.long, device=device)
    args = (mesh, torch.zeros(0, device=device, dtype=dtype), f0, z, z, torch.tensor([0.004], device=device, dtype=dtype),
            torch.zeros(1, device=device, dtype=dtype))
    excess = torch.tensor([0.1, 0.1, 0.1, 0.1, 0.001, 0.1], device=device, dtype=dtype)
    reach = torch.full((T,), 0.6, device=device, dtype=dtype)
    align = torch.tensor([0.2, 0.69, 0.71, 1.0, 0.0, 0.2], device=device, dtype=dtype)
    cov = (excess, reach, align)
    cfg = TestConfig(min_split_size=0.0, coverage_transverse=0.7, transverse_noisy=0.0)
    assert mark_triangles(*args, cfg, 3, coverage=cov)[0].tolist() == [True, True, False, False, False, True]
    # the noise gate: noise 0 and 0.002 (at the bound) split nothing, 0.0021 splits as above
    # (its effective tolerance 3 x 0.0021 = 0.0063 is still far below the pieces' 0.1)
    gated = TestConfig(min_split_size=0.0, coverage_transverse=0.7, transverse_noisy=0.5)
    for nz, want in ((0.0, [False] * 6), (0.002, [False] * 6), (0.0021, [True, True, False, False, False, True])):
        a = args[:-1] + (torch.tensor([nz], device=device, dtype=dtype),)
        assert mark_triangles(*a, gated, 3, coverage=cov)[0].tolist() == want
    assert not mark_triangles(*args, cfg, 3, coverage=(excess, reach))[0].any()
    assert not mark_triangles(*args, TestConfig(min_split_size=0.0, coverage_transverse=0.0), 3, coverage=cov)[0].any()
    # min_split_size 300 x 0.004 = 1.2 > 1 stops the other rules, not this one
    big = TestConfig(min_split_size=300.0, coverage_transverse=0.7, transverse_noisy=0.0)
    assert mark_triangles(*args, big, 3, coverage=cov)[0].tolist() == [True, True, False, False, False, True]
    # its own floor: 300 tolerances
    floor = TestConfig(min_split_size=0.0, coverage_transverse=0.7, transverse_split_size=300.0, transverse_noisy=0.0)
    assert not mark_triangles(*args, floor, 3, coverage=cov)[0].any()
