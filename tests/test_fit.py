"""Tests of the stages of the reconstruction loop (torch_isc.pipeline), each stage alone.

Expected values are computed by hand or by an independent route (float64 numpy / Python
loops over triangles and points, brute force over all sign patterns, closed forms); none is
read back from the library's own tables.
"""
from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import pytest
import torch

from torch_isc import locate_children, locate_grid
from torch_isc.core.curve import ImplicitCurve
from torch_isc.pipeline.values import (GeometryConfig, GeometryObjective, delta1_per_triangle, fit_geometry, point_residuals,
                                   vertex_data_distance, vertex_data_distance_near)
from torch_isc.pipeline.optim import batched_lbfgs
from torch_isc.pipeline.relax import RelaxConfig, mesh_energy, relax_mesh, relax_stage
from torch_isc.pipeline.workset import WorkingSet
from torch_isc.core.subdivide import subdivide
from torch_isc.pipeline.noise import NoiseConfig, estimate_noise, noise_and_frames
from torch_isc.pipeline.tolerance import (TestConfig, curve_coverage_excess, mark_triangles, point_curve_distance2,
                                          triangle_errors)
from torch_isc.core.segments import hash_uniform, segment_median
from torch_isc.pipeline.evidence import line_fits, pooled_moments, triangle_moments
from torch_isc.pipeline.signs import (TopologyConfig, anneal, edge_weights, ising_energy, remove_small_islands,
                                      sign_islands, vertex_coloring)
from torch_isc.core.locate import barycentric
from torch_isc.core.mesh import MeshBatch, hexagon_mesh, square_mesh

from conftest import assert_same, ref_bary64

SQ3 = math.sqrt(3.0)


# ----------------------------------------------------------------------------- helpers


def one_triangle(device, dtype):
    v = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.3, 0.9]], device=device, dtype=dtype)
    f = torch.tensor([[0, 1, 2]], device=device)
    return MeshBatch(v, f, torch.tensor([3]), torch.tensor([1]))


def hexagons(B, r, device, dtype, radius=1.0):
    c = torch.zeros(B, 2, device=device, dtype=dtype)
    c[:, 0] = torch.arange(B, dtype=dtype, device=device) * 3.0 * radius
    return hexagon_mesh(c, torch.full((B,), radius, device=device, dtype=dtype), r)


def locate_single(mesh, pts):
    item = torch.zeros(pts.shape[0], dtype=torch.long, device=pts.device)
    face, bary = locate_grid(mesh, pts, item)
    return item, face, bary


def naive_local_faces(mesh, b):
    v0 = int(mesh.verts_first_idx[b])
    f0, nf = int(mesh.faces_first_idx[b]), int(mesh.faces_per_item[b])
    return (mesh.faces[f0:f0 + nf] - v0).cpu().tolist()


def edge_index(mesh):
    return {(int(a), int(b)): k for k, (a, b) in enumerate(mesh.edges.cpu().tolist())}


def disc_points(n, radius, gen, dtype=torch.float64, center=(0.0, 0.0)):
    r = radius * torch.rand(n, generator=gen, dtype=torch.float64).sqrt()
    t = 2 * math.pi * torch.rand(n, generator=gen, dtype=torch.float64)
    return torch.stack([center[0] + r * t.cos(), center[1] + r * t.sin()], 1).to(dtype)


# ============================================================================= line fits


def test_line_fit_collinear_points(device, dtype):
    mesh = one_triangle(device, dtype)
    c = np.array([1.3 / 3, 0.3])                       # triangle centroid
    th = 0.3
    u = np.array([math.cos(th), math.sin(th)])
    n = np.array([-math.sin(th), math.cos(th)])
    s = np.linspace(-0.2, 0.2, 17)
    p = c[None, :] + s[:, None] * u[None, :]
    pts = torch.tensor(p, device=device, dtype=dtype)
    _, face, bary = locate_single(mesh, pts)
    assert (face == 0).all()
    mom = triangle_moments(mesh, pts, face, bary)
    L, eps, normal = line_fits(mesh, mom)
    assert float(mom.count[0]) == 17
    # eps: mean squared distance to the best line = 0 up to rounding
    assert 0 <= float(eps[0]) <= (1e-6 if dtype == torch.float32 else 1e-14)
    V = np.array([[0.0, 0.0], [1.0, 0.0], [0.3, 0.9]])
    pc = p.mean(0)
    Lref = (V - pc) @ n                                   # signed distances of the vertices to the line
    Lg = L[0].double().cpu().numpy()
    sgn = np.sign(Lg @ Lref)
    atol = 1e-5 if dtype == torch.float32 else 1e-12
    np.testing.assert_allclose(sgn * Lg, Lref, atol=atol)
    np.testing.assert_allclose(abs(float(normal[0].double().cpu() @ torch.tensor(n))), 1.0, atol=atol)
    np.testing.assert_allclose(mom.centroid[0].double().cpu().numpy(), pc, atol=atol)
    # M_t = mean of X Xᵀ (eq. 3.2), with X the barycentric coordinates by Cramer's rule
    X = np.array([ref_bary64(V, q) for q in p])
    Mref = (X[:, :, None] * X[:, None, :]).mean(0)
    np.testing.assert_allclose(mom.M[0].double().cpu().numpy(), Mref, atol=atol)
    # the line fit minimizes Lᵀ M L / Lᵀ N L, which is 0 on the exact line
    G = mesh.bary_gradients()[0].double().cpu().numpy()
    ratio = (Lref @ Mref @ Lref) / (Lref @ (G @ G.T) @ Lref)
    assert ratio < 1e-12


@pytest.mark.parametrize("d", [0.01, 0.03])
def test_line_fit_points_off_line_give_d_squared(d, device, dtype):
    mesh = one_triangle(device, dtype)
    c = np.array([1.3 / 3, 0.3])
    th = -0.7
    u = np.array([math.cos(th), math.sin(th)])
    n = np.array([-math.sin(th), math.cos(th)])
    s = np.linspace(-0.15, 0.15, 12)
    p = np.concatenate([c + s[:, None] * u + d * n, c + s[:, None] * u - d * n])
    pts = torch.tensor(p, device=device, dtype=dtype)
    _, face, bary = locate_single(mesh, pts)
    assert (face == 0).all()
    mom = triangle_moments(mesh, pts, face, bary)
    L, eps, normal = line_fits(mesh, mom)
    rtol = 1e-4 if dtype == torch.float32 else 1e-10
    np.testing.assert_allclose(float(eps[0]), d * d, rtol=rtol)
    V = np.array([[0.0, 0.0], [1.0, 0.0], [0.3, 0.9]])
    Lref = (V - c) @ n
    Lg = L[0].double().cpu().numpy()
    np.testing.assert_allclose(np.sign(Lg @ Lref) * Lg, Lref, atol=1e-5 if dtype == torch.float32 else 1e-12)


def test_line_fit_against_numpy_eigh(device):
    """Random points in many triangles: eps = smallest eigenvalue of the population covariance."""
    dtype = torch.float64
    mesh = hexagons(2, 3, device, dtype)
    g = torch.Generator().manual_seed(3)
    pts = torch.cat([disc_points(300, 0.85, g), disc_points(200, 0.85, g, center=(3.0, 0.0))]).to(device)
    item = torch.cat([torch.zeros(300, dtype=torch.long), torch.ones(200, dtype=torch.long)]).to(device)
    face, bary = locate_grid(mesh, pts, item)
    assert (face >= 0).all()
    mom = triangle_moments(mesh, pts, face, bary)
    L, eps, normal = line_fits(mesh, mom)
    P = pts.cpu().numpy()
    fc = face.cpu().numpy()
    V = mesh.verts.cpu().numpy()
    F = mesh.faces.cpu().numpy()
    checked = 0
    for t in range(F.shape[0]):
        q = P[fc == t]
        assert int(mom.count[t]) == len(q)
        if len(q) < 3:
            continue
        C = np.cov(q.T, bias=True)
        w, vec = np.linalg.eigh(C)
        np.testing.assert_allclose(float(eps[t]), w[0], rtol=1e-9, atol=1e-15)
        Lref = (V[F[t]] - q.mean(0)) @ vec[:, 0]
        Lg = L[t].cpu().numpy()
        np.testing.assert_allclose(np.sign(Lg @ Lref) * Lg, Lref, atol=1e-9)
        checked += 1
    assert checked > 30


def test_pooled_moments_equal_union_of_points(device, dtype):
    mesh = hexagons(2, 3, device, dtype)
    g = torch.Generator().manual_seed(5)
    # a cluster so that some triangles are empty, some have one point
    pts = torch.cat([disc_points(150, 0.6, g, center=(0.2, 0.1)), disc_points(7, 0.85, g),
                     disc_points(90, 0.5, g, center=(3.0, -0.2))]).to(device=device, dtype=dtype)
    item = torch.cat([torch.zeros(157, dtype=torch.long), torch.ones(90, dtype=torch.long)]).to(device)
    face, bary = locate_grid(mesh, pts, item)
    assert (face >= 0).all()
    mom = triangle_moments(mesh, pts, face, bary)
    pooled = pooled_moments(mesh, mom)
    # neighbours found independently: triangles sharing two vertices
    F = mesh.faces.cpu().tolist()
    by_edge = defaultdict(list)
    for t, tri in enumerate(F):
        for a in range(3):
            i, j = tri[a], tri[(a + 1) % 3]
            by_edge[(min(i, j), max(i, j))].append(t)
    nbrs = defaultdict(set)
    for ts in by_edge.values():
        for a in ts:
            nbrs[a].update(x for x in ts if x != a)
    P = pts.double().cpu().numpy()
    fc = face.cpu().numpy()
    atol = 1e-5 if dtype == torch.float32 else 1e-12
    n_multi = 0
    for t in range(len(F)):
        group = [t] + sorted(nbrs[t])
        assert len(group) <= 4
        q = P[np.isin(fc, group)]
        assert float(pooled.count[t]) == len(q)
        if len(q) == 0:
            continue
        np.testing.assert_allclose(pooled.centroid[t].double().cpu().numpy(), q.mean(0), atol=atol)
        C = np.cov(q.T, bias=True) if len(q) > 1 else np.zeros((2, 2))
        np.testing.assert_allclose(pooled.scatter[t].double().cpu().numpy(), C, atol=atol)
        n_multi += len(set(fc[np.isin(fc, group)].tolist())) > 1
    assert n_multi > 20
    # M is the per-triangle moment, not pooled
    assert torch.equal(pooled.M, mom.M)


# ============================================================================= edge weights


def naive_edge_weights(mesh, L, w, empty):
    """H_e = -Σ_{t ∋ e} σ_{t,i} σ_{t,j} w_t by a loop (eq. 3.6); empty triangles: σ = +1."""
    idx = edge_index(mesh)
    H = [0.0] * len(idx)
    for t, tri in enumerate(mesh.faces.cpu().tolist()):
        sig = [1.0, 1.0, 1.0] if empty[t] else [1.0 if float(x) >= 0 else -1.0 for x in L[t]]
        for a in range(3):
            b = (a + 1) % 3
            i, j = tri[a], tri[b]
            H[idx[(min(i, j), max(i, j))]] += -sig[a] * sig[b] * w[t]
    return torch.tensor(H, dtype=torch.float64)


def test_edge_weights_hand_values(device, dtype):
    mesh = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 1)
    assert mesh.faces.shape[0] == 6
    L = torch.tensor([[1.0, -2.0, 0.5], [-1.0, -1.0, 3.0], [0.2, 0.3, -0.1],
                      [1.0, -1.0, 1.0], [-1.0, 1.0, 1.0], [0.0, 0.0, 0.0]], device=device, dtype=dtype)
    eps = torch.tensor([0.1, 0.3, 0.5, 0.0, 0.0, 0.0], device=device, dtype=dtype)
    # triangles 0-2 fitted (eps 0.1, 0.3, 0.5 -> w = 1, 0.5, 0); 3 and 4 hold 2 and 1 points: no
    # evidence; 5 is empty: L = (1,1,1) with the empty weight
    count = torch.tensor([10.0, 4.0, 3.0, 2.0, 1.0, 0.0], device=device, dtype=dtype)
    H = edge_weights(mesh, L, eps, count, min_points=3, empty_weight=0.7)
    w = [1.0, 0.5, 0.0, 0.0, 0.0, 0.7]
    ref = naive_edge_weights(mesh, L.cpu().tolist(), w, [False] * 5 + [True])
    np.testing.assert_allclose(H.double().cpu().numpy(), ref.numpy(), atol=1e-6)
    # an edge of triangle 3 or 4 only (boundary) carries nothing; one of triangle 5 only carries -0.7
    idx = edge_index(mesh)
    F = mesh.faces.cpu().tolist()
    owners = defaultdict(list)
    for t, tri in enumerate(F):
        for a in range(3):
            i, j = tri[a], tri[(a + 1) % 3]
            owners[idx[(min(i, j), max(i, j))]].append(t)
    for e, ts in owners.items():
        if set(ts) <= {3, 4}:
            assert float(H[e]) == 0.0
        if ts == [5]:
            assert float(H[e]) == pytest.approx(-0.7)
    # pooled support: a triangle with no point of its own but a fitted neighbourhood is not empty
    pooled = torch.tensor([10.0, 4.0, 3.0, 2.0, 1.0, 5.0], device=device, dtype=dtype)
    H2 = edge_weights(mesh, L, eps, count, 3, 0.7, pooled_count=pooled)
    # eps 0 joins the fitted set: w = (0.5 - eps)/0.5 -> 0.8, 0.4, 0, 1
    ref2 = naive_edge_weights(mesh, L.cpu().tolist(), [0.8, 0.4, 0.0, 0.0, 0.0, 1.0], [False] * 6)
    np.testing.assert_allclose(H2.double().cpu().numpy(), ref2.numpy(), atol=1e-6)


def test_edge_weights_equal_weights_when_all_errors_equal(device):
    mesh = hexagon_mesh(torch.zeros(1, 2, device=device), torch.ones(1, device=device), 1)
    L = torch.tensor([[1.0, -1.0, 1.0]] * 6, device=device)
    eps = torch.full((6,), 0.25, device=device)
    count = torch.full((6,), 5.0, device=device)
    H = edge_weights(mesh, L, eps, count, 3, 1.0)
    ref = naive_edge_weights(mesh, L.cpu().tolist(), [1.0] * 6, [False] * 6)
    np.testing.assert_allclose(H.cpu().numpy(), ref.numpy(), atol=1e-6)


def test_edge_weights_on_a_data_line(device):
    """Crossed edges attract opposite signs (H > 0); far empty edges want equal signs."""
    dtype = torch.float64
    mesh = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 4)
    g = torch.Generator().manual_seed(11)
    x = torch.linspace(-0.6, 0.6, 240, dtype=dtype)
    y = 0.1 + 0.05 * x + 0.004 * torch.randn(240, generator=g, dtype=dtype)
    pts = torch.stack([x, y], 1).to(device)
    _, face, bary = locate_single(mesh, pts)
    assert (face >= 0).all()
    mom = triangle_moments(mesh, pts, face, bary)
    L, eps, _ = line_fits(mesh, mom)
    H = edge_weights(mesh, L, eps, mom.count, min_points=3, empty_weight=0.8)
    # independent: numpy line fits, weights by hand, naive edge sums
    P, fc = pts.cpu().numpy(), face.cpu().numpy()
    V, F = mesh.verts.cpu().numpy(), mesh.faces.cpu().numpy()
    Lref, epsref, fit, empty = [], [], [], []
    for t in range(F.shape[0]):
        q = P[fc == t]
        empty.append(len(q) == 0)
        fit.append(len(q) >= 3)
        if len(q) >= 3:
            wv, vec = np.linalg.eigh(np.cov(q.T, bias=True))
            Lref.append(((V[F[t]] - q.mean(0)) @ vec[:, 0]).tolist())
            epsref.append(wv[0])
        else:
            Lref.append([1.0, 1.0, 1.0])
            epsref.append(0.0)
    e_fit = [e for e, f in zip(epsref, fit) if f]
    emax, emin = max(e_fit), min(e_fit)
    w = [(emax - e) / (emax - emin) if f else (0.8 if em else 0.0) for e, f, em in zip(epsref, fit, empty)]
    ref = naive_edge_weights(mesh, Lref, w, empty)
    np.testing.assert_allclose(H.cpu().numpy(), ref.numpy(), atol=1e-7)
    # qualitative: an edge whose two triangles hold the line and whose ends lie on opposite
    # sides of it gets H > 0; an edge of empty triangles only gets -0.8 per triangle
    idx = edge_index(mesh)
    owners = defaultdict(list)
    for t, tri in enumerate(F.tolist()):
        for a in range(3):
            i, j = tri[a], tri[(a + 1) % 3]
            owners[idx[(min(i, j), max(i, j))]].append(t)
    cnt = mom.count.cpu().numpy()
    n_cross = n_far = 0
    for e, ts in owners.items():
        i, j = mesh.edges[e].tolist()
        side_i = V[i, 1] - (0.1 + 0.05 * V[i, 0])
        side_j = V[j, 1] - (0.1 + 0.05 * V[j, 0])
        if side_i * side_j < 0 and len(ts) == 2 and all(cnt[t] >= 10 for t in ts):
            assert float(H[e]) > 0
            n_cross += 1
        if all(cnt[t] == 0 for t in ts):
            assert float(H[e]) == pytest.approx(-0.8 * len(ts), abs=1e-12)
            n_far += 1
    assert n_cross >= 5 and n_far >= 20


