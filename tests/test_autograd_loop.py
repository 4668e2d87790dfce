"""reconstruct / reconstruct_batch with points that require grad, and packed=True."""
import math

import torch

import torch_isc
from torch_isc import ImplicitCurve
from torch_isc.measures import area

D = torch.float64


def ellipse(n=100, a=1.5, b=1.0, c=(0.0, 0.0), noise=0.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=D) * (2 * math.pi / n)
    p = torch.stack([a * t.cos(), b * t.sin()], 1) + torch.tensor(c, dtype=D)
    return p + noise * torch.randn(p.shape, generator=g, dtype=D)


def test_reconstruct_area_gradient_matches_finite_differences_of_the_resolve():
    p0 = ellipse(100, noise=0.005)
    p = p0.clone().requires_grad_()
    res = torch_isc.reconstruct(p)
    assert res.curve.values.requires_grad
    # the outputs are those of the plain call
    plain = torch_isc.reconstruct(p0)
    assert torch.equal(res.curve.values.detach(), plain.curve.values)
    a = area(res.curve)
    (g,) = torch.autograd.grad(a.sum(), p)
    assert g.shape == p.shape and bool(torch.isfinite(g).all())
    # finite differences of the converged re-solve, mesh and signs frozen: the values are
    # F + F*(p) - F*(p0) (keep_values), so the derivative is dA/dF(F) . dF*/dp
    frozen = plain.curve
    F = frozen.values
    sm = torch_isc.ReconstructConfig().band.band_smoothness      # the refit of the band stage's mesh
    F0 = torch_isc.refit(frozen, p0, smoothness=sm).values

    def area_of(q):
        return float(area(ImplicitCurve(frozen.mesh, F + torch_isc.refit(frozen, q, smoothness=sm).values - F0)))

    eps = 1e-6
    gen = torch.Generator().manual_seed(1)
    idx = torch.randperm(200, generator=gen)[:12]
    for k in idx.tolist():
        i, j = divmod(k, 2)
        e = torch.zeros_like(p0)
        e[i, j] = eps
        fd = (area_of(p0 + e) - area_of(p0 - e)) / (2 * eps)
        assert abs(fd - float(g[i, j])) <= 1e-6 + 1e-4 * abs(fd), (i, j, fd, float(g[i, j]))
    # moving every point outward along its normal grows the area (by about the perimeter per unit)
    n = torch.stack([p0[:, 0] / 1.5 ** 2, p0[:, 1]], 1)
    n = n / n.norm(dim=1, keepdim=True)
    assert float((g * n).sum(1).min()) > 0


def test_reconstruct_batch_of_8_gradients_stay_in_their_item():
    B = 8
    sets = [ellipse(60 + 5 * b, 1.0 + 0.1 * b, 0.8, c=(3.0 * b, -b), noise=0.004, seed=b).requires_grad_()
            for b in range(B)]
    res = torch_isc.reconstruct_batch(sets)
    for k in (0, 3, 7):
        grads = torch.autograd.grad(area(res[k].curve).sum(), sets, allow_unused=True, retain_graph=True)
        for b, gb in enumerate(grads):
            if b == k:
                assert gb is not None and float(gb.abs().max()) > 0
            else:
                assert gb is None or float(gb.abs().max()) == 0.0
    # the same gradient as the item reconstructed alone
    k = 3
    (g_batch,) = torch.autograd.grad(area(res[k].curve).sum(), sets[k], retain_graph=True)
    pk = sets[k].detach().clone().requires_grad_()
    (g_alone,) = torch.autograd.grad(area(torch_isc.reconstruct(pk).curve).sum(), pk)
    assert torch.allclose(g_batch, g_alone, rtol=1e-6, atol=1e-9)


def test_no_grad_path_untouched():
    p = ellipse(80).requires_grad_()
    with torch.no_grad():
        r = torch_isc.reconstruct(p)
    assert not r.curve.values.requires_grad
    r2 = torch_isc.reconstruct(p.detach())
    assert torch.equal(r.curve.values, r2.curve.values)


def test_packed_results():
    sets = [ellipse(60, 1.0, 0.7), ellipse(70, 2.0, 1.0, c=(5.0, 1.0)), ellipse(50, 0.5, 0.5, c=(-3.0, 0.0))]
    results, curve = torch_isc.reconstruct_batch(sets, packed=True)
    assert isinstance(curve, ImplicitCurve) and curve.num_items == 3 and len(results) == 3
    for b, r in enumerate(results):
        assert torch.equal(curve[b].values, r.curve.values)
        assert torch.equal(curve[b].mesh.verts, r.curve.mesh.verts)
    assert torch.allclose(area(curve), torch.cat([area(r.curve) for r in results]))
    assert curve.num_components().tolist() == [1, 1, 1]
    assert torch_isc.reconstruct_batch([], packed=True) == ([], None)
