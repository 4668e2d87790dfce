"""refit: convergence, implicit gradient vs finite differences of the re-solve, batch isolation."""
import math

import torch

from torch_isc import ImplicitCurve, hexagon_mesh
from torch_isc.core.measures import area
from torch_isc.pipeline.refit import attach_point_gradients, refit

D = torch.float64


def circle_pts(n, r, c=(0.0, 0.0), phase=0.1, noise=0.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=D) * (2 * math.pi / n) + phase
    p = r * torch.stack([t.cos(), t.sin()], 1) + torch.tensor(c, dtype=D)
    return p + noise * torch.randn(p.shape, generator=g, dtype=D)


def base_curve(B=1, res=3):
    cen = torch.stack([torch.arange(B, dtype=D) * 3.0, torch.zeros(B, dtype=D)], 1)
    m = hexagon_mesh(cen, torch.ones(B, dtype=D), res)
    return ImplicitCurve(m, (m.verts - cen[m.vert_item]).norm(dim=1) - 0.4517), cen


def test_refit_converged_and_signs_kept():
    c, _ = base_curve()
    pts = circle_pts(30, 0.47, noise=0.005)
    r = refit(c, pts)
    assert torch.equal(r.signs, c.signs)
    # stationarity of the objective at the returned values (independent autograd gradient)
    from torch_isc.pipeline.refit import RefitProblem
    from torch_isc.core.locate import locate_grid, barycentric
    from torch_isc.pipeline.evidence import triangle_moments
    face, _ = locate_grid(c.mesh, pts, torch.zeros(30, dtype=torch.long))
    mom = triangle_moments(c.mesh, pts, face, barycentric(c.mesh.verts, c.mesh.faces, face, pts))
    pb = RefitProblem(c, mom.count, 1e-4, 1e-2, 1e-2, 0.02)
    s = torch.log(r.values.abs() - pb.floor).requires_grad_()
    (g,) = torch.autograd.grad(pb.energy(s, mom.M).sum(), s)
    assert float(g.abs().max()) < 1e-9
    # and it fits: the zero set moved out toward the points (area ~ pi 0.55^2, not pi 0.45^2)
    assert abs(float(area(r)) - math.pi * 0.47 ** 2) < 0.03


def test_refit_gradcheck_points():
    c, _ = base_curve()
    # 2-3 points per triangle (with one point a triangle's line is any line through it: the fit is
    # held only by the smoothness term, and a 1e-5 move can switch basins)
    pts = circle_pts(24, 0.452, noise=0.003).requires_grad_()
    assert torch.autograd.gradcheck(lambda p: refit(c, p).values, (pts,), eps=1e-6, atol=1e-5, rtol=1e-4)
    assert torch.autograd.gradcheck(lambda p: area(refit(c, p)), (pts,), eps=1e-6, atol=1e-8, rtol=1e-5)


def test_refit_batch_of_8_isolated():
    B = 8
    c, cen = base_curve(B)
    sets = [circle_pts(40 + 3 * b, 0.46 + 0.003 * b, c=tuple(cen[b].tolist()), noise=0.005, seed=b) for b in range(B)]
    pts = torch.cat(sets).requires_grad_()
    item = torch.repeat_interleave(torch.arange(B), torch.tensor([s.shape[0] for s in sets]))
    r = refit(c, pts, item)
    a = area(r)
    for k in (0, 5):
        (g,) = torch.autograd.grad(a[k], pts, retain_graph=True)
        assert float(g[item != k].abs().max()) == 0.0
        assert float(g[item == k].abs().max()) > 0
        # the same gradient as the item alone
        pk = sets[k].clone().requires_grad_()
        (gk,) = torch.autograd.grad(area(refit(c[k], pk))[0], pk)
        assert torch.allclose(g[item == k], gk, rtol=1e-7, atol=1e-10)


def test_attach_point_gradients_keeps_values():
    B = 3
    c, cen = base_curve(B)
    curves = [c[b] for b in range(B)]
    sets = [circle_pts(40, 0.47, c=tuple(cen[b].tolist()), noise=0.005, seed=b).requires_grad_() for b in range(B)]
    out = attach_point_gradients(curves, sets)
    for b in range(B):
        assert torch.equal(out[b].values.detach(), curves[b].values)
    a = area(out[1])
    a.sum().backward()
    for b in (0, 2):                      # the batched refit links them, with exactly zero gradient
        assert sets[b].grad is None or float(sets[b].grad.abs().max()) == 0.0
    # the gradient is the refit's
    p1 = sets[1].detach().clone().requires_grad_()
    (g,) = torch.autograd.grad(area(ImplicitCurve(curves[1].mesh, refit(curves[1], p1).values)).sum(), p1)
    # the same implicit Jacobian, contracted with d area / d values at the kept values
    v = curves[1].values.clone().requires_grad_()
    (dv,) = torch.autograd.grad(area(ImplicitCurve(curves[1].mesh, v)).sum(), v)
    rv = refit(curves[1], p1).values
    (g2,) = torch.autograd.grad((rv * dv).sum(), p1)
    assert torch.allclose(sets[1].grad, g2, rtol=1e-5, atol=1e-8)   # batched vs single solve: same optimum to ~1e-6
    # without requires_grad nothing happens
    plain = [s.detach() for s in sets]
    assert attach_point_gradients(curves, plain) == curves