def test_edge_weights_per_item_extremes(device):
    """w uses the extremes of each item: the same item alone and in a batch gives the same H."""
    m1 = hexagon_mesh(torch.zeros(1, 2, device=device), torch.ones(1, device=device), 1)
    m2 = MeshBatch.cat([m1, m1])
    L = torch.tensor([[1.0, -2.0, 0.5], [-1.0, -1.0, 3.0], [0.2, 0.3, -0.1],
                      [1.0, -1.0, 1.0], [-1.0, 1.0, 1.0], [0.5, 0.5, -1.0]], device=device)
    eps1 = torch.tensor([0.1, 0.3, 0.5, 0.2, 0.4, 0.05], device=device)
    eps2 = eps1 * 100
    count = torch.full((6,), 5.0, device=device)
    Ha = edge_weights(m1, L, eps1, count, 3, 1.0)
    Hb = edge_weights(m1, L, eps2, count, 3, 1.0)
    H2 = edge_weights(m2, torch.cat([L, L]), torch.cat([eps1, eps2]), torch.cat([count, count]), 3, 1.0)
    E = Ha.shape[0]
    torch.testing.assert_close(H2[:E], Ha)
    torch.testing.assert_close(H2[E:], Hb)


# ============================================================================= Ising model


def naive_ising(mesh, H, s):
    E = [0.0] * mesh.num_items
    for k, (i, j) in enumerate(mesh.edges.cpu().tolist()):
        E[int(mesh.vert_item[i])] += float(H[k]) * float(s[i]) * float(s[j])
    return E


def brute_force_min(mesh_b, H_b, init_b, fixed_b):
    free = (~fixed_b).nonzero().squeeze(1)
    n = free.shape[0]
    assert n <= 16
    codes = torch.arange(2 ** n, device=H_b.device)
    bits = (codes[None, :] >> torch.arange(n, device=H_b.device)[:, None]) & 1      # (n, R)
    S = init_b.to(H_b.dtype)[:, None].repeat(1, 2 ** n)
    S[free] = (2 * bits - 1).to(H_b.dtype)
    E = ising_energy(mesh_b, H_b, S)[0]
    return float(E.min())


def test_ising_energy_against_loop(device):
    mesh = MeshBatch.cat([hexagons(1, 2, device, torch.float64), square_mesh(
        torch.zeros(1, 2, device=device, dtype=torch.float64), torch.ones(1, device=device, dtype=torch.float64), 3)])
    g = torch.Generator().manual_seed(2)
    H = (torch.rand(mesh.edges.shape[0], generator=g, dtype=torch.float64) * 2 - 1).to(device)
    s = torch.where(torch.rand(mesh.verts.shape[0], generator=g) < 0.5, -1.0, 1.0).to(device=device,
                                                                                      dtype=torch.float64)
    E = ising_energy(mesh, H, s)
    np.testing.assert_allclose(E.cpu().numpy(), naive_ising(mesh, H.cpu(), s.cpu()), rtol=1e-12)
    E2 = ising_energy(mesh, H, torch.stack([s, -s, torch.ones_like(s)], 1))
    np.testing.assert_allclose(E2[:, 0].cpu().numpy(), E.cpu().numpy(), rtol=1e-12)
    np.testing.assert_allclose(E2[:, 1].cpu().numpy(), E.cpu().numpy(), rtol=1e-12)   # global flip
    np.testing.assert_allclose(E2[:, 2].cpu().numpy(), naive_ising(mesh, H.cpu(), torch.ones_like(s).cpu()),
                               rtol=1e-12)


def _ising_cases(device):
    dt = torch.float64
    z = lambda B: torch.zeros(B, 2, device=device, dtype=dt)          # noqa: E731
    o = lambda B: torch.ones(B, device=device, dtype=dt)               # noqa: E731
    return [
        ("square3_free", square_mesh(z(3), o(3), 3), "none"),          # 16 free vertices
        ("hex2_boundary", hexagon_mesh(z(3), o(3), 2), "boundary"),    # 7 free vertices
        ("square4_boundary", square_mesh(z(3), o(3), 4), "boundary"),  # 9 free vertices
        ("hex1_free", hexagon_mesh(z(2), o(2), 1), "none"),             # 7 free vertices
    ]


@pytest.mark.parametrize("case", range(4))
@pytest.mark.parametrize("hseed", [0, 1, 2, 3])
def test_anneal_finds_exact_minimum(case, hseed, device):
    name, mesh, fix = _ising_cases(device)[case]
    g = torch.Generator().manual_seed(100 * case + hseed)
    H = (torch.rand(mesh.edges.shape[0], generator=g, dtype=torch.float64) * 2 - 1).to(device)
    V = mesh.verts.shape[0]
    fixed = mesh.is_boundary_vert.clone() if fix == "boundary" else torch.zeros(V, dtype=torch.bool, device=device)
    init = torch.where(torch.rand(V, generator=g) < 0.5, -1.0, 1.0).to(device=device, dtype=torch.float64)
    # 16 replicas: with the default 4, a replica can freeze into a near-degenerate local minimum
    # of these frustrated (spin-glass) problems
    s = anneal(mesh, H, init, fixed, TopologyConfig(anneal_sweeps=150, anneal_replicas=16), seed=7)
    assert set(s.unique().cpu().tolist()) <= {-1.0, 1.0}
    assert torch.equal(s[fixed], init[fixed])
    E = ising_energy(mesh, H, s)
    for b in range(mesh.num_items):
        v0, nv = int(mesh.verts_first_idx[b]), int(mesh.verts_per_item[b])
        e0 = int(torch.cumsum(mesh.edges_per_item, 0)[b] - mesh.edges_per_item[b])
        ne = int(mesh.edges_per_item[b])
        mb = mesh[b]
        assert torch.equal(mb.edges + v0, mesh.edges[e0:e0 + ne])
        Emin = brute_force_min(mb, H[e0:e0 + ne], init[v0:v0 + nv], fixed[v0:v0 + nv])
        assert float(E[b]) == pytest.approx(Emin, abs=1e-9), (name, b)


def test_anneal_fixed_determinism_and_ferromagnet(device):
    mesh = hexagons(2, 3, device, torch.float32)
    V = mesh.verts.shape[0]
    g = torch.Generator().manual_seed(4)
    H = (torch.rand(mesh.edges.shape[0], generator=g) * 2 - 1).to(device)
    fixed = mesh.is_boundary_vert | (torch.rand(V, generator=g) < 0.2).to(device)
    init = torch.where(torch.rand(V, generator=g) < 0.5, -1.0, 1.0).to(device)
    a = anneal(mesh, H, init, fixed, TopologyConfig(anneal_sweeps=60, anneal_replicas=3), seed=5)
    b = anneal(mesh, H, init, fixed, TopologyConfig(anneal_sweeps=60, anneal_replicas=3), seed=5)
    assert torch.equal(a, b)
    assert torch.equal(a[fixed], init[fixed])
    # warm start keeps fixed values too
    c = anneal(mesh, H, init, fixed, TopologyConfig(anneal_sweeps=60, anneal_replicas=3), seed=5, warm=True)
    assert torch.equal(c[fixed], init[fixed])
    # ferromagnet, boundary held at +1: the unique ground state is all +1 (from a random start)
    Hf = -(0.1 + torch.rand(mesh.edges.shape[0], generator=g)).to(device)
    init2 = torch.where(mesh.is_boundary_vert, 1.0, init)
    s = anneal(mesh, Hf, init2, mesh.is_boundary_vert, TopologyConfig(anneal_sweeps=60, anneal_replicas=2), seed=1)
    assert torch.equal(s, torch.ones_like(s))


def test_anneal_batch_independent(device):
    """An item's stream depends on its own keys: alone or in a batch, the same signs."""
    one = hexagons(1, 3, device, torch.float64)
    batch = MeshBatch.cat([hexagons(1, 2, device, torch.float64), one, hexagons(1, 4, device, torch.float64)])
    g = torch.Generator().manual_seed(9)
    H = (torch.rand(batch.edges.shape[0], generator=g, dtype=torch.float64) * 2 - 1).to(device)
    e0, ne = int(batch.edges_per_item[0]), int(batch.edges_per_item[1])
    v0, nv = int(batch.verts_per_item[0]), int(batch.verts_per_item[1])
    init = torch.ones(batch.verts.shape[0], dtype=torch.float64, device=device)
    fixed = batch.is_boundary_vert
    s_b = anneal(batch, H, init, fixed, TopologyConfig(anneal_sweeps=40, anneal_replicas=3), seed=2)
    s_1 = anneal(one, H[e0:e0 + ne], init[v0:v0 + nv], fixed[v0:v0 + nv], TopologyConfig(anneal_sweeps=40, anneal_replicas=3), seed=2)
    assert torch.equal(s_b[v0:v0 + nv], s_1)


def islands_by_bfs(mesh, signs):
    """Same-sign regions by breadth-first search over the edges (Python)."""
    V = signs.shape[0]
    nb = [[] for _ in range(V)]
    for a, b in mesh.edges.cpu().tolist():
        nb[a].append(b)
        nb[b].append(a)
    neg = (signs < 0).cpu().tolist()
    lab = [-1] * V
    for v in range(V):
        if lab[v] >= 0:
            continue
        lab[v], todo = v, [v]
        while todo:
            u = todo.pop()
            for w in nb[u]:
                if lab[w] < 0 and neg[w] == neg[v]:
                    lab[w] = v
                    todo.append(w)
    return lab


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sign_islands_and_their_removal_against_bfs(seed, device):
    mesh = hexagons(2, 6, device, torch.float64)
    g = torch.Generator().manual_seed(seed)
    signs = torch.where(torch.rand(mesh.verts.shape[0], generator=g) < 0.4, -1.0, 1.0).double().to(device)
    lab = sign_islands(mesh, signs).cpu().tolist()
    ref = islands_by_bfs(mesh, signs)
    assert lab == ref                                   # both label a region by its smallest vertex
    fixed = mesh.is_boundary_vert
    for k in (2, 3):
        out = remove_small_islands(mesh, signs, fixed, k).cpu()
        size = {r: ref.count(r) for r in set(ref)}
        pinned = {ref[v] for v in fixed.nonzero().squeeze(1).cpu().tolist()}
        want = [-float(x) if size[r] < k and r not in pinned else float(x)
                for x, r in zip(signs.cpu().tolist(), ref)]
        assert out.tolist() == want
        assert any(size[r] < k and r not in pinned for r in ref)     # the rule really fired
    assert torch.equal(remove_small_islands(mesh, signs, fixed, 0), signs)


@pytest.mark.parametrize("active_frac", [1.0, 0.6])
def test_vertex_coloring_proper(active_frac, device):
    mesh = MeshBatch.cat([hexagons(2, 4, device, torch.float32),
                          square_mesh(torch.zeros(1, 2, device=device), torch.ones(1, device=device), 5)])
    V = mesh.verts.shape[0]
    g = torch.Generator().manual_seed(1)
    active = (torch.rand(V, generator=g) < active_frac).to(device)
    col = vertex_coloring(mesh, None if active_frac == 1.0 else active)
    if active_frac == 1.0:
        active = torch.ones(V, dtype=torch.bool, device=device)
    assert (col[active] >= 0).all()
    assert (col[~active] == -1).all()
    for i, j in mesh.edges.cpu().tolist():
        if bool(active[i]) and bool(active[j]):
            assert int(col[i]) != int(col[j])
    # greedy: a vertex's colour is at most its degree
    assert (col[active] <= mesh.degrees[active]).all()


def test_hash_uniform():
    n = 100_000
    k = torch.arange(n)
    u = hash_uniform(torch.full((n,), 3), k, torch.full((n,), 17), dtype=torch.float64)
    assert float(u.min()) > 0 and float(u.max()) < 1
    assert abs(float(u.mean()) - 0.5) < 0.005
    assert abs(float(u.var()) - 1 / 12) < 0.003
    hist = torch.histc(u, bins=10, min=0, max=1)
    assert float((hist - n / 10).abs().max()) < 0.05 * n / 10
    # deterministic, and elementwise (a value depends only on its own keys)
    u2 = hash_uniform(torch.full((n,), 3), k, torch.full((n,), 17), dtype=torch.float64)
    assert torch.equal(u, u2)
    sub = hash_uniform(torch.full((10,), 3), k[500:510], torch.full((10,), 17), dtype=torch.float64)
    assert torch.equal(sub, u[500:510])
    # a different key gives a different stream (not merely shifted)
    v = hash_uniform(torch.full((n,), 4), k, torch.full((n,), 17), dtype=torch.float64)
    assert float((u == v).double().mean()) < 1e-3
    assert abs(float(torch.corrcoef(torch.stack([u, v]))[0, 1])) < 0.02
    assert abs(float(torch.corrcoef(torch.stack([u[:-1], u[1:]]))[0, 1])) < 0.02
    f32 = hash_uniform(torch.full((n,), 3), k, torch.full((n,), 17))
    assert f32.dtype == torch.float32 and float(f32.min()) > 0 and float(f32.max()) < 1


