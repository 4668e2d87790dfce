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


# ----------------------------------------------------------------------------- the band stage's problem

def _band_problem(B=2, reg=1e-4, scale_reg=1.0, slack=0.0):
    """Items of different sizes (so different Hessian size classes): points near circles of
    radius 0.6, signs from a circle of 0.45 (the crossings lie far from the data: the crossing
    term is active), the loop's start (distances to the data)."""
    from torch_isc.core.locate import barycentric, locate_grid
    from torch_isc.pipeline.evidence import triangle_moments
    from torch_isc.pipeline.refit import RefitProblem
    from torch_isc.pipeline.values import vertex_data_distance, vertex_data_distance_near
    from torch_isc.core.mesh import MeshBatch
    meshes, sets = [], []
    for b in range(B):
        m = hexagon_mesh(torch.tensor([[3.0 * b, 0.0]], dtype=D), torch.ones(1, dtype=D), 3 + b)
        meshes.append(m)
        sets.append(circle_pts(40 + 10 * b, 0.6, c=(3.0 * b, 0.0), noise=0.01, seed=b))
    m = MeshBatch.cat(meshes) if B > 1 else meshes[0]
    pts = torch.cat(sets)
    item = torch.repeat_interleave(torch.arange(B), torch.tensor([s.shape[0] for s in sets]))
    face, _ = locate_grid(m, pts, item)
    mom = triangle_moments(m, pts, face, barycentric(m.verts, m.faces, face, pts))
    cen = torch.tensor([[3.0 * b, 0.0] for b in range(B)], dtype=D)
    signs = torch.where((m.verts - cen[m.vert_item]).norm(dim=1) < 0.45, -1.0, 1.0).to(D)
    init = vertex_data_distance(m, pts, face)
    near = vertex_data_distance_near(m, pts, face)
    tol = torch.full((B,), 0.02, dtype=D)
    sl = torch.full((B,), slack, dtype=D)
    pb = RefitProblem.geometry(m, mom.count, signs, init, tol, 0.02, 3.0, 1.0, near, sl, reg=reg, scale_reg=scale_reg)
    return pb, m, mom, signs, init, tol, near, sl


def test_band_problem_is_the_loops_objective_with_exact_derivatives():
    """RefitProblem.geometry against an independent implementation: its objective (reg terms
    off) equals GeometryObjective.value (the loop's, plain tensor code), its gradient and its
    Hessian (assembled in per-item blocks of two size classes) equal autograd's in float64."""
    from torch_isc.pipeline.values import GeometryConfig, GeometryObjective
    pb, m, mom, signs, init, tol, near, sl = _band_problem(reg=0.0, scale_reg=0.0)
    assert len(pb.groups) == 2 and pb.cross is not None
    obj = GeometryObjective(m, mom, signs, init, tol, GeometryConfig(smoothness=3.0), near, sl)
    assert obj.cross and torch.equal(obj.s0, pb.s0)
    g0 = torch.Generator().manual_seed(0)
    s = obj.s0 + 0.3 * torch.randn(obj.s0.shape, generator=g0, dtype=D)
    E, g, H = pb.terms(s, mom.M[pb.act], hessian=True)
    assert torch.allclose(E, obj.value(s), rtol=1e-13, atol=0)
    # the crossing term is active: without it the objective differs
    assert float((obj.value(s) - GeometryObjective(m, mom, signs, init, tol, GeometryConfig(smoothness=3.0)).value(s)).abs().min()) > 1e-6
    sr = s.clone().requires_grad_()
    (ga,) = torch.autograd.grad(obj.value(sr).sum(), sr)
    assert torch.allclose(g, ga, rtol=1e-12, atol=1e-14)
    Ha = torch.autograd.functional.hessian(lambda x: obj.value(x).sum(), s)
    for its, Hg, vs in pb._views(H):
        for j, b in enumerate(its.tolist()):
            sel = pb.av_item == b
            v, loc = pb.av[sel], pb.av_loc[sel]
            assert torch.allclose(Hg[j][loc[:, None], loc[None, :]], Ha[v[:, None], v[None, :]], rtol=1e-11, atol=1e-12)
            pad = torch.ones(Hg.shape[1], dtype=torch.bool)
            pad[loc] = False
            assert torch.equal(Hg[j][pad][:, pad], torch.eye(int(pad.sum()), dtype=D))   # identity padding
    inactive = torch.ones(s.shape[0], dtype=torch.bool)
    inactive[pb.av] = False
    assert float(Ha[inactive].abs().max()) == 0.0 and float(ga[inactive].abs().max()) == 0.0


def test_band_newton_converges_to_a_kkt_point_item_by_item():
    """The projected Newton solve ends at a first-order point of the bound-constrained problem
    (autograd's gradient: ~0 at free vertices, >= 0 where s sits on its lower bound), before
    the cap, and each item's solution is the one it gets alone."""
    pb, m, mom, signs, init, tol, near, sl = _band_problem()
    s = pb.solve(mom.M, 100)
    assert bool(pb.converged.all()) and pb.iterations < 100
    sr = s.clone().requires_grad_()
    (g,) = torch.autograd.grad(pb.energy(sr, mom.M).sum(), sr)
    at = s <= pb.lower
    assert float(g[~at].abs().max()) < 1e-9
    assert bool((g[at] >= -1e-12).all())
    E = pb.energy(s, mom.M)
    for d in (1e-3, -1e-3):                      # and it is a minimum along random feasible moves
        g1 = torch.Generator().manual_seed(int(d > 0))
        t = torch.maximum(s + d * torch.randn(s.shape, generator=g1, dtype=D), pb.lower)
        assert bool((pb.energy(t, mom.M) >= E - 1e-14).all())
    pb1, m1, mom1, *_ = _band_problem(B=1)
    s1 = pb1.solve(mom1.M, 100)
    k = m.vert_item == 0
    assert torch.allclose(pb.values(s)[k], pb1.values(s1), rtol=1e-10, atol=1e-14)
