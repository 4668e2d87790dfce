"""Evidence at the noise's scale (pipeline/evidence.py: ring_moments, scaled_moments, local_fits
with a noise level), against weighted unions of points computed point by point in numpy."""
import math

import numpy as np
import torch

from torch_isc.core.locate import locate_grid
from torch_isc.core.mesh import hexagon_mesh
from torch_isc.pipeline.evidence import (EvidenceConfig, local_fits, own_fits, ring_moments, scaled_moments,
                                         triangle_moments)


def setup(dtype, noise=0.02, n=400, seed=0):
    mesh = hexagon_mesh(torch.zeros(1, 2, dtype=dtype), torch.ones(1, dtype=dtype), 8)
    g = np.random.default_rng(seed)
    x = g.uniform(-0.7, 0.7, n)
    pts = np.stack([x, 0.1 + 0.05 * x + g.normal(0, noise, n)], 1)           # a noisy line
    p = torch.as_tensor(pts, dtype=dtype)
    face, bary = locate_grid(mesh, p, torch.zeros(n, dtype=torch.long))
    return mesh, pts, face, triangle_moments(mesh, p, face, bary)


def weighted_stats(P, w):
    W = w.sum()
    m = (w[:, None] * P).sum(0) / W
    d = P - m
    return W, m, (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) / W


def test_ring_moments_equal_corner_weighted_union_of_points():
    for dtype, atol in ((torch.float64, 1e-12), (torch.float32, 2e-5)):
        mesh, P, face, mom = setup(dtype)
        ring = ring_moments(mesh, mom)
        F = mesh.faces.numpy()
        fc = face.numpy()
        checked = 0
        for t in range(F.shape[0]):
            # weight of a point: how many corners its triangle shares with t (0..3)
            shared = np.array([len(set(F[t]) & set(F[s])) for s in range(F.shape[0])])
            w = shared[fc].astype(float)
            if w.sum() == 0:
                assert float(ring.count[t]) == 0
                continue
            W, m, C = weighted_stats(P, w)
            assert abs(float(ring.count[t]) - W) < 1e-6
            np.testing.assert_allclose(ring.centroid[t].double().numpy(), m, atol=atol)
            np.testing.assert_allclose(ring.scatter[t].double().numpy(), C, atol=atol)
            checked += 1
        assert checked > 20


def test_scaled_moments_widen_until_the_span_reaches_the_noise_widths():
    dtype = torch.float64
    noise = 0.02
    mesh, P, face, mom = setup(dtype, noise)
    T = mesh.faces.shape[0]
    cfg = EvidenceConfig(evidence_noise_widths=6.0, evidence_rings=3, evidence_line_widths=2.0)
    nz = torch.full((T,), noise, dtype=dtype)
    wide = scaled_moments(mesh, mom, nz, cfg)
    # the same rule by hand: ring k = k-fold ring_moments, the first that spans 6 noise widths
    rings = [mom]
    for _ in range(3):
        rings.append(ring_moments(mesh, rings[-1]))
    for t in range(T):
        if mom.count[t] == 0:
            continue
        k = 0
        while k < 3:
            lam = np.linalg.eigvalsh(rings[k].scatter[t].numpy())
            if 3 * lam[1] >= (6 * noise) ** 2:
                break
            lam1 = np.linalg.eigvalsh(rings[k + 1].scatter[t].numpy())
            if lam1[0] > max((2 * noise) ** 2, lam[0]):
                break
            k += 1
        np.testing.assert_allclose(wide.centroid[t].numpy(), rings[k].centroid[t].numpy(), atol=1e-12)
        np.testing.assert_allclose(wide.scatter[t].numpy(), rings[k].scatter[t].numpy(), atol=1e-12)