def _preimage_of_hash(h):
    """A key k with hash_uniform(k) built on the 32-bit hash value h: the lowbias32-like mix is a
    bijection (xorshifts and odd multipliers mod 2^32), inverted here step by step."""
    m = 0xFFFFFFFF

    def unxorshift(y, s):
        x = y
        for _ in range(32 // s + 1):
            x = y ^ (x >> s)
        return x & m

    x = unxorshift(h, 16)
    x = x * pow(0x846CA68B, -1, 2 ** 32) & m
    x = unxorshift(x, 15)
    x = x * pow(0x7FEB352D, -1, 2 ** 32) & m
    x = unxorshift(x, 16)
    return (x - 0x632BE5AB) & m          # one key: h = mix(0 * C + k + 0x632BE5AB)


def test_hash_uniform_extremes_float64():
    lo, hi = _preimage_of_hash(0), _preimage_of_hash(0xFFFFFFFF)
    u = hash_uniform(torch.tensor([lo, hi]), dtype=torch.float64)
    assert float(u[0]) == 0.5 / 2 ** 32
    assert float(u[1]) == 1 - 0.5 / 2 ** 32


def test_hash_uniform_float32_stays_below_one():
    hi = _preimage_of_hash(0xFFFFFFFF)
    u = hash_uniform(torch.tensor([hi, _preimage_of_hash(0xFFFFFFFF - 5)]), dtype=torch.float32)
    assert float(u.max()) < 1.0


# ============================================================================= batched L-BFGS


class Problems:
    """A sum of independent per-segment problems packed in one vector."""

    def __init__(self, specs, device):
        self.specs = specs
        self.sizes = [s["x0"].shape[0] for s in specs]
        self.seg = torch.repeat_interleave(torch.arange(len(specs)), torch.tensor(self.sizes)).to(device)
        self.x0 = torch.cat([s["x0"] for s in specs]).to(device)
        self.device = device

    def __call__(self, x):
        out, o = [], 0
        for s, n in zip(self.specs, self.sizes):
            xs = x[o:o + n]
            o += n
            if s["kind"] == "quad":
                out.append((s["a"].to(x) * (xs - s["c"].to(x)) ** 2).sum())
            else:
                a, b = s["ab"]
                out.append(s["scale"] * ((a - xs[0]) ** 2 + b * (xs[1] - xs[0] ** 2) ** 2))
        return torch.stack(out)


def _lbfgs_specs():
    d = torch.float64
    return [
        {"kind": "quad", "x0": torch.zeros(3, dtype=d), "a": torch.tensor([1e-2, 1.0, 1e2], dtype=d),
         "c": torch.tensor([1.0, -2.0, 3.0], dtype=d), "xmin": torch.tensor([1.0, -2.0, 3.0], dtype=d)},
        {"kind": "rosen", "x0": torch.tensor([-1.2, 1.0], dtype=d), "ab": (1.0, 100.0), "scale": 1.0,
         "xmin": torch.tensor([1.0, 1.0], dtype=d)},
        {"kind": "quad", "x0": torch.full((5,), 10.0, dtype=d), "a": torch.tensor([1e-4, 2e-4, 5e-4, 1e-3, 3e-4], dtype=d),
         "c": torch.tensor([0.5, 0.1, -0.3, 7.0, 2.0], dtype=d), "xmin": torch.tensor([0.5, 0.1, -0.3, 7.0, 2.0], dtype=d)},
        {"kind": "rosen", "x0": torch.tensor([0.0, 2.0], dtype=d), "ab": (2.0, 10.0), "scale": 1e3,
         "xmin": torch.tensor([2.0, 4.0], dtype=d)},
        {"kind": "quad", "x0": torch.tensor([3.0], dtype=d), "a": torch.tensor([1e4], dtype=d),
         "c": torch.tensor([-1e-3], dtype=d), "xmin": torch.tensor([-1e-3], dtype=d)},
    ]


def test_batched_lbfgs_converges_per_segment_and_is_batch_independent(device):
    specs = _lbfgs_specs()
    prob = Problems(specs, device)
    x, f, iters = batched_lbfgs(prob, prob.x0, prob.seg, len(specs), iterations=300, history=8, rel_tol=1e-14)
    o = 0
    for k, s in enumerate(specs):
        n = s["x0"].shape[0]
        np.testing.assert_allclose(x[o:o + n].cpu().numpy(), s["xmin"].numpy(), rtol=1e-5, atol=1e-5,
                                   err_msg=f"segment {k}")
        assert float(f[k]) < 1e-9 * max(1.0, float(prob(prob.x0)[k]))
        # the same problem alone follows exactly the same trajectory
        alone = Problems([s], device)
        xa, fa, ia = batched_lbfgs(alone, alone.x0, alone.seg, 1, iterations=300, history=8, rel_tol=1e-14)
        assert torch.equal(xa, x[o:o + n]), f"segment {k} depends on its batch"
        assert torch.equal(fa[0], f[k]) and int(ia[0]) == int(iters[k])
        o += n
    # the returned objective is the objective at the returned point
    torch.testing.assert_close(prob(x), f)


def test_batched_lbfgs_order_of_segments_irrelevant(device):
    specs = _lbfgs_specs()
    a = Problems(specs, device)
    b = Problems(specs[::-1], device)
    xa, fa, _ = batched_lbfgs(a, a.x0, a.seg, len(specs), iterations=40)
    xb, fb, _ = batched_lbfgs(b, b.x0, b.seg, len(specs), iterations=40)
    assert torch.equal(fa, fb.flip(0))
    ob = 0
    parts_b = []
    for s in specs[::-1]:
        n = s["x0"].shape[0]
        parts_b.append(xb[ob:ob + n])
        ob += n
    assert torch.equal(xa, torch.cat(parts_b[::-1]))


def test_batched_lbfgs_iteration_cap_and_monotone(device):
    specs = _lbfgs_specs()
    prob = Problems(specs, device)
    f0 = prob(prob.x0)
    prev = f0
    for it in (1, 3, 10):
        x, f, iters = batched_lbfgs(prob, prob.x0, prob.seg, len(specs), iterations=it)
        assert (iters <= it).all()
        assert (f <= prev + 1e-15).all()          # a longer run never ends higher (monotone descent)
        prev = f


def _two_loop_reference(g, pairs, gamma):
    """The textbook two-loop recursion (Nocedal & Wright, Alg. 7.4) for one segment, in
    float64; pairs with ``s·y <= 0`` are skipped."""
    q = g.clone()
    alphas = []
    for s, y in reversed(pairs):
        sy = float(s @ y)
        a = (s @ q) / sy if sy > 0 else 0.0
        alphas.append(a)
        q = q - a * y
    r = gamma * q
    for (s, y), a in zip(pairs, reversed(alphas)):
        sy = float(s @ y)
        b = (y @ r) / sy if sy > 0 else 0.0
        r = r + (a - b) * s
    return r


def test_compact_lbfgs_direction_matches_two_loop(device):
    """The compact form gives the two-loop direction, per segment, with skipped (zero) pairs."""
    from torch_isc.pipeline.optim import _neg_direction, _segmat
    gen = torch.Generator().manual_seed(3)
    sizes, k = [5, 3, 7], 4
    seg = torch.repeat_interleave(torch.arange(3), torch.tensor(sizes))
    n = seg.shape[0]
    S = torch.randn(k, n, generator=gen, dtype=torch.float64)
    Y = torch.zeros_like(S)
    o = 0
    for m in sizes:                        # y = A s with A positive definite per segment
        A = torch.randn(m, m, generator=gen, dtype=torch.float64)
        A = A @ A.T + m * torch.eye(m, dtype=torch.float64)
        Y[:, o:o + m] = S[:, o:o + m] @ A
        o += m
    S[1, 5:8] = 0.0                        # segment 1 skipped its second pair
    Y[1, 5:8] = 0.0
    g = torch.randn(n, generator=gen, dtype=torch.float64)
    gamma = torch.tensor([0.3, 2.0, 1.0], dtype=torch.float64)
    SY = torch.stack([_segmat(Y, S[i], seg, 3) for i in range(k)], 1)      # [b, i, j] = s_i . y_j
    YY = torch.stack([_segmat(Y, Y[i], seg, 3) for i in range(k)], 1)
    # the stored convention: a skipped (zero) pair carries a unit s·y diagonal
    SY = SY + torch.diag_embed((torch.diagonal(SY, dim1=1, dim2=2) == 0).double())
    assert float(SY[1, 1, 1]) == 1.0
    H, Q = torch.stack([S, Y]).to(device), torch.stack([SY, YY], 1).to(device)
    gd, sd = gamma.to(device), seg.to(device)
    r = -_neg_direction(g.to(device), -g.to(device) * gd[sd], H, Q, gd, sd, 3).cpu()
    o = 0
    for b, m in enumerate(sizes):
        sl = slice(o, o + m)
        ref = _two_loop_reference(g[sl], [(S[i, sl], Y[i, sl]) for i in range(k)], float(gamma[b]))
        torch.testing.assert_close(r[sl], ref, rtol=1e-10, atol=1e-12)
        o += m


class StackedProblems:
    """:class:`Problems` evaluated row by row of ``X (K, n)`` (stacked), with ``restrict``."""

    def __init__(self, specs, device):
        self.specs, self.device, self.prob = specs, device, Problems(specs, device)
        self.calls = 0

    def __call__(self, X):
        self.calls += 1
        return torch.stack([self.prob(x) for x in X])

    def restrict(self, items):
        sub = StackedProblems([s for s, k in zip(self.specs, items.tolist()) if k], self.device)
        sub.calls = self.calls
        return sub, sub.restrict


@pytest.mark.parametrize("history", [2, 8])
def test_line_search_layout_does_not_change_trajectories(history, device):
    """Trials per stacked call, host reads every few rounds and compaction of the working set
    change only how the work is laid out: every trajectory is bit-identical to one trial per
    round (the sequential halving search), and to each problem solved alone."""
    specs = _lbfgs_specs()
    prob = Problems(specs, device)
    ref = batched_lbfgs(prob, prob.x0, prob.seg, len(specs), iterations=60, history=history, trials=1, check_every=1,
                        tail_entries=0)
    n = prob.x0.shape[0]
    # tail: more trials per call once the working set is small (never, from the start, or once
    # compaction has taken it below half of its entries)
    for trials, check_every, tail in [(2, 4, 0), (3, 1, 0), (5, 7, 0), (12, 3, 0), (1, 4, n), (1, 2, n // 2),
                                      (2, 3, n // 2)]:
        got = batched_lbfgs(prob, prob.x0, prob.seg, len(specs), iterations=60, history=history, trials=trials,
                            check_every=check_every, tail_entries=tail)
        assert all(torch.equal(u, v) for u, v in zip(ref, got)), (trials, check_every, tail)
        st = StackedProblems(specs, device)
        got = batched_lbfgs(st, prob.x0, prob.seg, len(specs), iterations=60, history=history, trials=trials,
                            check_every=check_every, stacked=True, restrict=st.restrict, tail_entries=tail)
        assert all(torch.equal(u, v) for u, v in zip(ref, got)), ("stacked, compacted", trials, check_every, tail)
    # the iterations differ per problem, so compaction really happened
    assert len(set(ref[2].tolist())) > 2
    o = 0
    for k, sp in enumerate(specs):
        n = sp["x0"].shape[0]
        alone = Problems([sp], device)
        xa, fa, ia = batched_lbfgs(alone, alone.x0, alone.seg, 1, iterations=60, history=history, trials=3)
        assert torch.equal(xa, ref[0][o:o + n]) and torch.equal(fa[0], ref[1][k]) and int(ia[0]) == int(ref[2][k])
        o += n


def test_line_search_host_reads_bounded(device):
    """Once the history has filled, a round has no host read: reads come only every
    ``check_every`` rounds (counted at the dispatcher: item/bool/nonzero)."""
    from torch.utils._python_dispatch import TorchDispatchMode
    reads = []

    class Count(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func in (torch.ops.aten._local_scalar_dense.default, torch.ops.aten.nonzero.default):
                reads.append(func)
            return func(*args, **(kwargs or {}))

    specs = _lbfgs_specs()
    prob = Problems(specs, device)
    st = StackedProblems(specs, device)
    history, trials, every = 2, 2, 5
    with Count():
        batched_lbfgs(st, prob.x0, prob.seg, len(specs), iterations=60, history=history, trials=trials,
                      check_every=every, stacked=True, tail_entries=0)
    rounds = st.calls - 1
    # the lockstep rounds read once per block of trials at most; later ones once per check
    bound = history * (1 + 12 // trials) + (rounds - history) // every + 1
    assert rounds > 40 and len(reads) <= bound


def test_true_indices_are_the_true_positions(device):
    """The compaction's indices (count read beforehand): those of the True entries, ascending."""
    from torch_isc.pipeline.optim import true_indices
    m = torch.tensor([False, True, True, False, True], device=device)
    assert true_indices(m, 3).tolist() == [1, 2, 4]
    assert true_indices(m[:1], 0).shape == (0,) and true_indices(m[1:3], 2).tolist() == [0, 1]


def test_with_grad_objective_follows_the_autograd_trajectory(device):
    """``with_grad=True`` (the objective returns its own gradient) gives the trajectory of the
    autograd path when that gradient is the same."""
    specs = _lbfgs_specs()
    prob = Problems(specs, device)

    def own_grad(x):
        xx = x.detach().requires_grad_(True)
        with torch.enable_grad():
            f = prob(xx)
            g, = torch.autograd.grad(f.sum(), xx)
        return f.detach(), g

    xa, fa, ia = batched_lbfgs(prob, prob.x0, prob.seg, len(specs), iterations=60)
    xb, fb, ib = batched_lbfgs(own_grad, prob.x0, prob.seg, len(specs), iterations=60, with_grad=True)
    assert torch.equal(xa, xb) and torch.equal(fa, fb) and torch.equal(ia, ib)
    for sp, o, n in zip(specs, torch.cumsum(torch.tensor([0] + prob.sizes), 0).tolist(), prob.sizes):
        torch.testing.assert_close(xb[o:o + n].cpu(), sp["xmin"], rtol=1e-4, atol=1e-4)


# ============================================================================= geometry


def circle_setup(device, dtype, n=200, R=0.5, res=8):
    mesh = hexagons(1, res, device, dtype)
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n) + 0.1
    pts = (R * torch.stack([t.cos(), t.sin()], 1)).to(device=device, dtype=dtype)
    item, face, bary = locate_single(mesh, pts)
    assert (face >= 0).all()
    mom = triangle_moments(mesh, pts, face, bary)
    signs = torch.where(mesh.verts.norm(dim=1) < R, -1.0, 1.0).to(dtype)
    init = vertex_data_distance(mesh, pts, face)
    return mesh, pts, face, bary, mom, signs, init


def delta1_from_points(mesh, values, pts, face):
    """Δ1 as the mean over points of f(p)²/|∇f|² (float64, barycentrics by Cramer's rule)."""
    V = mesh.verts.double().cpu().numpy()
    Fc = mesh.faces.cpu().numpy()
    val = values.double().cpu().numpy()
    tot = 0.0
    P = pts.double().cpu().numpy()
    for p, t in zip(P, face.cpu().tolist()):
        tri = V[Fc[t]]
        X = np.array(ref_bary64(tri, p))
        fv = val[Fc[t]]
        f = X @ fv
        # gradient of the linear interpolant: solve [x y 1] a = f at the vertices
        A = np.c_[tri, np.ones(3)]
        a = np.linalg.solve(A, fv)
        tot += f * f / (a[0] ** 2 + a[1] ** 2)
    return tot / len(P)


def test_delta1_per_triangle_equals_point_mean(device):
    dtype = torch.float64
    mesh, pts, face, bary, mom, signs, init = circle_setup(device, dtype, n=120, res=4)
    g = torch.Generator().manual_seed(0)
    values = signs * (0.05 + torch.rand(signs.shape[0], generator=g, dtype=dtype).to(device))
    d = delta1_per_triangle(mesh, mom.M, values)
    total = float((d * mom.count).sum() / mom.count.sum())
    assert total == pytest.approx(delta1_from_points(mesh, values, pts, face), rel=1e-9)
    r = point_residuals(mesh, values, face, bary)
    assert float(r.mean()) == pytest.approx(total, rel=1e-9)


def two_circle_objective(device, smoothness, crossing_weight):
    """A GeometryObjective over a batch of two circle fits of different sizes (float64)."""
    return two_circle_objective_cfg(device, GeometryConfig(smoothness=smoothness, crossing_weight=crossing_weight),
                                    full=True)


def two_circle_objective_cfg(device, cfg, full=False):
    dtype = torch.float64
    m1, p1, _, _, _, s1, i1 = circle_setup(device, dtype, n=90, R=0.5, res=5)
    m2, p2, _, _, _, s2, i2 = circle_setup(device, dtype, n=60, R=0.3, res=4)
    mesh = MeshBatch.cat([m1, m2])
    pts = torch.cat([p1, p2])
    item = torch.cat([torch.zeros(90, dtype=torch.long), torch.ones(60, dtype=torch.long)]).to(device)
    face, bary = locate_grid(mesh, pts, item)
    mom = triangle_moments(mesh, pts, face, bary)
    near = vertex_data_distance_near(mesh, pts, face)
    tol = torch.tensor([0.01, 0.02], dtype=dtype, device=device)
    obj = GeometryObjective(mesh, mom, torch.cat([s1, s2]), torch.cat([i1, i2]), tol, cfg, near, 0.5 * tol)
    return (obj, mesh, pts, face, tol) if full else obj


@pytest.mark.parametrize("smoothness,crossing", [(0.0, 0.0), (1e-2, 0.0), (1e-2, 1.0), (0.3, 5.0)])
def test_geometry_objective_gradient_against_finite_differences(smoothness, crossing, device):
    """The hand-written gradient of the fit's objective equals central differences of the
    objective (float64), for the whole batch and for one item selected."""
    obj, mesh, *_ = two_circle_objective(device, smoothness, crossing)
    if crossing > 0:
        assert obj.cross                       # the crossing term is really in play
    g = torch.Generator().manual_seed(1)
    s = obj.s0 + 0.5 * torch.randn(obj.s0.shape, generator=g, dtype=torch.float64).to(device)
    f, grad = obj.value_and_grad(s)
    torch.testing.assert_close(f, obj.value(s), rtol=1e-12, atol=0)
    h = 1e-6
    idx = torch.randperm(s.shape[0], generator=g)[:40].to(device)
    for i in idx.tolist():
        e = torch.zeros_like(s)
        e[i] = h
        b = int(mesh.vert_item[i])
        fd = (obj.value(s + e)[b] - obj.value(s - e)[b]) / (2 * h)
        assert float(grad[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-7 * max(1.0, float(f[b])))
    # one item selected: its objective and gradient are bit-identical to the full evaluation's
    mine = mesh.vert_item == 1
    sub = obj.restrict(torch.tensor([False, True], device=device))
    f1, g1 = sub.value_and_grad(s[mine])
    assert f1.shape == (1,)
    assert_same(f1[0], f[1], rtol=1e-12, atol=0)
    assert_same(g1, grad[mine], rtol=1e-12, atol=1e-12)
    # several points in one stacked call: row by row the single evaluations
    S2 = torch.stack([s, obj.s0, s + 0.1])
    fs, gs = obj.value_and_grad(S2)
    torch.testing.assert_close(fs, obj.value(S2), rtol=1e-12, atol=0)
    for k in range(3):
        fk, gk = obj.value_and_grad(S2[k])
        assert_same(fs[k], fk, rtol=1e-12, atol=0)
        assert_same(gs[k], gk, rtol=1e-12, atol=1e-12)


def test_geometry_objective_is_delta1_over_tol2_without_extra_terms(device):
    """With no smoothness and no crossing term the objective is Δ1 / tol² per item, Δ1 taken
    as the mean over the points of f(p)²/|∇f|² (independent float64 reference)."""
    obj, mesh, pts, face, tol = two_circle_objective(device, 0.0, 0.0)
    g = torch.Generator().manual_seed(2)
    s = obj.s0 + 0.3 * torch.randn(obj.s0.shape, generator=g, dtype=torch.float64).to(device)
    f = obj.value(s)
    F = obj.values(s)
    item = mesh.face_item[face]
    for b in range(2):
        sub, vk, _ = mesh.select_items(torch.tensor([b], device=device))
        fb = face[item == b] - int(mesh.faces_first_idx[b])
        ref = delta1_from_points(sub, F[vk], pts[item == b], fb)
        assert float(f[b]) == pytest.approx(ref / float(tol[b]) ** 2, rel=1e-9)


@pytest.mark.parametrize("smoothness", [0.0, 0.3])
def test_gauss_newton_diagonal_against_autograd_hessian_of_frozen_surrogate(smoothness, device):
    """The preconditioner's diagonal equals the diagonal of the autograd Hessian (float64, in F)
    of an independent surrogate, built from the points rather than M_t: per item, the mean over
    its points of f(p)² over the start's |∇f_t|² (frozen), over tol², plus smoothness times the
    length-weighted squared jump of ∇f (each triangle's gradient by solving [x y 1] a = F) over
    the start's size S (frozen); then times (dF/ds)² = exp(2 s)."""
    obj, mesh, pts, face, tol = two_circle_objective(device, smoothness, 0.0)
    s = obj.s0 + 0.2 * torch.randn(obj.s0.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64).to(device)
    h = obj.gauss_newton_diagonal(s)
    V = mesh.verts.detach().double()
    faces = mesh.faces
    A = torch.cat([V[faces], torch.ones(faces.shape[0], 3, 1, dtype=torch.float64, device=device)], -1)   # (T,3,3)
    _, bary = locate_grid(mesh, pts, mesh.face_item[face])
    pitem = mesh.face_item[face]
    npts = torch.bincount(pitem, minlength=2).double()

    def tri_grad(F):
        return torch.linalg.solve(A, F[faces])[:, :2]              # (T,2) a, b of f = a x + b y + c

    F0 = obj.values(s).detach()
    g0 = tri_grad(F0)
    den0 = (g0 * g0).sum(1)
    # the objective keeps the faces with points or on a band edge: its edges' faces, in the mesh
    ef, el, eitem = obj.face_ids[obj.ef], obj.el, obj.eitem
    S0 = torch.zeros(2, dtype=torch.float64, device=device).index_add_(
        0, eitem, el * 0.5 * (den0[ef[:, 0]] + den0[ef[:, 1]]))

    def surrogate(F):
        f = (F[faces[face]] * bary).sum(1)
        d = (f * f / den0[face] / npts[pitem] / (tol[pitem] ** 2)).sum()
        if smoothness > 0:
            g = tri_grad(F)
            jump = ((g[ef[:, 0]] - g[ef[:, 1]]) ** 2).sum(1)
            d = d + smoothness * (el * jump / S0[eitem]).sum()
        return d

    H = torch.autograd.functional.hessian(surrogate, F0)
    ref = torch.diagonal(H) * torch.exp(2 * s)
    torch.testing.assert_close(h, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
    assert float(h.min()) >= 0 and int((h > 0).sum()) > 0.2 * h.shape[0]     # not a test of zeros


def test_preconditioned_fit_reaches_the_same_minimum_in_fewer_iterations(device):
    """Preconditioning changes the path, not the minimum: run long, both variants agree on the
    objective; after 15 iterations the preconditioned one is nearer to it (two circles of
    different sizes and tolerances, smoothness and crossing terms on)."""
    from torch_isc.pipeline.values import run_fit
    res = {}
    for pre in (0.0, 0.1):
        cfg = GeometryConfig(smoothness=1e-2, crossing_weight=1.0, precondition=pre)
        o = two_circle_objective_cfg(device, cfg)
        assert (o.pc is None) == (pre == 0)
        res[pre] = [o.value(run_fit(o, cfg, it, 0.0)[0]) for it in (15, 400)]
    best = torch.minimum(res[0.0][1], res[0.1][1])
    torch.testing.assert_close(res[0.0][1], res[0.1][1], rtol=1e-5, atol=0)
    gap = {p: (r[0] - best) / best for p, r in res.items()}
    assert (gap[0.1] < gap[0.0]).all(), gap


def test_fit_in_the_moving_variables_is_bit_identical_to_the_whole_fit(device):
    """run_fit leaves out the vertices no term reaches (no corner of a face with points or on a
    band edge, no crossing end): its minimizer, objectives and iteration counts are bit-identical
    to a plain batched L-BFGS over every vertex, and the vertices left out keep their start."""
    from torch_isc.pipeline.optim import batched_lbfgs
    from torch_isc.pipeline.values import run_fit
    cfg = GeometryConfig(smoothness=1e-2, crossing_weight=1.0)
    obj = two_circle_objective_cfg(device, cfg)
    _, kv = obj.variables()
    V = obj.s0.shape[0]
    assert kv is not None and 0 < kv.shape[0] < V                 # some vertices are left out
    out = torch.ones(V, dtype=torch.bool, device=obj.s0.device)
    out[kv] = False
    _, g = obj.value_and_grad(obj.s0 + 0.3)
    assert bool((g[out] == 0).all()) and bool((g[~out] != 0).any())
    s, f, it = run_fit(obj, cfg)
    x, f2, it2 = batched_lbfgs(obj._evaluate, obj.s0, obj.vi, obj.B, iterations=cfg.lbfgs_iterations,
                               history=cfg.lbfgs_history, with_grad=True, rel_tol=1e-7, stacked=True, trials=1)
    assert torch.equal(s, x) and torch.equal(f, f2) and torch.equal(it, it2)
    assert torch.equal(s[out], obj.s0[out]) and int(it.min()) > 1


def test_vertex_data_distance_near_is_exact_where_finite(device):
    dtype = torch.float64
    mesh, pts, face, bary, mom, signs, init = circle_setup(device, dtype, n=60, res=4)
    V = mesh.verts.cpu().numpy()
    P = pts.cpu().numpy()
    true = np.sqrt(((V[:, None, :] - P[None, :, :]) ** 2).sum(-1)).min(1)
    d = vertex_data_distance_near(mesh, pts, face).cpu().numpy()
    fin = np.isfinite(d)
    assert fin.any() and (~fin).any()
    # never below the true distance; on this mesh the nearest point is always in reach
    assert (d[fin] >= true[fin] - 1e-12).all()
    assert np.allclose(d[fin], true[fin], rtol=1e-12)


def test_fit_geometry_crossing_term_keeps_signs_and_crossings_near_data(device):
    """With the crossing term the signs are kept and no crossing ends up provably farther
    from the data than without it (beyond twice the dead zone)."""
    dtype = torch.float64
    mesh, pts, face, bary, mom, signs, init = circle_setup(device, dtype, n=60, res=4)
    tol = torch.tensor([0.01], dtype=dtype, device=device)
    near = vertex_data_distance_near(mesh, pts, face)
    slack = tol.clone()

    def worst_crossing(F):
        e = mesh.edges[(F[mesh.edges[:, 0]] < 0) != (F[mesh.edges[:, 1]] < 0)]
        m = F[e].abs()
        ln = (mesh.verts[e[:, 0]] - mesh.verts[e[:, 1]]).norm(dim=1)
        a = ln[:, None] * m / m.sum(1, keepdim=True)
        ex = torch.where(torch.isfinite(near[e]), near[e] - a, torch.zeros_like(a))
        return float(ex.max())

    F0, _ = fit_geometry(mesh, mom, signs, init, tol, GeometryConfig(crossing_weight=0.0))
    F1, _ = fit_geometry(mesh, mom, signs, init, tol, GeometryConfig(crossing_weight=1.0), data_dist=near,
                         slack=slack)
    assert torch.equal(F1 < 0, signs < 0)
    assert worst_crossing(F1) <= max(worst_crossing(F0), 2 * float(slack)) + 1e-9


def test_vertex_data_distance_is_upper_bound_exact_near_data(device):
    dtype = torch.float64
    mesh, pts, face, bary, mom, signs, init = circle_setup(device, dtype, n=60, res=4)
    V = mesh.verts.cpu().numpy()
    P = pts.cpu().numpy()
    true = np.sqrt(((V[:, None, :] - P[None, :, :]) ** 2).sum(-1)).min(1)
    d = init.cpu().numpy()
    assert (d >= true - 1e-12).all()
    # vertices of triangles with points: min distance to the points of incident triangles
    Fc = mesh.faces.cpu().numpy()
    fc = face.cpu().numpy()
    for vtx in range(V.shape[0]):
        inc = np.nonzero((Fc == vtx).any(1))[0]
        q = P[np.isin(fc, inc)]
        if len(q):
            assert d[vtx] == pytest.approx(np.sqrt(((q - V[vtx]) ** 2).sum(1)).min(), rel=1e-12)
        # relaxed along edges: never more than a neighbour's bound plus the edge
    for i, j in mesh.edges.cpu().tolist():
        el = np.linalg.norm(V[i] - V[j])
        assert d[i] <= d[j] + el + 1e-12 and d[j] <= d[i] + el + 1e-12


@pytest.mark.parametrize("smoothness", [0.0, 1e-2])
def test_fit_geometry_lowers_delta1_keeps_signs_and_fits_circle(smoothness, device, dtype):
    R = 0.5
    mesh, pts, face, bary, mom, signs, init = circle_setup(device, dtype, R=R)
    tol = torch.tensor([0.004], device=device, dtype=dtype)
    d1_start = delta1_from_points(mesh, signs * init, pts, face)
    F, d1 = fit_geometry(mesh, mom, signs, init, tol, GeometryConfig(smoothness=smoothness,
                                                                     crossing_weight=0.0))
    assert F.dtype == dtype and F.shape == signs.shape
    assert torch.isfinite(F).all()
    assert ((F * signs) > 0).all() and not (F == 0).any()
    # magnitudes are floored at magnitude_floor x the item's mean starting magnitude
    assert float(F.abs().min()) >= 0.02 * float(init.mean()) * (1 - 1e-5)
    # the reported Δ1 is the mean squared approximate distance of the points
    d1_pts = delta1_from_points(mesh, F, pts, face)
    assert float(d1[0]) == pytest.approx(d1_pts, rel=1e-3 if dtype == torch.float32 else 1e-8)
    assert d1_pts < 0.5 * d1_start
    # the zero set is close to the circle (mesh edge = 1/8)
    zs = ImplicitCurve(mesh, F).zero_set()
    assert zs.closed.tolist() == [True]
    r = zs.points.double().norm(dim=1)
    assert float((r - R).abs().max()) < 0.01
    # and closer than the linear interpolation of the starting magnitudes
    r0 = ImplicitCurve(mesh, signs * init).zero_set().points.double().norm(dim=1)
    assert float((r - R).abs().max()) < float((r0 - R).abs().max())


@pytest.mark.parametrize("pre", [0.0, 0.1])
def test_fit_geometry_batch_independent(device, pre):
    dtype = torch.float64
    m1, p1, f1, b1, mom1, s1, i1 = circle_setup(device, dtype, n=150, R=0.5, res=6)
    m2, p2, f2, b2, mom2, s2, i2 = circle_setup(device, dtype, n=90, R=0.3, res=4)
    tol = torch.tensor([0.004], device=device, dtype=dtype)
    F1, d1 = fit_geometry(m1, mom1, s1, i1, tol, GeometryConfig(lbfgs_iterations=40, crossing_weight=0.0,
                                                                precondition=pre))
    mesh = MeshBatch.cat([m2, m1])
    pts = torch.cat([p2, p1])
    item = torch.cat([torch.zeros(90, dtype=torch.long), torch.ones(150, dtype=torch.long)]).to(device)
    face, bary = locate_grid(mesh, pts, item)
    mom = triangle_moments(mesh, pts, face, bary)
    F, d = fit_geometry(mesh, mom, torch.cat([s2, s1]), torch.cat([i2, i1]), torch.cat([tol, tol]),
                        GeometryConfig(lbfgs_iterations=40, crossing_weight=0.0, precondition=pre))
    nv2 = m2.verts.shape[0]
    cuda = device.type == "cuda"               # atomic adds: rounding, amplified by 40 iterations
    torch.testing.assert_close(F[nv2:], F1, rtol=1e-6 if cuda else 1e-10, atol=1e-7 if cuda else 1e-12)
    torch.testing.assert_close(d[1], d1[0], rtol=1e-6 if cuda else 1e-10, atol=1e-12 if cuda else 1e-15)
    # the line search's layout (trials per stacked call) does not change a bit of the result
    F4, d4 = fit_geometry(mesh, mom, torch.cat([s2, s1]), torch.cat([i2, i1]), torch.cat([tol, tol]),
                          GeometryConfig(lbfgs_iterations=40, crossing_weight=0.0, lbfgs_trials=4, precondition=pre))
    # on CUDA another trial layout can accept another step where atomic rounding ties two trials
    # (an H200 run: 2e-6 on values of about 0.3)
    assert_same(F4, F, rtol=1e-4, atol=1e-5)
    assert_same(d4, d, atol=1e-12)


def test_fit_geometry_compile_falls_back_to_eager_with_a_warning(device, monkeypatch):
    """``compile=True`` where torch.compile cannot be made, or its function fails when called:
    a warning, and the eager result bit for bit."""
    import torch_isc.pipeline.values as V
    mesh, pts, face, bary, mom, signs, init = circle_setup(device, torch.float64, n=60, res=4)
    tol = torch.tensor([0.004], device=device, dtype=torch.float64)
    cfg = dict(lbfgs_iterations=15, crossing_weight=0.0)
    F0, d0 = fit_geometry(mesh, mom, signs, init, tol, GeometryConfig(**cfg))

    def no_compile(*a, **k):
        raise RuntimeError("no inductor here")

    monkeypatch.setattr(torch, "compile", no_compile)
    monkeypatch.setattr(V, "_COMPILED", [])
    with pytest.warns(RuntimeWarning, match="torch.compile is unavailable"):
        F1, d1 = fit_geometry(mesh, mom, signs, init, tol, GeometryConfig(compile=True, **cfg))
    assert_same(F1, F0, atol=1e-7)
    assert_same(d1, d0, atol=1e-12)

    def broken(obj, s):
        raise RuntimeError("backend failed")

    monkeypatch.setattr(V, "_COMPILED", [broken])
    with pytest.warns(RuntimeWarning, match="failed"):
        F2, _ = fit_geometry(mesh, mom, signs, init, tol, GeometryConfig(compile=True, **cfg))
    assert_same(F2, F0, atol=1e-7)
    assert V._COMPILED == [None]


# ============================================================================= subdivision


def check_conforming(old, new, tol=1e-9):
    """Every directed edge once; an undirected edge used once lies on the old outer boundary."""
    F = new.faces.cpu().tolist()
    V = new.verts.double().cpu().numpy()
    directed = set()
    undirected = defaultdict(int)
    for tri in F:
        for a in range(3):
            i, j = tri[a], tri[(a + 1) % 3]
            assert (i, j) not in directed
            directed.add((i, j))
            undirected[(min(i, j), max(i, j))] += 1
    assert max(undirected.values()) <= 2
    ob = old.edges[old.is_boundary_edge].cpu().numpy()
    OV = old.verts.double().cpu().numpy()
    A, Bv = OV[ob[:, 0]], OV[ob[:, 1]]
    for (i, j), c in undirected.items():
        if c == 2:
            continue
        # a hanging vertex would leave an interior edge used once: it must lie on an old boundary edge
        ok = False
        for a, b in zip(A, Bv):
            d = b - a
            cr_i = d[0] * (V[i][1] - a[1]) - d[1] * (V[i][0] - a[0])
            cr_j = d[0] * (V[j][1] - a[1]) - d[1] * (V[j][0] - a[0])
            L2 = d @ d
            ti, tj = (V[i] - a) @ d / L2, (V[j] - a) @ d / L2
            if abs(cr_i) < tol and abs(cr_j) < tol and -tol <= ti <= 1 + tol and -tol <= tj <= 1 + tol:
                ok = True
                break
        assert ok, f"edge {(i, j)} used once but not on the outer boundary"


def item_areas(mesh):
    a = mesh.signed_areas().double()
    return torch.zeros(mesh.num_items, dtype=torch.float64, device=a.device).index_add_(0, mesh.face_item, a)


@pytest.mark.parametrize("kind", ["hexagon", "square"])
@pytest.mark.parametrize("frac", [0.1, 0.4])
def test_subdivide_random_marks_conforming(kind, frac, device, dtype):
    c = torch.tensor([[0.0, 0.0], [5.0, 1.0], [-3.0, 2.0]], device=device, dtype=dtype)
    r = torch.tensor([1.0, 2.0, 0.5], device=device, dtype=dtype)
    mesh = hexagon_mesh(c, r, 3) if kind == "hexagon" else square_mesh(c, r, 4)
    g = torch.Generator().manual_seed(int(frac * 100))
    for rnd in range(3):
        marked = (torch.rand(mesh.faces.shape[0], generator=g) < frac).to(device)
        sd = subdivide(mesh, marked)
        new = sd.mesh
        new.validate()
        assert (new.signed_areas() > 0).all()
        check_conforming(mesh, new, 1e-5 if dtype == torch.float32 else 1e-9)
        # items stay contiguous and keep their own vertices
        assert new.num_items == mesh.num_items
        assert (new.vert_item[new.faces] == new.face_item[:, None]).all()
        atol = 1e-5 if dtype == torch.float32 else 1e-12
        torch.testing.assert_close(item_areas(new), item_areas(mesh), rtol=1e-5 if dtype == torch.float32 else 1e-12,
                                   atol=atol)
        # children: each old face's children partition it (area), marked faces split in 4
        ch = sd.children
        nchild = (ch >= 0).sum(1)
        assert (nchild[marked] == 4).all()
        assert set(nchild.unique().tolist()) <= {1, 2, 4}
        assert sorted(ch[ch >= 0].tolist()) == list(range(new.faces.shape[0]))
        a_new = new.signed_areas().double()
        a_sum = torch.where(ch >= 0, a_new[ch.clamp_min(0)], torch.zeros_like(a_new[ch.clamp_min(0)])).sum(1)
        torch.testing.assert_close(a_sum, mesh.signed_areas().double(), rtol=1e-5 if dtype == torch.float32 else 1e-12,
                                   atol=atol)
        # an old triangle with 0 or 1 marked vertex is kept as it is
        vm = torch.zeros(mesh.verts.shape[0], dtype=torch.bool, device=device)
        vm[mesh.faces[marked].reshape(-1)] = True
        nm = vm[mesh.faces].sum(1)
        kept = nm <= 1
        assert (nchild[kept] == 1).all()
        assert torch.equal(sd.old_to_new_vert[mesh.faces[kept]], new.faces[ch[kept, 0]])
        assert (nchild[nm == 2] == 2).all() and (nchild[nm == 3] == 4).all()
        # old vertices keep their positions
        assert torch.equal(new.verts[sd.old_to_new_vert], mesh.verts)
        # new vertices sit at midpoints of the edges with both ends marked
        nv = sd.new_vert_edge >= 0
        e = mesh.edges[sd.new_vert_edge[nv]]
        assert vm[e].all()
        assert int(nv.sum()) == int((vm[mesh.edges[:, 0]] & vm[mesh.edges[:, 1]]).sum())
        torch.testing.assert_close(new.verts[nv], 0.5 * (mesh.verts[e[:, 0]] + mesh.verts[e[:, 1]]))
        mesh = new


@pytest.mark.parametrize("r", [1, 2, 3])
def test_subdivide_all_gives_double_resolution(r, device, dtype):
    c = torch.tensor([[0.0, 0.0], [4.0, 0.0]], device=device, dtype=dtype)
    rad = torch.tensor([1.0, 1.5], device=device, dtype=dtype)
    mesh = hexagon_mesh(c, rad, r)
    sd = subdivide(mesh, torch.ones(mesh.faces.shape[0], dtype=torch.bool, device=device))
    ref = hexagon_mesh(c, rad, 2 * r)
    assert sd.mesh.faces.shape[0] == 4 * mesh.faces.shape[0] == 2 * 6 * (2 * r) ** 2
    assert torch.equal(sd.mesh.verts_per_item, ref.verts_per_item)
    assert torch.equal(sd.mesh.faces_per_item, ref.faces_per_item)
    for b in range(2):
        a = sd.mesh[b].verts.double().cpu().numpy()
        bb = ref[b].verts.double().cpu().numpy()
        a = a[np.lexsort((a[:, 1].round(6), a[:, 0].round(6)))]
        bb = bb[np.lexsort((bb[:, 1].round(6), bb[:, 0].round(6)))]
        np.testing.assert_allclose(a, bb, atol=1e-5)
    q = sd.mesh.quality()
    torch.testing.assert_close(q, torch.ones_like(q), rtol=1e-4, atol=1e-4)


def test_subdivide_no_marks_is_identity(device):
    mesh = hexagons(2, 2, device, torch.float64)
    sd = subdivide(mesh, torch.zeros(mesh.faces.shape[0], dtype=torch.bool, device=device))
    assert torch.equal(sd.mesh.verts, mesh.verts) and torch.equal(sd.mesh.faces, mesh.faces)
    assert torch.equal(sd.children[:, 0], torch.arange(mesh.faces.shape[0], device=device))
    assert (sd.children[:, 1:] == -1).all()


@pytest.mark.parametrize("kind", ["hexagon", "square"])
def test_locate_children_equals_fresh_locate(kind, device, dtype):
    c = torch.tensor([[0.0, 0.0], [5.0, 1.0]], device=device, dtype=dtype)
    r = torch.tensor([1.0, 2.0], device=device, dtype=dtype)
    mesh = hexagon_mesh(c, r, 3) if kind == "hexagon" else square_mesh(c, r, 4)
    g = torch.Generator().manual_seed(8)
    pts = torch.cat([disc_points(400, 0.85, g), disc_points(400, 1.7, g, center=(5.0, 1.0))]).to(device=device,
                                                                                            dtype=dtype)
    item = torch.cat([torch.zeros(400, dtype=torch.long), torch.ones(400, dtype=torch.long)]).to(device)
    face, _ = locate_grid(mesh, pts, item)
    assert (face >= 0).all()
    for rnd in range(2):
        marked = (torch.rand(mesh.faces.shape[0], generator=g) < 0.4).to(device)
        sd = subdivide(mesh, marked)
        fc, bc = locate_children(sd.mesh, pts, face, sd.children)
        fg, bg = locate_grid(sd.mesh, pts, item)
        strict = bg.min(1).values > 1e-4
        assert int(strict.sum()) > 700
        assert torch.equal(fc[strict], fg[strict])
        torch.testing.assert_close(bc[strict], bg[strict])
        # the child is one of the parent's children
        assert (sd.children[face] == fc[:, None]).any(1).all()
        mesh, face = sd.mesh, fc


def test_interpolate_linear_function_exact(device):
    dtype = torch.float64
    mesh = MeshBatch.cat([hexagons(1, 3, device, dtype), square_mesh(
        torch.tensor([[4.0, 0.0]], device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 3)])
    g = torch.Generator().manual_seed(3)
    marked = (torch.rand(mesh.faces.shape[0], generator=g) < 0.5).to(device)
    sd = subdivide(mesh, marked)

    def lin(v):
        return 0.7 * v[:, 0] - 1.3 * v[:, 1] + 0.25

    vals = sd.interpolate(lin(mesh.verts), mesh.edges)
    torch.testing.assert_close(vals, lin(sd.mesh.verts), rtol=0, atol=1e-13)
    assert torch.equal(vals[sd.old_to_new_vert], lin(mesh.verts))
    # vector values: interpolating the positions gives the new positions
    pos = sd.interpolate(mesh.verts, mesh.edges)
    torch.testing.assert_close(pos, sd.mesh.verts, rtol=0, atol=1e-15)
    # a sign pattern: new vertices are means of their ends (0 where the ends differ)
    s = torch.where(mesh.verts[:, 0] > 0.1, 1.0, -1.0).to(dtype)
    si = sd.interpolate(s, mesh.edges)
    nv = sd.new_vert_edge >= 0
    e = mesh.edges[sd.new_vert_edge[nv]]
    assert torch.equal(si[nv], 0.5 * (s[e[:, 0]] + s[e[:, 1]]))


# ============================================================================= relaxation


def naive_mesh_energy(mesh, pts, face, kd, ke, rho, min_dist):
    V = mesh.verts.double().cpu().numpy()
    Fc = mesh.faces.cpu().tolist()
    P = pts.double().cpu().numpy()
    nD = sum(1 for f in face.tolist() if f >= 0)
    phi = np.zeros(len(V))
    for p, f in zip(P, face.tolist()):
        if f < 0:
            continue
        for i in Fc[f]:
            phi[i] += 1.0 / max(np.linalg.norm(V[i] - p), min_dist)
    phi /= nD
    E = mesh.edges.cpu().tolist()
    deg = np.zeros(len(V))
    for i, j in E:
        deg[i] += 1
        deg[j] += 1
    nu = deg / deg.mean()
    UD = rho ** 2 * sum((phi[i] - phi[j]) ** 2 for i, j in E)
    UE = sum(nu[i] * nu[j] * ((V[i] - V[j]) ** 2).sum() for i, j in E) / rho ** 2
    return kd * UD + ke * UE


def test_mesh_energy_hand_values(device):
    dtype = torch.float64
    mesh = square_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 2)
    pts = torch.tensor([[0.3, 0.2], [-0.5, 0.6], [0.0, 0.0], [0.9, -0.9]], device=device, dtype=dtype)
    _, face, _ = locate_single(mesh, pts)
    face = face.clone()
    face[3] = -1                                       # an ignored point
    rho = torch.tensor([2 * math.sqrt(2)], device=device, dtype=dtype)
    n_pts = torch.tensor([3.0], device=device, dtype=dtype)
    md = torch.tensor([0.05], device=device, dtype=dtype)
    U = mesh_energy(mesh, mesh.verts, pts, face, 1.0, 0.25, rho, n_pts, md)
    ref = naive_mesh_energy(mesh, pts, face, 1.0, 0.25, 2 * math.sqrt(2), 0.05)
    assert float(U[0]) == pytest.approx(ref, rel=1e-12)
    # the distance guard: a point on a vertex counts 1/min_dist
    U2 = mesh_energy(mesh, mesh.verts, pts, face, 1.0, 0.0, rho, n_pts, md * 0.1)
    ref2 = naive_mesh_energy(mesh, pts, face, 1.0, 0.0, 2 * math.sqrt(2), 0.005)
    assert float(U2[0]) == pytest.approx(ref2, rel=1e-12)


def relax_setup(device, dtype, n_items=2):
    meshes, pts_l, item_l = [], [], []
    g = torch.Generator().manual_seed(21)
    for b in range(n_items):
        c = torch.tensor([[3.0 * b, 0.0]], device=device, dtype=dtype)
        m = hexagon_mesh(c, torch.ones(1, device=device, dtype=dtype), 4) if b % 2 == 0 else \
            square_mesh(c, torch.ones(1, device=device, dtype=dtype), 5)
        meshes.append(m)
        R = 0.5 + 0.1 * b
        t = torch.rand(150, generator=g, dtype=torch.float64) * 2 * math.pi
        p = torch.stack([R * t.cos() + 3.0 * b, R * t.sin()], 1)
        pts_l.append(p)
        item_l.append(torch.full((150,), b, dtype=torch.long))
    mesh = MeshBatch.cat(meshes)
    pts = torch.cat(pts_l).to(device=device, dtype=dtype)
    item = torch.cat(item_l).to(device)
    face, _ = locate_grid(mesh, pts, item)
    marked = torch.zeros(mesh.faces.shape[0], dtype=torch.bool, device=device)
    marked[face] = True
    sd = subdivide(mesh, marked)
    face, _ = locate_children(sd.mesh, pts, face, sd.children)
    return sd.mesh, pts, item, face


def test_relax_mesh_invariants(device, dtype):
    mesh, pts, item, face = relax_setup(device, dtype)
    min_q = 0.3
    q0 = mesh.quality()
    bbox = mesh.item_bbox()
    rho = (bbox[:, 2:] - bbox[:, :2]).norm(dim=1)
    npts = torch.bincount(item, minlength=mesh.num_items).to(dtype)
    md = 1e-4 * rho
    U0 = mesh_energy(mesh, mesh.verts, pts, face, 1.0, 0.25, rho, npts, md)
    out, f2, b2 = relax_mesh(mesh, pts, item, face, RelaxConfig(relax_iterations=15, min_quality=min_q))
    v0, v1 = mesh.verts, out.verts
    assert torch.equal(out.faces, mesh.faces)
    assert float((v1 - v0).abs().max()) > 1e-3                 # it did move something
    assert (out.signed_areas() > 0).all()
    floor = torch.minimum(q0, torch.full_like(q0, min_q))
    assert (out.quality() >= floor - 1e-6).all()
    corner = mesh.is_corner_vert
    assert int(corner.sum()) == 6 + 4
    assert torch.equal(v1[corner], v0[corner])
    # other boundary vertices stay on their side: no move across the boundary direction
    side = mesh.is_boundary_vert & ~corner
    d = mesh.boundary_edge_dir[side]
    mv = (v1 - v0)[side]
    off = (mv[:, 0] * d[:, 1] - mv[:, 1] * d[:, 0]).abs()
    assert float(off.max()) < (1e-5 if dtype == torch.float32 else 1e-12)
    # energy per item does not increase (with the points re-partitioned)
    U1 = mesh_energy(out, out.verts, pts, f2, 1.0, 0.25, rho, npts, md)
    assert (U1 <= U0 * (1 + 1e-6)).all()
    assert (U1 < U0).any()
    # the returned partition is the true one
    fg, bg = locate_grid(out, pts, item)
    strict = bg.min(1).values > 1e-5
    assert torch.equal(f2[strict], fg[strict])
    torch.testing.assert_close(b2, barycentric(out.verts, out.faces, f2, pts))
    assert (b2.min(1).values >= -1e-5).all()


@pytest.mark.parametrize("max_move", [0.3, 0.9])
def test_relax_mesh_energy_monotone_per_iteration(max_move, device):
    """A run of k+1 iterations continues the run of k: the energy never goes up, even with
    long tentative steps (which must be backtracked)."""
    dtype = torch.float64
    mesh, pts, item, face = relax_setup(device, dtype)
    bbox = mesh.item_bbox()
    rho = (bbox[:, 2:] - bbox[:, :2]).norm(dim=1)
    npts = torch.bincount(item, minlength=mesh.num_items).to(dtype)
    prev = mesh_energy(mesh, mesh.verts, pts, face, 1.0, 0.25, rho, npts, 1e-4 * rho)
    for it in range(1, 7):
        out, f2, _ = relax_mesh(mesh, pts, item, face, RelaxConfig(relax_iterations=it, relax_max_move=max_move))
        U = mesh_energy(out, out.verts, pts, f2, 1.0, 0.25, rho, npts, 1e-4 * rho)
        assert (U <= prev).all(), (it, U, prev)
        prev = U


def test_relax_mesh_quality_floor_with_slivers(device):
    """Triangles already below the floor may not get worse; nothing gets inverted."""
    dtype = torch.float64
    mesh = square_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 4)
    v = mesh.verts.clone()
    inner = ~mesh.is_boundary_vert
    g = torch.Generator().manual_seed(2)
    v[inner] += (torch.rand(int(inner.sum()), 2, generator=g, dtype=dtype).to(device) - 0.5) * 0.3
    mesh = mesh.with_verts(v)
    assert (mesh.signed_areas() > 0).all()
    t = torch.rand(200, generator=g, dtype=dtype) * 2 * math.pi
    pts = (0.6 * torch.stack([t.cos(), t.sin()], 1)).to(device)
    item, face, _ = locate_single(mesh, pts)
    q0 = mesh.quality()
    out, f2, _ = relax_mesh(mesh, pts, item, face, RelaxConfig(relax_iterations=20, min_quality=0.9))
    assert (out.signed_areas() > 0).all()
    assert (out.quality() >= torch.minimum(q0, torch.full_like(q0, 0.9)) - 1e-12).all()


def test_relax_mesh_batch_independent(device):
    dtype = torch.float64
    mesh, pts, item, face = relax_setup(device, dtype, n_items=2)
    out, f2, _ = relax_mesh(mesh, pts, item, face, RelaxConfig(relax_iterations=10))
    m1 = mesh[1]
    sel = item == 1
    f1 = face[sel] - int(mesh.faces_first_idx[1])
    o1, g1, _ = relax_mesh(m1, pts[sel], torch.zeros(int(sel.sum()), dtype=torch.long, device=device), f1,
                           RelaxConfig(relax_iterations=10))
    v0 = int(mesh.verts_first_idx[1])
    torch.testing.assert_close(out.verts[v0:], o1.verts, rtol=1e-12, atol=1e-12)


def test_relax_stage_relaxes_only_items_whose_noise_is_within_relax_noisy_of_the_tolerance(device):
    """``relax_noisy`` 0.5 with tolerance 0.004: an item whose noise is 0.002 (exactly at the bound)
    or 0 is relaxed as it would be alone; an item whose noise is 0.0021 keeps its mesh bit for bit
    (a noisy band says nothing about where a vertex is "away from the data")."""
    dtype = torch.float64
    mesh, pts, item, face = relax_setup(device, dtype, n_items=3)
    B = mesh.num_items
    bary = barycentric(mesh.verts, mesh.faces, face, pts)
    ws = WorkingSet.start(mesh, pts, item, face, bary, torch.zeros(pts.shape[0], 5, dtype=dtype, device=device),
                          torch.zeros(B, 2, dtype=dtype, device=device), torch.ones(B, dtype=dtype, device=device),
                          torch.full((B,), 0.004, dtype=dtype, device=device),
                          torch.tensor([0.002, 0.0021, 0.0], dtype=dtype, device=device),
                          torch.zeros(B, dtype=torch.bool, device=device))
    cfg = RelaxConfig(relax_iterations=10, relax_noisy=0.5)
    out = relax_stage(ws, cfg)
    every, f_every, _ = relax_mesh(mesh, pts, item, face, RelaxConfig(relax_iterations=10))
    vi = mesh.vert_item
    assert torch.equal(out.mesh.verts[vi == 1], mesh.verts[vi == 1])
    for b in (0, 2):
        moved = (out.mesh.verts[vi == b] - mesh.verts[vi == b]).abs().max()
        assert float(moved) > 1e-3
        torch.testing.assert_close(out.mesh.verts[vi == b], every.verts[vi == b], rtol=1e-12, atol=1e-12)
    # the points' triangles and barycentrics are those of the returned mesh
    assert torch.equal(out.face[item != 1], f_every[item != 1])
    torch.testing.assert_close(out.bary, barycentric(out.mesh.verts, out.mesh.faces, out.face, pts))
    # a large bound relaxes every item
    assert_same(relax_stage(ws, RelaxConfig(relax_iterations=10, relax_noisy=1e6)).mesh.verts, every.verts,
                rtol=1e-12, atol=1e-12)


def naive_relax(mesh, pts, face, cfg):
    """One item, the backtracking written plainly: each trial length in turn, the points
    re-located on the grid, the first length that keeps the mesh valid and lowers U taken."""
    dtype = mesh.dtype
    item = torch.zeros(pts.shape[0], dtype=torch.long, device=pts.device)
    v = mesh.verts.detach().clone()
    bb = mesh.item_bbox()[0]
    rho = (bb[2:] - bb[:2]).norm()[None]
    npts = (face >= 0).sum()[None].to(dtype)
    md = 1e-4 * rho
    E = mesh.edges.cpu().tolist()
    el = (v[mesh.edges[:, 0]] - v[mesh.edges[:, 1]]).norm(dim=1).cpu().tolist()
    short = [math.inf] * v.shape[0]
    for (i, j), l in zip(E, el):
        short[i], short[j] = min(short[i], l), min(short[j], l)
    short = torch.tensor(short, dtype=dtype, device=v.device)
    corner, side = mesh.is_corner_vert, mesh.is_boundary_vert & ~mesh.is_corner_vert
    sdir = mesh.boundary_edge_dir
    q0 = mesh.quality()
    floor = torch.minimum(q0, torch.full_like(q0, cfg.min_quality))
    for _ in range(cfg.relax_iterations):
        vv = v.clone().requires_grad_(True)
        U = mesh_energy(mesh, vv, pts, face, cfg.kappa_data, cfg.kappa_edge, rho, npts, md)
        g, = torch.autograd.grad(U.sum(), vv)
        d = -g
        d[corner] = 0
        d[side] = (d[side] * sdir[side]).sum(1, keepdim=True) * sdir[side]
        worst = float((d.norm(dim=1) / short).max())
        if worst == 0:
            break
        step, moved = cfg.relax_max_move / worst, False
        for _k in range(cfg.relax_max_backtracks):
            vt = v + step * d
            q = mesh.quality(vt)
            if bool((q > 0).all()) and bool((q >= floor).all()):
                ft, _ = locate_grid(mesh.with_verts(vt), pts, item)
                if float(mesh_energy(mesh, vt, pts, ft, cfg.kappa_data, cfg.kappa_edge, rho, npts, md)) < float(U.detach()):
                    v, face, moved = vt, ft, True
                    break
            step = step / 2
        if not moved:
            break
    return v, face


@pytest.mark.parametrize("max_move, iterations", [(0.3, 12), (0.9, 8)])
def test_relax_mesh_equals_plain_backtracking(max_move, iterations, device):
    """The stacked trials give what trying each length in turn per item gives."""
    dtype = torch.float64
    mesh, pts, item, face = relax_setup(device, dtype, n_items=3)
    cfg = RelaxConfig(relax_iterations=iterations, relax_max_move=max_move)
    out, f2, _ = relax_mesh(mesh, pts, item, face, cfg)
    moved = 0
    for b in range(mesh.num_items):
        sel = item == b
        v0, nv = int(mesh.verts_first_idx[b]), int(mesh.verts_per_item[b])
        f0 = int(mesh.faces_first_idx[b])
        v_ref, f_ref = naive_relax(mesh[b], pts[sel], face[sel] - f0, cfg)
        torch.testing.assert_close(out.verts[v0:v0 + nv], v_ref, rtol=0, atol=1e-12)
        assert torch.equal(f2[sel] - f0, f_ref)
        moved += int((v_ref != mesh.verts[v0:v0 + nv]).any())
    assert moved == mesh.num_items


def test_relax_mesh_host_reads_do_not_grow_with_batch(device):
    """Host reads (and kernels) of a relaxation are the same for 3 items and for the same
    items 4 times over: nothing is read per item or per trial."""
    from torch.overrides import TorchFunctionMode
    from torch.utils._python_dispatch import TorchDispatchMode
    dtype = torch.float64
    mesh, pts, item, face = relax_setup(device, dtype, n_items=3)

    def counts(m, p, it, f):
        seen = {"read": 0, "ops": 0}

        class Reads(TorchFunctionMode):
            def __torch_function__(self, func, types, args=(), kwargs=None):
                if getattr(func, "__name__", "") in ("tolist", "__bool__", "item", "__int__", "__float__"):
                    seen["read"] += 1
                return func(*args, **(kwargs or {}))

        class Ops(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                seen["ops"] += 1
                if func in (torch.ops.aten.nonzero.default, torch.ops.aten._local_scalar_dense.default):
                    seen["read"] += 1
                return func(*args, **(kwargs or {}))

        for attr in ("face_neighbors", "is_corner_vert", "boundary_edge_dir", "degrees", "edges"):
            getattr(m, attr)                                  # topology built outside
        with Reads(), Ops():
            relax_mesh(m, p, it, f, RelaxConfig(relax_iterations=8))
        return seen

    one = counts(mesh, pts, item, face)
    n = 4
    big = MeshBatch.cat([mesh] * n)
    T = mesh.faces.shape[0]
    four = counts(big, pts.repeat(n, 1), torch.cat([item + 3 * r for r in range(n)]),
                  torch.cat([face + T * r for r in range(n)]))
    assert one == four, (one, four)
    assert 0 < one["read"] <= 8 * 6


# ============================================================================= tolerance / testing


def noisy_line(n, sigma, seed, even=False):
    g = torch.Generator().manual_seed(seed)
    x = torch.linspace(-0.5, 0.5, n, dtype=torch.float64) if even else torch.rand(n, generator=g, dtype=torch.float64) - 0.5
    y = 0.2 * x + sigma * torch.randn(n, generator=g, dtype=torch.float64)
    return torch.stack([x, y], 1)


@pytest.mark.parametrize("sigma,n,even", [(0.002, 200, False), (0.005, 200, False), (0.01, 100, True)])
@pytest.mark.parametrize("seed", [0, 1])
def test_estimate_noise_line(sigma, n, even, seed, device):
    """Where the 8 nearest neighbours span a stretch of line several σ long."""
    pts = noisy_line(n, sigma, seed, even).to(device)
    est = estimate_noise(pts, torch.zeros(n, dtype=torch.long, device=device), 1)
    assert est.shape == (1,)
    assert abs(float(est[0]) - sigma) < 0.25 * sigma


def test_estimate_noise_dense_noisy_line(device):
    """Points much denser than the noise is wide: 8 neighbours form a round blob and read about
    0.35 sigma; the estimate refits on hashed subsets until the neighbourhoods are line-like.
    It does not depend on the batch (the subset is chosen by the index within the item)."""
    n, sigma = 6000, 0.002
    pts = noisy_line(n, sigma, 1).to(device)
    item = torch.zeros(n, dtype=torch.long, device=device)
    est = estimate_noise(pts, item, 1)
    assert abs(float(est[0]) - sigma) < 0.25 * sigma
    # the single-scale fit is the biased one (so the subsets are what fixes it)
    assert float(estimate_noise(pts, item, 1, NoiseConfig(noise_min_subset=10 ** 9))[0]) < 0.5 * sigma
    # with a sparse item before it in the batch, the same estimate
    other = noisy_line(300, 0.01, 2).to(device)
    both = estimate_noise(torch.cat([other, pts]), torch.cat([item[:300], item + 1]), 2)
    assert float(both[1]) == float(est[0])
    assert float(both[0]) == float(estimate_noise(other, item[:300], 1)[0])


def test_estimate_noise_circle_and_batch(device):
    g = torch.Generator().manual_seed(1)
    t = torch.rand(500, generator=g, dtype=torch.float64) * 2 * math.pi
    r = 0.5 / math.sqrt(2)
    circ = torch.stack([r * t.cos(), r * t.sin()], 1)
    noisy = noisy_line(200, 0.004, 3)
    pts = torch.cat([noisy, circ]).to(device)
    item = torch.cat([torch.zeros(200, dtype=torch.long), torch.ones(500, dtype=torch.long)]).to(device)
    est = estimate_noise(pts, item, 2)
    assert float(est[1]) < 1e-3
    assert abs(float(est[0]) - 0.004) < 0.25 * 0.004
    # each item alone gives the same estimate
    alone = estimate_noise(circ.to(device), torch.zeros(500, dtype=torch.long, device=device), 1)
    assert float(alone[0]) < 1e-3
    alone0 = estimate_noise(noisy.to(device), torch.zeros(200, dtype=torch.long, device=device), 1)
    assert float(alone0[0]) == pytest.approx(float(est[0]), rel=1e-9)
    # fewer than 3 points: 0
    assert float(estimate_noise(circ[:2].to(device), torch.zeros(2, dtype=torch.long, device=device), 1)[0]) == 0.0


@pytest.mark.parametrize("n,sigma", [(60, 0.0), (60, 0.002), (100, 0.004), (60, 0.01)])
def test_estimate_noise_sparse_circle_is_not_its_curvature(n, sigma, device):
    """A unit circle sampled by n points (normalized: diagonal 1): eight neighbours span an arc
    whose sagitta a line fit would read as noise (n=60: 0.036 of the radius against a true
    0.002); the estimate follows sigma instead."""
    g = torch.Generator().manual_seed(n)
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n) + 0.3
    p = torch.stack([t.cos(), t.sin()], 1) + sigma * torch.randn(n, 2, generator=g, dtype=torch.float64)
    d = float((p.max(0).values - p.min(0).values).norm())
    est = float(estimate_noise((p / d).to(device), torch.zeros(n, dtype=torch.long, device=device), 1)[0]) * d
    spacing = 2 * math.pi / n
    assert est < sigma * 1.3 + 0.01 * spacing
    assert est > sigma * 0.7


@pytest.mark.parametrize("n", [12, 16, 24])
@pytest.mark.parametrize("sigma", [0.0, 0.01, 0.03])
def test_estimate_noise_circle_of_few_points(n, sigma, device):
    """A unit circle of 12-24 points: eight neighbours span 120-270 degrees of it, which even a
    parabola reads as noise (0.44 / 0.12 / 0.02 of the radius, clean); four neighbours read a
    tenth or less of that (their noise ratio is 0.02-0.2, where noise gives 0.55 or more), and
    the estimate is theirs: within 2.5% of the radius, or twice sigma, and above half sigma."""
    g = torch.Generator().manual_seed(n)
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n) + 0.3
    p = torch.stack([t.cos(), t.sin()], 1) + sigma * torch.randn(n, 2, generator=g, dtype=torch.float64)
    d = float((p.max(0).values - p.min(0).values).norm())
    est = float(estimate_noise((p / d).to(device), torch.zeros(n, dtype=torch.long, device=device), 1)[0]) * d
    assert est < max(2 * sigma, 0.025)
    assert est > 0.5 * sigma


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_estimate_noise_circle_noise_wider_than_spacing(seed, device):
    """600 points on a circle with noise 2.7x their spacing: eight neighbours are a round blob,
    so the estimate comes from subsets (64+ points, parabola fits); full-density fits read 0.68
    of the noise."""
    n, sigma = 600, 0.01 * 2 * math.sqrt(2)
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    p = torch.stack([t.cos(), t.sin()], 1) + sigma * torch.randn(n, 2, generator=g, dtype=torch.float64)
    d = float((p.max(0).values - p.min(0).values).norm())
    est = float(estimate_noise((p / d).to(device), torch.zeros(n, dtype=torch.long, device=device), 1)[0]) * d
    assert 0.78 * sigma < est < 1.25 * sigma


@pytest.mark.parametrize("k,gap", [(2, 2.5), (3, 3.0), (5, 4.0)])
def test_estimate_noise_of_clean_strands_a_few_spacings_apart(k, gap, device):
    """Clean concentric circles ``gap`` spacings apart: eight neighbours reach the next circle
    and read a noisy band (1.5-4% of the radius); four see one circle each, a thousand times
    less, so the estimate is theirs. A noisy pair of circles (noise 1% of the radius, 10 noise
    widths apart) is left to the eight (the four read 0.55-1 of them): the same estimate as
    with the ratio test off, within 25% of the noise."""
    import torch_isc.pipeline.noise as noise_mod
    n = 300
    h = 2 * math.pi / n
    rings = []
    for j in range(k):
        r = 1 - j * gap * h
        m = int(round(n * r))
        t = torch.arange(m, dtype=torch.float64) * (2 * math.pi / m) + 0.37 * j
        rings.append(torch.stack([r * t.cos(), r * t.sin()], 1))
    p = torch.cat(rings) / (2 * math.sqrt(2))
    item = torch.zeros(p.shape[0], dtype=torch.long, device=device)
    est = float(estimate_noise(p.to(device), item, 1)[0]) * 2 * math.sqrt(2)
    old = noise_mod.MISFIT_RATIOS
    try:
        noise_mod.MISFIT_RATIOS = (1e-300, 2e-300)          # the ratio test off: eight neighbours
        band = float(estimate_noise(p.to(device), item, 1)[0]) * 2 * math.sqrt(2)
    finally:
        noise_mod.MISFIT_RATIOS = old
    assert est < 1e-4 and band > 0.01
    g = torch.Generator().manual_seed(k)
    sigma = 0.01
    t = torch.rand(2 * n, generator=g, dtype=torch.float64) * 2 * math.pi
    r = torch.where(torch.arange(2 * n) < n, 1.0, 0.9).to(torch.float64)
    q = torch.stack([r * t.cos(), r * t.sin()], 1) + sigma * torch.randn(2 * n, 2, generator=g, dtype=torch.float64)
    q = q / (2 * math.sqrt(2))
    item = torch.zeros(2 * n, dtype=torch.long, device=device)
    got = float(estimate_noise(q.to(device), item, 1)[0])
    assert abs(got * 2 * math.sqrt(2) - sigma) < 0.25 * sigma
    old = noise_mod.MISFIT_RATIOS
    try:
        noise_mod.MISFIT_RATIOS = (1e-300, 2e-300)
        assert float(estimate_noise(q.to(device), item, 1)[0]) == got
    finally:
        noise_mod.MISFIT_RATIOS = old


def test_segment_median_against_loop(device):
    g = torch.Generator().manual_seed(0)
    n, B = 500, 9
    x = torch.randn(n, generator=g, dtype=torch.float64).to(device)
    x[::7] = x[3]                                      # ties
    seg = torch.randint(0, B, (n,), generator=g).to(device)
    seg[seg == 4] = 5                                  # an empty segment
    med = segment_median(x, seg, B)
    for b in range(B):
        xs = x[seg == b]
        want = torch.median(xs) if xs.numel() else torch.zeros((), dtype=x.dtype, device=device)
        if xs.numel():
            srt = sorted(xs.cpu().tolist())
            assert float(want) == srt[(len(srt) - 1) // 2]     # lower median
        assert float(med[b]) == float(want), b
    for m in (1, 2, 3, 4):                             # tiny segments
        xs = torch.arange(m, 0, -1, dtype=torch.float64, device=device)
        assert float(segment_median(xs, torch.zeros(m, dtype=torch.long, device=device), 1)[0]) == float(torch.median(xs))
    assert torch.equal(segment_median(torch.zeros(0, device=device), torch.zeros(0, dtype=torch.long, device=device), 3),
                       torch.zeros(3, device=device))


def hex1_line(device, dtype):
    """Hexagon (radius 1, 6 triangles) with f(x, y) = y - 0.1: the zero set is y = 0.1."""
    mesh = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 1)
    values = mesh.verts[:, 1] - 0.1
    assert not (values == 0).any()
    return mesh, values


def which_face(mesh, p, dtype, device):
    _, f, _ = locate_single(mesh, torch.tensor([p], device=device, dtype=dtype))
    return int(f[0])


def test_point_curve_distance_hand_values(device, dtype):
    mesh, values = hex1_line(device, dtype)
    # upper-right triangle (0,0),(1,0),(0.5,0.866): the segment y=0.1 for x in [0.0577, 0.9423]
    pts = torch.tensor([[0.5, 0.11], [0.4, 0.15], [0.5, 0.3],
                        [-0.6, 0.15],                # upper-left triangle: 0.05 from its own segment
                        [0.6, -0.1],                 # lower-right: no curve, neighbour above has it: 0.2
                        [0.0, -0.5],                 # lower-middle: no curve in it or its neighbours,
                                                     # the nearest in their neighbours (upper-left/right)
                        [0.02, 0.5]],                # upper-middle: the short segment x in [-0.0577, 0.0577]
                       device=device, dtype=dtype)
    _, face, _ = locate_single(mesh, pts)
    d2 = point_curve_distance2(mesh, values, pts, face)
    # last point: above the short segment of its own triangle (|x| < 0.1/√3), 0.4 above it
    want = [0.01 ** 2, 0.05 ** 2, 0.2 ** 2, 0.05 ** 2, 0.2 ** 2, 0.6 ** 2 + (0.1 / SQ3) ** 2, 0.4 ** 2]
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    for k, w in enumerate(want):
        if math.isinf(w):
            assert math.isinf(float(d2[k]))
        else:
            assert float(d2[k]) == pytest.approx(w, abs=tol), k
    # a point left of the segment end: distance to the end point, not to the extended line
    q = torch.tensor([[-0.95, 0.02]], device=device, dtype=dtype)
    _, fq, _ = locate_single(mesh, q)
    dq = point_curve_distance2(mesh, values, q, fq)
    end = (-1 + 0.1 / SQ3, 0.1)
    assert float(dq[0]) == pytest.approx((end[0] + 0.95) ** 2 + 0.08 ** 2, abs=tol)
    # point_residuals uses the extended line of the own triangle: f²/|∇f|² = (y-0.1)²
    _, bary = locate_grid(mesh, pts, torch.zeros(pts.shape[0], dtype=torch.long, device=device))
    r = point_residuals(mesh, values, face, bary)
    torch.testing.assert_close(r, (pts[:, 1] - 0.1) ** 2, rtol=1e-4, atol=tol)


def coverage_reference(mesh, values, pts, face, frames):
    """curve_coverage_excess by loops: segment midpoints by edge interpolation, neighbours as
    triangles sharing two vertices (float64)."""
    V = mesh.verts.double().cpu().numpy()
    F = mesh.faces.cpu().tolist()
    val = values.double().cpu().numpy()
    P = pts.double().cpu().numpy()
    fr = frames.double().cpu().numpy()
    fc = face.cpu().tolist()
    out = []
    for t, tri in enumerate(F):
        cross = []
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            if (val[a] < 0) != (val[b] < 0):
                u = val[a] / (val[a] - val[b])
                cross.append(V[a] + u * (V[b] - V[a]))
        if len(cross) != 2:
            out.append(-math.inf)
            continue
        m = 0.5 * (cross[0] + cross[1])
        near = {t} | {u for u, other in enumerate(F) if len(set(other) & set(tri)) == 2}
        best = math.inf
        for p, f, (tx, ty, r) in zip(P, fc, fr):
            off = m - p
            if f in near and abs(off[0] * tx + off[1] * ty) <= r:
                best = min(best, abs(off[0] * ty - off[1] * tx))
        out.append(best)
    return out


def test_curve_coverage_excess_hand_values_and_reference(device, dtype):
    mesh, values = hex1_line(device, dtype)
    # upper-right triangle: segment y = 0.1, midpoint (0.5, 0.1)
    pts = torch.tensor([[0.5, 0.12], [-0.3, 0.12], [0.0, -0.5], [-0.5, 0.3]], device=device, dtype=dtype)
    frames = torch.tensor([[1.0, 0.0, 0.05], [1.0, 0.0, 0.1], [0.0, 1.0, 0.0], [1.0, 0.0, 0.05]], device=device,
                          dtype=dtype)
    _, face, _ = locate_single(mesh, pts)
    ex, reach = curve_coverage_excess(mesh, values, pts, face, frames)
    ur = which_face(mesh, (0.5, 0.3), dtype, device)
    ul = which_face(mesh, (-0.5, 0.3), dtype, device)
    low = which_face(mesh, (0.0, -0.5), dtype, device)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    # 0.02 across the tangent of the first point, within its reach along it
    assert float(ex[ur]) == pytest.approx(0.02, abs=tol)
    # upper-left midpoint (-0.5, 0.1): the second point is 0.2 along its tangent, beyond its
    # reach 0.1, so says nothing; the fourth is 0.2 across its tangent
    assert float(ex[ul]) == pytest.approx(0.2, abs=tol)
    # upper-middle midpoint (0, 0.1): every point near it sees it beyond its reach
    um = which_face(mesh, (0.0, 0.5), dtype, device)
    assert float(ex[um]) == math.inf
    assert float(ex[low]) == -math.inf                     # no segment
    # the smallest reach among the points that see the midpoint
    assert float(reach[ur]) == pytest.approx(0.05, abs=tol) and float(reach[ul]) == pytest.approx(0.05, abs=tol)
    ref = coverage_reference(mesh, values, pts, face, frames)
    for t, r in enumerate(ref):
        if math.isinf(r):
            assert float(ex[t]) == r
        else:
            assert float(ex[t]) == pytest.approx(r, abs=tol)
    # a finer mesh, random points and frames: the reference again
    m2 = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 4)
    v2 = (m2.verts.double() ** 2).sum(1).sub(0.4).to(dtype)
    g = torch.Generator().manual_seed(3)
    p2 = (torch.rand(40, 2, generator=g, dtype=torch.float64) * 1.2 - 0.6).to(device=device, dtype=dtype)
    ang = torch.rand(40, generator=g, dtype=torch.float64) * math.pi
    f2 = torch.stack([ang.cos(), ang.sin(), 0.1 * torch.rand(40, generator=g, dtype=torch.float64)], 1).to(
        device=device, dtype=dtype)
    _, face2, _ = locate_single(m2, p2)
    ex2, _ = curve_coverage_excess(m2, v2, p2, face2, f2)
    ref2 = coverage_reference(m2, v2, p2, face2, f2)
    assert any(math.isfinite(r) for r in ref2) and any(r == math.inf for r in ref2)
    for t, r in enumerate(ref2):
        if math.isinf(r):
            assert float(ex2[t]) == r
        else:
            assert float(ex2[t]) == pytest.approx(r, abs=10 * tol)


def test_estimate_noise_frames_follow_the_curve(device):
    """The frames are the circle's tangents, and the reach is the farthest of 8 neighbours."""
    n = 200
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    p = 0.35 * torch.stack([t.cos(), t.sin()], 1)
    est = noise_and_frames(p.to(device), torch.zeros(n, dtype=torch.long, device=device), 1)
    noise, fr = est.level, est.frames
    fr = fr.cpu()
    tangent = torch.stack([-t.sin(), t.cos()], 1)
    assert float((fr[:, :2] * tangent).sum(1).abs().min()) > 0.999
    step = 0.35 * 2 * math.pi / n
    # eight nearest along a uniformly sampled circle: four on each side
    torch.testing.assert_close(fr[:, 2], torch.full((n,), 4 * step, dtype=torch.float64), rtol=1e-3, atol=0)


def test_point_curve_distance_second_ring_against_loops(device):
    """Points with no curve in their triangle's 1-ring are measured against the 2-ring, and
    read inf beyond it (float64 loops over triangles sharing an edge as the reference)."""
    dtype = torch.float64
    mesh = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device, dtype=dtype), 5)
    # a small closed curve around (0.45, 0.1): most of the hexagon is far from it
    values = ((mesh.verts - torch.tensor([0.45, 0.1], device=device, dtype=dtype)) ** 2).sum(1) - 0.03
    g = torch.Generator().manual_seed(4)
    pts = (torch.rand(200, 2, generator=g, dtype=dtype) * 1.4 - 0.7).to(device)
    _, face, _ = locate_single(mesh, pts)
    d2 = point_curve_distance2(mesh, values, pts, face).cpu()
    F = mesh.faces.cpu().tolist()
    V = mesh.verts.cpu().numpy()
    val = values.cpu().numpy()
    nbrs = [[u for u, o in enumerate(F) if len(set(o) & set(t)) == 2] for t in F]

    def segment(t):
        cross = []
        for a, b in ((F[t][0], F[t][1]), (F[t][1], F[t][2]), (F[t][2], F[t][0])):
            if (val[a] < 0) != (val[b] < 0):
                u = val[a] / (val[a] - val[b])
                cross.append(V[a] + u * (V[b] - V[a]))
        return cross if len(cross) == 2 else None

    def dist2(p, ts):
        best = math.inf
        for t in ts:
            sg = segment(t)
            if sg is None:
                continue
            a, d = sg[0], sg[1] - sg[0]
            u = min(max(float((p - a) @ d / max(d @ d, 1e-300)), 0.0), 1.0)
            best = min(best, float(((p - a - u * d) ** 2).sum()))
        return best
    kinds = set()
    for p, f, got in zip(pts.cpu().numpy(), face.cpu().tolist(), d2.tolist()):
        ring1 = [f] + nbrs[f]
        want = dist2(p, ring1)
        if math.isinf(want):
            want = dist2(p, sorted({u for t in nbrs[f] for u in nbrs[t]}))
            kinds.add("ring2" if math.isfinite(want) else "inf")
        else:
            kinds.add("ring1")
        if math.isinf(want):
            assert math.isinf(got)
        else:
            assert got == pytest.approx(want, rel=1e-9, abs=1e-15)
    assert kinds == {"ring1", "ring2", "inf"}


def _mark(mesh, pts, values, device, dtype, tol=0.004, noise=0.0, line_eps=None, statistic="max",
          noise_factor=3.0, min_points_split=6, min_points_fit=3, thin_factor=3.0, min_split_size=0.0):
    item, face, _ = locate_single(mesh, pts)
    res = point_curve_distance2(mesh, values, pts, face)
    count = torch.bincount(face, minlength=mesh.faces.shape[0]).to(dtype)
    if line_eps is None:
        line_eps = torch.zeros(mesh.faces.shape[0], device=device, dtype=dtype)
    cfg = TestConfig(test_statistic=statistic, noise_factor=noise_factor, min_points_split=min_points_split,
                     thin_feature_factor=thin_factor, min_split_size=min_split_size)
    return mark_triangles(mesh, res, face, count, line_eps, torch.tensor([tol], device=device, dtype=dtype),
                          torch.tensor([noise], device=device, dtype=dtype), cfg, min_points_fit), face


def test_mark_triangles_coverage_rule(device, dtype):
    """A triangle is marked for coverage when its excess is finite and above the effective
    tolerance and it is larger than twice the reach of the data near it."""
    mesh, values = hex1_line(device, dtype)
    pts = torch.zeros(0, 2, device=device, dtype=dtype)
    face = torch.zeros(0, dtype=torch.long, device=device)
    T = mesh.faces.shape[0]
    z = torch.zeros(T, device=device, dtype=dtype)
    excess = torch.tensor([0.1, 0.001, float("inf"), -float("inf"), 0.1, 0.1], device=device, dtype=dtype)
    reach = torch.tensor([0.1, 0.1, 0.1, 0.1, 0.6, 0.1], device=device, dtype=dtype)
    args = (mesh, torch.zeros(0, device=device, dtype=dtype), face, z, z, torch.tensor([0.004], device=device,
            dtype=dtype), torch.tensor([0.0], device=device, dtype=dtype))
    cfg = TestConfig(min_split_size=0.0)
    marked, _, _ = mark_triangles(*args, cfg, 3, coverage=(excess, reach))
    # every edge of the unit hexagon's triangles is 1 long: 1 > 2 x 0.6 fails for the fifth
    assert marked.tolist() == [True, False, False, False, False, True]
    assert not mark_triangles(*args, cfg, 3)[0].any()
    assert not mark_triangles(*args, TestConfig(min_split_size=300.0), 3, coverage=(excess, reach))[0].any()


def cluster(x0, y, n, device, dtype, dx=0.04):
    xs = x0 + dx * torch.arange(n, dtype=torch.float64)
    return torch.stack([xs, torch.full((n,), y, dtype=torch.float64)], 1).to(device=device, dtype=dtype)


def test_edge_weights_noise_floor():
    """Fits whose error is within the noise are all equally good: with ``noise2`` the weight
    of a triangle is 1 up to that error and falls linearly to 0 at the item's worst fit."""
    mesh = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), 1)
    T = mesh.faces.shape[0]
    L = torch.tensor([[1.0, -1.0, 1.0]], dtype=torch.float64).repeat(T, 1)
    eps = torch.linspace(0.0, 1.0, T, dtype=torch.float64)      # errors 0 .. 1
    count = torch.full((T,), 10.0, dtype=torch.float64)
    a = edge_weights(mesh, L, eps, count, 3, 1.0)
    b = edge_weights(mesh, L, eps, count, 3, 1.0, noise2=torch.tensor([0.6], dtype=torch.float64))
    # the same per-face weights by hand: w = (1 - eps) / (1 - emin), clamped to [0, 1]
    def by_hand(emin):
        w = ((1.0 - eps) / (1.0 - emin)).clamp(0, 1)
        sig = torch.where(L >= 0, 1.0, -1.0)
        prod = sig[:, [1, 2, 0]] * sig[:, [2, 0, 1]]
        return torch.zeros(mesh.edges.shape[0], dtype=torch.float64).index_add_(
            0, mesh.face_edges.reshape(-1), (-prod * w[:, None]).reshape(-1))
    torch.testing.assert_close(a, by_hand(0.0))
    torch.testing.assert_close(b, by_hand(0.6))
    assert b.abs().sum() > a.abs().sum()


