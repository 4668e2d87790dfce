"""The winding-number prior (pipeline/winding.py) and its field term in the Ising energy."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_isc.core.mesh import hexagon_mesh
from torch_isc.pipeline.signs import TopologyConfig, anneal, ising_energy
from torch_isc.pipeline.winding import (WindingPrior, knn, orient_normals, point_normals, winding_at, winding_field,
                                        winding_on_grid, winding_prior)


def circle(n, r, c=(0.0, 0.0), noise=0.0, seed=0, phase=0.3):
    g = torch.Generator().manual_seed(seed)
    t = phase + torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    p = torch.stack([r * torch.cos(t) + c[0], r * torch.sin(t) + c[1]], 1)
    return p + noise * torch.randn(n, 2, generator=g, dtype=torch.float64)


def test_winding_of_sampled_circle_against_analytic():
    """Analytic outward normals and arc lengths: w = 1 inside, 0 outside (the quadrature of
    Gauss's integral), away from the curve by a few smoothing lengths."""
    n, r = 400, 0.4
    p = circle(n, r)
    b = p / r * (2 * math.pi * r / n)
    prior = WindingPrior(p, torch.zeros(n, dtype=torch.long), b, torch.tensor([0.005], dtype=torch.float64),
                         torch.ones(1, dtype=torch.float64))
    g = torch.Generator().manual_seed(1)
    q = (torch.rand(2000, 2, generator=g, dtype=torch.float64) - 0.5) * 1.2
    rad = q.norm(dim=1)
    keep = (rad - r).abs() > 0.05
    w = winding_at(prior, q[keep], torch.zeros(int(keep.sum()), dtype=torch.long))
    truth = (rad[keep] < r).double()
    assert float((w - truth).abs().max()) < 0.01
    # on the curve: one half
    on = winding_at(prior, circle(16, r, phase=0.3 + math.pi / n), torch.zeros(16, dtype=torch.long))
    np.testing.assert_allclose(on.numpy(), 0.5, atol=0.02)


def test_normals_against_analytic_tangents():
    """PCA normals of a noisy circle are within a few degrees of the radial direction."""
    n, r, s = 500, 0.45, 0.005
    p = circle(n, r, noise=s, seed=3)
    nbr, d2 = knn(p, torch.zeros(n, dtype=torch.long), 12)
    # nearly every neighbour is among the true nearest (approximate: Morton candidates)
    D = torch.cdist(p, p)
    D.fill_diagonal_(float("inf"))
    kth = D.topk(12, largest=False).values[:, -1]
    assert bool((d2.sqrt() <= kth[:, None] + 1e-12).float().mean() > 0.95)
    nrm = point_normals(p, nbr, d2, smooth_rounds=2)
    radial = p / p.norm(dim=1, keepdim=True)
    ang = torch.rad2deg(torch.acos((nrm * radial).sum(1).abs().clamp(max=1)))
    assert float(ang.median()) < 3.0 and float(ang.max()) < 15.0


@pytest.mark.parametrize("noise", [0.0, 0.005, 0.01])
def test_nested_noisy_rings_get_opposite_orientations(noise):
    """An annulus: the outer ring's normals point away from the centre, the inner ring's toward
    it (the hole's boundary, nested once), and the winding is 1 in the ring, 0 in the hole and
    outside."""
    p1, p2 = circle(360, 0.45, noise=noise, seed=1), circle(240, 0.28, noise=noise, seed=2)
    p = torch.cat([p1, p2])
    item = torch.zeros(p.shape[0], dtype=torch.long)
    sig = torch.tensor([noise], dtype=torch.float64)
    o, a, piece, h, over = orient_normals(p, item, 1, sig)
    radial = p / p.norm(dim=1, keepdim=True)
    al = (o * radial).sum(1)
    assert float((al[:360] > 0).double().mean()) > 0.98
    assert float((al[360:] < 0).double().mean()) > 0.98
    assert float(over[0]) == 0.0
    prior = winding_prior(p, item, 1, sig)
    q = torch.tensor([[0.0, 0.0], [0.05, -0.1], [0.365, 0.0], [0.0, -0.365], [0.6, 0.6], [-0.55, 0.1]],
                     dtype=torch.float64)
    w = winding_at(prior, q, torch.zeros(6, dtype=torch.long))
    np.testing.assert_allclose(w.numpy(), [0, 0, 1, 1, 0, 0], atol=0.1)


def test_prior_is_batch_independent_and_ignores_outliers():
    """An item's prior does not depend on the other items; isolated points weigh nothing."""
    ring = circle(300, 0.4, noise=0.004, seed=5)
    g = torch.Generator().manual_seed(9)
    stray = (torch.rand(6, 2, generator=g, dtype=torch.float64) - 0.5) * 0.2      # in the hole
    other = circle(200, 0.3, c=(0.1, 0.0), noise=0.002, seed=6)
    alone = torch.cat([ring, stray])
    pts = torch.cat([other, alone])
    item = torch.cat([torch.zeros(200, dtype=torch.long), torch.ones(306, dtype=torch.long)])
    noise = torch.tensor([0.002, 0.004], dtype=torch.float64)
    pb = winding_prior(pts, item, 2, noise)
    p1 = winding_prior(alone, torch.zeros(306, dtype=torch.long), 1, noise[1:])
    assert torch.allclose(pb.b[200:], p1.b, atol=1e-12)
    assert float(pb.b[200 + 300:].abs().max()) == 0.0
    q = torch.tensor([[0.0, 0.0], [0.6, 0.0]], dtype=torch.float64)
    w = winding_at(p1, q, torch.zeros(2, dtype=torch.long))
    # the length per point is a kernel density within the neighbours' reach: under noise it runs
    # about 10% long (the winding inside about 1.1)
    np.testing.assert_allclose(w.numpy(), [1, 0], atol=0.12)
    f = winding_field(p1, q, torch.zeros(2, dtype=torch.long), 2.0)
    assert float(f[0]) > 1.8 and float(f[1]) < -1.8      # inside favours F = -1, outside F = +1


def test_anneal_with_field_finds_brute_force_minimum():
    """The field term: anneal minimizes Σ H F F + Σ g F (checked by enumeration), and the energy
    with a field equals the hand sum."""
    mesh = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), 1)
    V = mesh.verts.shape[0]
    fixed = mesh.is_boundary_vert.clone()
    g = torch.Generator().manual_seed(2)
    for trial in range(4):
        H = (torch.rand(mesh.edges.shape[0], generator=g, dtype=torch.float64) * 2 - 1) * 0.5
        field = (torch.rand(V, generator=g, dtype=torch.float64) * 2 - 1) * 2.0
        init = torch.ones(V, dtype=torch.float64)
        s = anneal(mesh, H, init, fixed, TopologyConfig(anneal_sweeps=100, anneal_replicas=8), seed=trial, field=field)
        e = mesh.edges
        hand = float((H * s[e[:, 0]] * s[e[:, 1]]).sum() + (field * s).sum())
        assert float(ising_energy(mesh, H, s, field)[0]) == pytest.approx(hand, abs=1e-12)
        free = (~fixed).nonzero().squeeze(1)
        n = free.shape[0]
        codes = torch.arange(2 ** n)
        bits = (codes[None, :] >> torch.arange(n)[:, None]) & 1
        S = init[:, None].repeat(1, 2 ** n)
        S[free] = (2 * bits - 1).double()
        Emin = float(ising_energy(mesh, H, S, field)[0].min())
        assert hand == pytest.approx(Emin, abs=1e-9)
        assert torch.equal(s[fixed], init[fixed])


def test_grid_winding_matches_the_exact_sum():
    """The field reads the winding from the piece-sign grid (bilinear): it agrees with the exact
    sum over the points, two items in one batch."""
    p = torch.cat([circle(300, 0.4, noise=0.005, seed=1), circle(200, 0.2, c=(0.3, 0.1), noise=0.005, seed=2)])
    item = torch.cat([torch.zeros(300, dtype=torch.long), torch.ones(200, dtype=torch.long)])
    pr = winding_prior(p, item, 2, torch.tensor([0.005, 0.005], dtype=torch.float64))
    g = torch.Generator().manual_seed(3)
    q = (torch.rand(3000, 2, generator=g, dtype=torch.float64) - 0.5) * 0.9
    qi = torch.randint(0, 2, (3000,), generator=g)
    q[qi == 1] = q[qi == 1] * 0.5 + torch.tensor([0.3, 0.1], dtype=torch.float64)
    exact, grid = winding_at(pr, q, qi), winding_on_grid(pr, q, qi)
    assert float((exact - grid).abs().median()) < 0.01
    assert float(((exact > 0.5) == (grid > 0.5)).double().mean()) > 0.99