def test_wide_fits_cross_only_the_triangles_the_true_line_crosses():
    """A noisy band three noise widths around y = 0.1 + 0.05 x: with their own points nearly
    every non-empty triangle's line crosses it (the centroid is inside); fitted at the noise's
    scale, the lines cross where the true line does."""
    dtype = torch.float64
    noise = 0.03
    mesh, P, face, mom = setup(dtype, noise, n=1500, seed=3)
    cfg0 = EvidenceConfig()
    cfg = EvidenceConfig(evidence_noise_widths=8.0)
    own = own_fits(mesh, mom)
    narrow = local_fits(mesh, mom, own, cfg0, noise=torch.tensor([noise], dtype=dtype))
    wide = local_fits(mesh, mom, own, cfg, noise=torch.tensor([noise], dtype=dtype))
    tri = mesh.verts[mesh.faces].numpy()
    truth = tri[..., 1] - (0.1 + 0.05 * tri[..., 0])
    crossed = (truth.min(1) < 0) & (truth.max(1) > 0)
    fit = (mom.count >= 3).numpy()
    # centre of the band only: triangles near the mesh's rim see one side of the pool
    inner = np.abs(tri[..., 0]).max(1) < 0.5

    def agree(L):
        Lc = L.numpy()
        says = (Lc.min(1) < 0) & (Lc.max(1) > 0)
        sel = fit & inner
        return float((says[sel] == crossed[sel]).mean())

    a0, a1 = agree(narrow.L), agree(wide.L)
    assert a0 < 0.7 and a1 >= 0.9, (a0, a1)      # measured 0.56 and 0.92
    # without a noise level or with the knob at 0 nothing changes
    np.testing.assert_array_equal(narrow.L.numpy(), local_fits(mesh, mom, own, cfg).L.numpy())


def test_two_lines_split_a_strip_by_hand():
    """Points on x = 0.4 ± 0.05 (10 each) in one big triangle: the
    line fit is vertical through the centroid, the sides are the two lines, their offsets ∓0.05
    along the normal and their pooled variance 0 (noise 0.01: 10 noise widths apart). The apex
    (0.4, 2) lies between them: its product is negative, the other corners' positive."""
    from torch_isc.core.mesh import MeshBatch
    from torch_isc.pipeline.evidence import line_fits, two_line_evidence, two_lines, LineFits
    dtype = torch.float64
    v = torch.tensor([[-1.0, -1.0], [1.5, -1.0], [0.4, 2.0]], dtype=dtype)
    mesh = MeshBatch(v, torch.tensor([[0, 1, 2]]), torch.tensor([3]), torch.tensor([1]))
    y = torch.linspace(-0.8, 1.5, 10, dtype=dtype)
    pts = torch.cat([torch.stack([torch.full_like(y, 0.35), y], 1), torch.stack([torch.full_like(y, 0.45), y], 1)])
    face, bary = locate_grid(mesh, pts, torch.zeros(20, dtype=torch.long))
    assert (face == 0).all()
    mom = triangle_moments(mesh, pts, face, bary)
    L, eps, nrm = line_fits(mesh, mom)
    own = LineFits(L, eps, nrm)
    own.two = two_lines(mesh, mom, nrm, pts, face)
    assert own.two.n.tolist() == [[10.0, 10.0]]
    np.testing.assert_allclose(own.two.mean.numpy(), [[-0.05, 0.05]], atol=1e-12)
    np.testing.assert_allclose(own.two.var.numpy(), [0.0], atol=1e-12)
    assert abs(float(eps[0]) - 0.05 ** 2) < 1e-12                     # one line: residual 0.05²
    cfg = EvidenceConfig(two_line_separation=4.0)
    two, Q, var = two_line_evidence(mesh, own, torch.tensor([0.01], dtype=dtype), cfg)
    assert two.tolist() == [True]
    # by hand: corner offsets along the normal from the centroid x = 0.4
    off = (v[:, 0] - 0.4) * float(nrm[0, 0])
    np.testing.assert_allclose(Q[0].numpy(), ((off + 0.05) * (off - 0.05)).numpy(), atol=1e-12)
    assert (Q[0] < 0).tolist() == [False, False, True]
    # not two lines when 12 noise widths are asked for, nor with noise 0.04 (2.5 widths apart)
    assert not two_line_evidence(mesh, own, torch.tensor([0.01], dtype=dtype),
                                 EvidenceConfig(two_line_separation=12.0))[0].any()
    assert not two_line_evidence(mesh, own, torch.tensor([0.04], dtype=dtype), cfg)[0].any()