def test_mark_triangles_hand_cases(device, dtype):
    mesh, values = hex1_line(device, dtype)
    ur = which_face(mesh, (0.5, 0.2), dtype, device)       # upper right
    ul = which_face(mesh, (-0.5, 0.2), dtype, device)      # upper left
    near = cluster(0.3, 0.1 + 0.001, 6, device, dtype)     # 0.001 from the curve
    far = cluster(-0.7, 0.1 + 0.05, 6, device, dtype)      # 0.05 from the curve
    (marked, eff, worst), face = _mark(mesh, torch.cat([near, far]), values, device, dtype)
    assert (face[:6] == ur).all() and (face[6:] == ul).all()
    assert marked.tolist() == [t == ul for t in range(6)]
    assert float(eff[0]) == pytest.approx(0.004)
    assert float(worst[0]) == pytest.approx(0.05, rel=1e-4)
    # the noise raises the tolerance: 3 x 0.02 = 0.06 > 0.05
    (m2, eff2, _), _ = _mark(mesh, torch.cat([near, far]), values, device, dtype, noise=0.02)
    assert not m2.any()
    assert float(eff2[0]) == pytest.approx(0.06)


def test_mark_triangles_max_allows_the_spread_of_many_noisy_points(device, dtype):
    """The largest of n Gaussian deviations grows like sqrt(2 ln n): with noise 0.005 (factor
    3: 0.015 allowed) a triangle of 400 points whose worst lies 0.016 off the curve passes
    (sqrt(2 ln 400) * 0.005 = 0.0173), the same worst among 6 points fails (sqrt(2 ln 6) < 3)."""
    mesh, values = hex1_line(device, dtype)
    ul = which_face(mesh, (-0.5, 0.2), dtype, device)

    def pts(n):
        p = cluster(-0.75, 0.1, n, device, dtype, dx=0.3 / n)
        p[0, 1] += 0.016
        return p
    (m400, eff, worst), _ = _mark(mesh, pts(400), values, device, dtype, noise=0.005)
    assert float(eff[0]) == pytest.approx(0.015) and float(worst[0]) == pytest.approx(0.016, rel=1e-3)
    assert not m400.any()
    (m6, _, _), _ = _mark(mesh, pts(6), values, device, dtype, noise=0.005)
    assert m6.tolist() == [t == ul for t in range(6)]
    # 2 ln(400) * 0.005^2 < 0.018^2: a point 0.018 off fails even among 400
    p = pts(400)
    p[0, 1] += 0.002
    (m400b, _, _), _ = _mark(mesh, p, values, device, dtype, noise=0.005)
    assert m400b.tolist() == [t == ul for t in range(6)]


def test_mark_triangles_point_guards(device, dtype):
    mesh, values = hex1_line(device, dtype)
    ul = which_face(mesh, (-0.5, 0.2), dtype, device)
    # one point 0.008 off, the others on the curve: max fails (6.4e-5 > 1.6e-5), mean passes
    def pts(n):
        p = cluster(-0.7, 0.1, n, device, dtype)
        p[0, 1] += 0.008
        return p
    (m5, _, _), _ = _mark(mesh, pts(5), values, device, dtype)          # 5 < min_points_split
    assert not m5.any()
    (m6, _, _), _ = _mark(mesh, pts(6), values, device, dtype)          # 6 points: the max test applies
    assert m6.tolist() == [t == ul for t in range(6)]
    # rms statistic: mean 6.4e-5/6 < 1.6e-5 passes
    (mr, _, worst), _ = _mark(mesh, pts(6), values, device, dtype, statistic="rms")
    assert not mr.any()
    assert float(worst[0]) == pytest.approx(math.sqrt(0.008 ** 2 / 6), rel=1e-3)
    # few points but all far: the mean fails, marked from min_points_fit on
    far3 = cluster(-0.7, 0.15, 3, device, dtype)
    (mf, _, _), _ = _mark(mesh, far3, values, device, dtype)
    assert mf.tolist() == [t == ul for t in range(6)]
    (mf2, _, _), _ = _mark(mesh, far3[:2], values, device, dtype)     # 2 points: no evidence
    assert not mf2.any()
    # a large line-fit error (two strokes in one triangle) splits with few points
    eps = torch.zeros(6, device=device, dtype=dtype)
    eps[ul] = 0.02 ** 2
    near3 = cluster(-0.7, 0.1, 3, device, dtype)
    (mt, _, _), _ = _mark(mesh, near3, values, device, dtype, line_eps=eps)
    assert mt.tolist() == [t == ul for t in range(6)]
    (mt2, _, _), _ = _mark(mesh, near3, values, device, dtype, line_eps=eps, noise=0.01)   # 3 x 0.01 > 0.02
    assert not mt2.any()
    # too small to split at this tolerance: the longest edge (1) below min_split_size x tol
    far = cluster(-0.7, 0.15, 6, device, dtype)
    (ms, _, _), _ = _mark(mesh, far, values, device, dtype, min_split_size=200.0)     # 200 x 0.004 = 0.8 < 1
    assert ms.any()
    (ms2, _, _), _ = _mark(mesh, far, values, device, dtype, min_split_size=300.0)    # 1.2 > 1
    assert not ms2.any()


def test_triangle_errors_hand_values(device):
    mesh, _ = hex1_line(device, torch.float64)
    face = torch.tensor([0, 0, 0, 2, -1, 2], device=device)
    r = torch.tensor([1.0, 4.0, 7.0, 2.0, 100.0, 0.5], device=device, dtype=torch.float64)
    mx, mean = triangle_errors(mesh, r, face)
    assert mx.tolist() == [7.0, 0.0, 2.0, 0.0, 0.0, 0.0]
    assert mean.tolist() == [4.0, 0.0, 1.25, 0.0, 0.0, 0.0]


# ------------------------------------------------------------------ annealer tables and colouring


def fan_mesh(n, device, dtype):
    """One vertex joined to a ring of ``n`` (degree ``n``: the annealer's full-width table, more
    slots than its one-op sum takes)."""
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    v = torch.cat([torch.zeros(1, 2, dtype=torch.float64), torch.stack([t.cos(), t.sin()], 1)]).to(device, dtype)
    i = torch.arange(n)
    f = torch.stack([torch.zeros_like(i), 1 + i, 1 + (i + 1) % n], 1).to(device)
    return MeshBatch(v, f, torch.tensor([n + 1]), torch.tensor([n]))


def annealer_meshes(device, dtype):
    return MeshBatch.cat([hexagons(2, 4, device, dtype), fan_mesh(23, device, dtype),
                          square_mesh(torch.zeros(1, 2, device=device, dtype=dtype),
                                      torch.ones(1, device=device, dtype=dtype), 6), fan_mesh(11, device, dtype)])


def naive_neighbors(mesh):
    nb = defaultdict(list)
    for k, (i, j) in enumerate(mesh.edges.cpu().tolist()):
        nb[i].append((j, k))
        nb[j].append((i, k))
    return {v: sorted(x) for v, x in nb.items()}


def greedy_coloring_by_priority(mesh, active):
    """Sequential greedy colouring, highest hashed priority first (Python loop)."""
    from torch_isc.core.segments import mix32
    V = mesh.verts.shape[0]
    local = torch.arange(V) - mesh.verts_first_idx.cpu()[mesh.vert_item.cpu()]
    prio = (mix32(local * 2654435761 + 12345) * V + local).tolist()
    nb = naive_neighbors(mesh)
    act = active.cpu().tolist()
    col = [-1] * V
    for v in sorted(range(V), key=lambda v: -prio[v]):
        if act[v]:
            used = {col[u] for u, _ in nb.get(v, []) if col[u] >= 0}
            col[v] = next(c for c in range(V + 1) if c not in used)
    return col


@pytest.mark.parametrize("active_frac", [1.0, 0.7])
def test_vertex_coloring_is_the_priority_greedy(active_frac, device, monkeypatch):
    """The bounded rounds give the sequential greedy colouring, also when the first block of
    rounds is too short and more blocks follow."""
    import torch_isc.pipeline.signs as signs
    mesh = annealer_meshes(device, torch.float32)
    g = torch.Generator().manual_seed(3)
    active = (torch.rand(mesh.verts.shape[0], generator=g) < active_frac).to(device)
    want = greedy_coloring_by_priority(mesh, active)
    assert vertex_coloring(mesh, active).cpu().tolist() == want
    assert max(want) >= 3                                     # the fan centre needs a 4th colour or more
    monkeypatch.setattr(signs, "_COLOR_ROUNDS", 1)
    assert vertex_coloring(mesh, active).cpu().tolist() == want


@pytest.mark.parametrize("bag", [False, True])
@pytest.mark.parametrize("R, dt, fans", [(1, torch.float64, False), (3, torch.float64, False), (4, torch.float64, False),
                                         (4, torch.float32, False), (3, torch.float64, True), (4, torch.float32, True)])
def test_annealer_tables_give_the_local_fields(R, dt, fans, bag, device, monkeypatch):
    """The padded-gather fields of every colour class equal the neighbour sums: to rounding
    against a dense float64 product, and on the CPU bit for bit against the sum in neighbour
    order (the CSR order), rounded to the dtype at each step. Every free vertex is in exactly
    one class, no class holds an edge. With ``fans``, two adjacent wide vertices (degrees 28
    and 16, in different classes, each class's table as wide as its own largest degree). With
    ``bag``, the fields of one embedding bag per sweep (the layout off the CPU), the same bits."""
    from torch_isc.pipeline import signs
    from torch_isc.pipeline.signs import _color_layout
    monkeypatch.setitem(signs._FIELDS_BY_BAG, device.type, bag)
    mesh = annealer_meshes(device, dt)
    if fans:
        mesh = MeshBatch.cat([double_fan(device, dt), mesh])
    V = mesh.verts.shape[0]
    g = torch.Generator().manual_seed(R)
    H = (torch.rand(mesh.edges.shape[0], generator=g, dtype=torch.float64) * 2 - 1).to(device, dt)
    fixed = (mesh.is_boundary_vert.cpu() & (torch.rand(V, generator=g) < 0.5)).to(device)
    s, pos, classes, color, free = _color_layout(mesh, H, fixed, R)
    sv = torch.where(torch.rand(V, R, generator=g) < 0.5, -1.0, 1.0).to(device, dt)
    s[:, pos] = sv.T
    Wd = torch.zeros(V, V, dtype=torch.float64)
    e = mesh.edges.cpu()
    Wd[e[:, 0], e[:, 1]] = H.cpu().double()
    Wd[e[:, 1], e[:, 0]] = H.cpu().double()
    dense = (Wd @ sv.cpu().double()).to(dt)
    tol = 1e-12 if dt == torch.float64 else 1e-5
    nb = naive_neighbors(mesh)
    npdt = np.float64 if dt == torch.float64 else np.float32
    Hl, svl = H.cpu().numpy().astype(npdt), sv.cpu().numpy().astype(npdt)
    col_of = {c: v for v, c in enumerate(pos.cpu().tolist())}
    seen = []
    for cl in classes:
        f = cl.fields().cpu()
        verts = [col_of[c] for c in range(cl.a, cl.a + cl.width) if c in col_of]
        seen += verts
        cols = torch.tensor([int(pos[v]) - cl.a for v in verts])
        torch.testing.assert_close(f[:, cols].T, dense[verts], rtol=tol, atol=tol)
        # the in-order sum is what torch 2.13's AVX-512 CPU reduction does for these tables;
        # other vector widths block the sum differently (the fields still match to rounding)
        if device.type == "cpu" and torch.backends.cpu.get_cpu_capability() == "AVX512":
            for v, c in zip(verts, cols.tolist()):
                for r in range(R):
                    acc = npdt(0)
                    for u, k in nb[v]:
                        acc = npdt(acc + Hl[k] * svl[u, r])
                    assert float(f[r, c]) == float(acc)
        cset = set(verts)
        assert not any(u in cset for v in verts for u, _ in nb[v])
    assert sorted(seen) == sorted(free.cpu().tolist()) == (~fixed).nonzero().squeeze(1).cpu().tolist()


def csr_anneal(mesh, H, init, fixed, cfg, seed, warm):
    """The annealer as it was: colour classes by nonzero, a sparse CSR product per class."""
    import warnings
    from torch_isc.core.segments import hash_keys, hash_to_unit
    V, R, dt = mesh.verts.shape[0], cfg.anneal_replicas, H.dtype
    color = vertex_coloring(mesh, ~fixed)
    s = init.to(dt)[:, None].repeat(1, R)
    t0 = torch.full((R,), cfg.anneal_t_start, dtype=dt)
    if warm:
        s[:, 1:] = torch.where(fixed, init.to(dt), torch.ones_like(init, dtype=dt))[:, None]
        t0[0] = min(cfg.anneal_warm_t_start, cfg.anneal_t_start)
    ratio = (cfg.anneal_t_end / t0) ** (1.0 / max(cfg.anneal_sweeps - 1, 1))
    local = torch.arange(V) - mesh.verts_first_idx[mesh.vert_item]
    nb = naive_neighbors(mesh)
    groups = []
    for c in range(int(color.max()) + 1):
        g = (color == c).nonzero().squeeze(1)
        crow, cols, vals = [0], [], []
        for v in g.tolist():
            cols += [u for u, _ in nb[v]]
            vals += [float(H[k]) for _, k in nb[v]]
            crow.append(len(cols))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            W = torch.sparse_csr_tensor(torch.tensor(crow), torch.tensor(cols, dtype=torch.long),
                                        torch.tensor(vals, dtype=dt), size=(g.shape[0], V))
        h0 = hash_keys(torch.zeros(g.shape[0], R, dtype=torch.long), torch.full((g.shape[0], R), seed),
                       local[g][:, None].expand(-1, R), torch.arange(R)[None, :].expand(g.shape[0], -1))
        groups.append((g, W, h0))
    for k in range(cfg.anneal_sweeps + cfg.anneal_greedy_sweeps):
        for c, (g, W, h0) in enumerate(groups):
            sg = s[g]
            dE = -2.0 * sg * (W @ s)
            if k < cfg.anneal_sweeps:
                thr = -(t0 * ratio ** k) * torch.log(hash_to_unit(hash_keys(h0, torch.full_like(h0, 64 * k + c)), dt))
            else:
                thr = 0.0
            s[g] = torch.where(dE < thr, -sg, sg)
    E = ising_energy(mesh, H, s)
    return s.gather(1, torch.argmin(E, 1)[mesh.vert_item][:, None]).squeeze(1)


@pytest.mark.parametrize("dtype_, warm", [(torch.float32, False), (torch.float32, True), (torch.float64, True)])
def test_anneal_same_signs_as_csr_annealer(dtype_, warm):
    """Same random draws per vertex and sweep and the same field sums: the same signs."""
    mesh = annealer_meshes(torch.device("cpu"), dtype_)
    V = mesh.verts.shape[0]
    g = torch.Generator().manual_seed(11)
    H = (torch.rand(mesh.edges.shape[0], generator=g, dtype=torch.float64) * 2 - 1).to(dtype_)
    H[::7] = 0.0                                             # exact zero fields: the greedy sweeps' ties
    fixed = mesh.is_boundary_vert.clone()
    init = torch.where(fixed | (torch.rand(V, generator=g) < 0.5), 1.0, -1.0).to(dtype_)
    cfg = TopologyConfig(anneal_sweeps=30, anneal_replicas=3, anneal_greedy_sweeps=2)
    got = anneal(mesh, H, init, fixed, cfg, seed=4, warm=warm)
    want = csr_anneal(mesh, H, init, fixed, cfg, 4, warm)
    assert torch.equal(got, want)
    assert bool((got != init).any())                          # the annealer did flip signs


def double_fan(device, dtype, n=40, top=10, bottom=36):
    """Two adjacent interior vertices A, B, each the centre of a fan over part of a ring of
    ``n``: A of degree ``bottom - top + 2``, B of ``n - bottom + top + 2`` (different colours,
    full-width tables of different widths)."""
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    ring = 2.0 * torch.stack([t.cos(), t.sin()], 1)
    v = torch.cat([torch.tensor([[-0.5, 0.0], [0.5, 0.0]], dtype=torch.float64), ring]).to(device, dtype)
    A, B = 0, 1
    f = [[A, 2 + k, 2 + k + 1] for k in range(top, bottom)]
    f += [[B, 2 + k % n, 2 + (k + 1) % n] for k in range(bottom, top + n)]
    f += [[A, B, 2 + top], [B, A, 2 + bottom]]
    return MeshBatch(v, torch.tensor(f, device=device), torch.tensor([n + 2]), torch.tensor([len(f)]))


@pytest.mark.parametrize("bag", [False, True])
@pytest.mark.parametrize("dtype_", [torch.float32, torch.float64])
def test_anneal_tables_of_per_class_width_same_signs_as_csr(dtype_, bag, monkeypatch):
    """Full-width tables as wide as their own class's largest degree (28 with carries, 16, 11
    and 23 in one batch): the signs of the CSR annealer, bit for bit (also with the fields of
    an embedding bag, ``bag``)."""
    from torch_isc.pipeline import signs
    from torch_isc.pipeline.signs import vertex_coloring
    monkeypatch.setitem(signs._FIELDS_BY_BAG, "cpu", bag)
    mesh = MeshBatch.cat([double_fan(torch.device("cpu"), dtype_), annealer_meshes(torch.device("cpu"), dtype_)])
    assert bool((mesh.signed_areas() > 0).all())
    col = vertex_coloring(mesh, ~mesh.is_boundary_vert)
    deg = mesh.degrees
    assert deg[0] == 28 and deg[1] == 16 and col[0] != col[1]
    V = mesh.verts.shape[0]
    g = torch.Generator().manual_seed(3)
    H = (torch.rand(mesh.edges.shape[0], generator=g, dtype=torch.float64) * 2 - 1).to(dtype_)
    H[::5] = 0.0
    fixed = mesh.is_boundary_vert.clone()
    init = torch.where(fixed | (torch.rand(V, generator=g) < 0.5), 1.0, -1.0).to(dtype_)
    cfg = TopologyConfig(anneal_sweeps=30, anneal_replicas=3, anneal_greedy_sweeps=2)
    for warm in (False, True):
        got = anneal(mesh, H, init, fixed, cfg, seed=9, warm=warm)
        assert torch.equal(got, csr_anneal(mesh, H, init, fixed, cfg, 9, warm))
        assert bool((got != init).any())


@pytest.mark.parametrize("unfused_forms", [True, False])
@pytest.mark.parametrize("K", [1, 3])
def test_short_sums_and_row_adds_match_torch_bit_for_bit(K, unfused_forms, device, monkeypatch):
    """The objective's explicit short sums, its index_add and its gathers give the bits of
    torch's own (x.sum(-1) over 2 or 3, x.sum(-2) over 3, x.index_add(1, ...), x[:, index]),
    in float32 and float64, on random data with repeated indices."""
    from torch_isc.pipeline import optim
    from torch_isc.pipeline.values import _add_cols, _sum_last, _sum_rows, _take
    monkeypatch.setattr(optim, "UNFUSED_DEVICES", {device.type} if unfused_forms else set())

    def same(a, b):                                   # a GPU's reduction order is its own
        if device.type == "cpu":
            assert torch.equal(a, b)
        else:
            torch.testing.assert_close(a, b)
    g = torch.Generator().manual_seed(K)
    for dt in (torch.float32, torch.float64):
        for c in (2, 3):
            x = torch.randn(K, 257, c, generator=g, dtype=dt).to(device)
            same(_sum_last(x), x.sum(-1))
        y = torch.randn(K, 257, 3, 5, generator=g, dtype=dt).to(device)
        same(_sum_rows(y), y.sum(-2))
        z = torch.randn(K, 50, generator=g, dtype=dt).to(device)
        idx = torch.randint(0, 50, (400,), generator=g).to(device)
        src = torch.randn(K, 400, generator=g, dtype=dt).to(device)
        same(_add_cols(z, idx, src), z.index_add(1, idx, src))
        w = torch.randn(K, 50, 3, generator=g, dtype=dt).to(device)
        ix = torch.randint(0, 50, (7, 4), generator=g).to(device)
        assert torch.equal(_take(w, ix), w[:, ix]) and torch.equal(_take(z, ix), z[:, ix])


def test_objective_gives_the_same_bits_in_the_fused_and_unfused_forms(monkeypatch):
    """The CPU's unfused forms of the fit's objective (explicit short sums, one gradient
    component at a time) and the fused forms a GPU takes give the same objective and gradient
    bits on the CPU, for one point and for a stack of trials (smoothness and crossings on)."""
    from torch_isc.pipeline import optim
    obj, *_ = two_circle_objective(torch.device("cpu"), 0.3, 5.0)
    assert obj.cross and obj.smooth
    g = torch.Generator().manual_seed(7)
    s = obj.s0 + 0.4 * torch.randn(obj.s0.shape, generator=g, dtype=torch.float64)
    S3 = torch.stack([s, obj.s0, s - 0.2])
    out = {}
    for forms in ({"cpu"}, set()):
        monkeypatch.setattr(optim, "UNFUSED_DEVICES", forms)
        out[bool(forms)] = (obj.value_and_grad(s), obj.value_and_grad(S3))
    for a, b in zip(out[True], out[False]):
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_short_ops_script_reports_the_same_bits(capsys, monkeypatch):
    """scripts/benchmark_short_ops.py (the README's table of why the fit writes some ops out on a
    CPU): every written-out form it times gives the torch form's bits."""
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "scripts" / "benchmark_short_ops.py"
    spec = importlib.util.spec_from_file_location("benchmark_short_ops", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    monkeypatch.setattr("sys.argv", ["benchmark_short_ops.py", "--rows", "300", "--repeats", "1"])
    n = torch.get_num_threads()
    try:
        mod.main()
    finally:
        torch.set_num_threads(n)
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| `")]
    assert len(rows) == 4 and all(ln.rstrip().endswith("| yes |") for ln in rows)
