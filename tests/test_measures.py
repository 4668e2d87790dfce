"""Measures against analytic shapes, independent routes and gradcheck (float64)."""
import math

import pytest
import torch
from conftest import polygon_signed_area

from torch_isc import ImplicitCurve, hexagon_mesh, square_mesh
from torch_isc.core.measures import area, centroid, curvature, length, point_curve_distance

D = torch.float64


def square_curve(device, dtype, hw=0.6, shift=(0.0, 0.0), n=4):
    m = square_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device), n)
    return ImplicitCurve(m, (m.verts - torch.tensor(shift, device=device, dtype=dtype)).abs().amax(1) - hw)


def test_square_area_length_exact(device, dtype, tol):
    # corner cells of square_mesh(4) have their diagonal through the square's corners: the zero
    # set is exactly the square |x|,|y| < 0.6
    c = square_curve(device, dtype)
    rt, at = tols = tol
    assert torch.allclose(area(c), torch.tensor([1.44], device=device, dtype=dtype), rtol=rt, atol=at)
    assert torch.allclose(length(c), torch.tensor([4.8], device=device, dtype=dtype), rtol=rt, atol=at)


def test_halfplane_linear_values(device, dtype, tol):
    m = square_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device), 5)
    c = ImplicitCurve(m, m.verts[:, 0] - 0.3 * m.verts[:, 1] - 0.17)   # linear: zero set the line x = 0.3y + 0.17
    # region x < 0.3 y + 0.17 of [-1,1]^2: a trapezoid, area 2 * (0.17 + 1) = 2.34, centroid by hand
    rt, at = tol
    assert torch.allclose(area(c), torch.tensor([2.34], device=device, dtype=dtype), rtol=rt, atol=at)
    assert torch.allclose(length(c), torch.tensor([2 * math.sqrt(1 + 0.09)], device=device, dtype=dtype), rtol=rt, atol=at)
    # centroid of the trapezoid with x-extent a(y) = 1.17 + 0.3y for y in [-1,1]
    ys = torch.linspace(-1, 1, 200001, dtype=D)
    a = 1.17 + 0.3 * ys
    cx = float(((-1 + a / 2) * a).sum() / a.sum())
    cy = float((ys * a).sum() / a.sum())
    assert torch.allclose(centroid(c).double().cpu(), torch.tensor([[cx, cy]], dtype=D), atol=1e-5 if dtype == torch.float32 else 1e-8)


def test_area_matches_polygon_of_zero_set(device, dtype):
    # independent route: shoelace area of the extracted closed loops (outer CCW, holes CW)
    m = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device), 10)
    v = m.verts
    vals = torch.minimum((v - torch.tensor([-0.3, 0.1], device=device, dtype=dtype)).norm(dim=1) - 0.4517,
                         (v - torch.tensor([0.5, -0.1], device=device, dtype=dtype)).norm(dim=1) - 0.2513)
    vals = torch.maximum(vals, -(v - torch.tensor([-0.3, 0.1], device=device, dtype=dtype)).norm(dim=1) + 0.2213)  # a hole
    vals = torch.where(vals.abs() < 1e-3, torch.full_like(vals, 1e-3), vals)
    c = ImplicitCurve(m, vals)
    pl = c.zero_set()
    assert bool(pl.closed.all()) and len(pl) == 3
    ref = sum(polygon_signed_area(p) for p in pl.polyline_list())
    lref = sum(float((p - torch.roll(p, -1, 0)).norm(dim=1).sum()) for p in pl.polyline_list())
    rt = 1e-5 if dtype == torch.float32 else 1e-12
    assert abs(float(area(c)) - ref) <= rt * abs(ref)
    assert abs(float(length(c)) - lref) <= rt * lref
    # centroid: shoelace first moments
    mx = my = 0.0
    for p in pl.polyline_list():
        p = p.double().cpu(); q = torch.roll(p, -1, 0)
        cr = p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]
        mx += float(((p[:, 0] + q[:, 0]) * cr).sum()) / 6; my += float(((p[:, 1] + q[:, 1]) * cr).sum()) / 6
    assert torch.allclose(centroid(c).double().cpu(), torch.tensor([[mx / ref, my / ref]], dtype=D),
                          atol=1e-5 if dtype == torch.float32 else 1e-11)


def test_batch_packed_equals_items(device):
    m = hexagon_mesh(torch.tensor([[0.0, 0.0], [3.0, 1.0], [-2.0, 5.0]], device=device, dtype=D),
                     torch.tensor([1.0, 2.0, 0.5], device=device, dtype=D), 4)
    cen = torch.tensor([[0.1, 0.0], [3.2, 1.1], [-2.0, 5.1]], device=device, dtype=D)
    rad = torch.tensor([0.5, 1.1, 0.2], device=device, dtype=D)
    vals = (m.verts - cen[m.vert_item]).norm(dim=1) - rad[m.vert_item]
    c = ImplicitCurve(m, vals)
    for fn in (area, length, centroid):
        whole = fn(c)
        for b in range(3):
            assert torch.allclose(whole[b], fn(c[b])[0], rtol=1e-13, atol=1e-13)


def test_circle_curvature_fine_mesh(device):
    r = 0.5017
    m = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=D), torch.ones(1, device=device), 40)
    c = ImplicitCurve(m, m.verts.norm(dim=1) - r)
    pl = c.zero_set()
    P = pl.points
    ell = 0.5 * ((P - torch.roll(P, 1, 0)).norm(dim=1) + (torch.roll(P, -1, 0) - P).norm(dim=1))
    for method in ("turning", "circle"):
        k = curvature(c, method=method)
        assert k.shape[0] == P.shape[0]
        assert abs(float((k * ell).sum() / ell.sum()) - 1 / r) < 0.02 / r
        assert abs(float(k.median()) - 1 / r) < 0.05 / r
    # turning angles of a CCW loop add up to 2 pi exactly
    assert abs(float((curvature(c) * ell).sum()) - 2 * math.pi) < 1e-10
    # area / length of the circle to O(h^2)
    assert abs(float(area(c)) - math.pi * r * r) < 2e-3
    assert abs(float(length(c)) - 2 * math.pi * r) < 5e-3


def test_curvature_hand_values(device):
    # a regular hexagon of circumradius 1/2 (hexagon_mesh(1), centre negative): Menger curvature 2
    m = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=D), torch.ones(1, device=device), 1)
    vals = torch.ones(7, device=device, dtype=D); vals[3] = -1
    assert torch.allclose(curvature(ImplicitCurve(m, vals), method="circle"), torch.full((6,), 2.0, device=device, dtype=D))
    assert torch.allclose(curvature(ImplicitCurve(m, vals)), torch.full((6,), 4 * math.pi / 6, device=device, dtype=D))
    # a hole runs clockwise: negative curvature
    assert torch.allclose(curvature(ImplicitCurve(m, -vals), method="circle"), torch.full((6,), -2.0, device=device, dtype=D))
    # straight open chain: zero everywhere (ends by convention)
    sq = square_mesh(torch.zeros(1, 2, device=device, dtype=D), torch.ones(1, device=device), 4)
    k = curvature(ImplicitCurve(sq, sq.verts[:, 0] - 0.3))
    assert torch.allclose(k, torch.zeros_like(k), atol=1e-12)


def brute_distance(segs_a, segs_b, p):
    best = float("inf")
    for a, b in zip(segs_a.tolist(), segs_b.tolist()):
        ax, ay = a; bx, by = b
        dx, dy = bx - ax, by - ay
        t = max(0.0, min(1.0, ((p[0] - ax) * dx + (p[1] - ay) * dy) / (dx * dx + dy * dy)))
        best = min(best, math.hypot(p[0] - ax - t * dx, p[1] - ay - t * dy))
    return best


def test_point_curve_distance_brute_force(device):
    m = hexagon_mesh(torch.tensor([[0.0, 0.0], [5.0, 0.0]], device=device, dtype=D),
                     torch.ones(2, device=device, dtype=D), 5)
    cen = torch.tensor([[0.1, 0.0], [5.0, 0.2]], device=device, dtype=D)
    vals = (m.verts - cen[m.vert_item]).norm(dim=1) - torch.tensor([0.5017, 0.3013], device=device, dtype=D)[m.vert_item]
    c = ImplicitCurve(m, vals)
    g = torch.Generator().manual_seed(1)
    pts = (torch.rand(60, 2, generator=g, dtype=D) * 3 - 1.5)
    item = torch.arange(60) % 2
    pts = (pts + torch.tensor([5.0, 0.0], dtype=D) * item[:, None]).to(device)
    d = point_curve_distance(c, pts, item.to(device))
    pl = c.zero_set()
    for b in range(2):
        poly = [p for p, it in zip(pl.polyline_list(), pl.item.tolist()) if it == b]
        P = torch.cat(poly).cpu(); Q = torch.roll(P, -1, 0)
        for n in (item == b).nonzero().squeeze(1).tolist():
            assert abs(float(d[n]) - brute_distance(P, Q, pts[n].tolist())) < 1e-12


def test_no_curve_distance_inf(device):
    m = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=D), torch.ones(1, device=device), 2)
    c = ImplicitCurve(m, torch.ones(m.verts.shape[0], device=device, dtype=D))
    assert torch.isinf(point_curve_distance(c, torch.zeros(2, 2, device=device, dtype=D))).all()
    assert float(area(c)) == 0 and float(length(c)) == 0


def _gc_setup():
    m = hexagon_mesh(torch.zeros(1, 2, dtype=D), torch.ones(1, dtype=D), 3)
    g = torch.Generator().manual_seed(3)
    verts = (m.verts + 0.03 * torch.randn(m.verts.shape, generator=g, dtype=D)).detach()
    vals = ((verts - torch.tensor([0.05, -0.02], dtype=D)).norm(dim=1) - 0.45
            + 0.02 * torch.randn(verts.shape[0], generator=g, dtype=D)).detach()
    return m, verts, vals


@pytest.mark.parametrize("fn", [area, length, centroid, curvature, lambda c: curvature(c, method="circle")])
def test_measures_gradcheck(fn):
    m, verts, vals = _gc_setup()
    verts.requires_grad_(); vals.requires_grad_()
    f = lambda v, f_: fn(ImplicitCurve(m.with_verts(v), f_, validate=False))  # noqa: E731
    assert torch.autograd.gradcheck(f, (verts, vals), eps=1e-6, atol=1e-6)


def test_distance_gradcheck():
    m, verts, vals = _gc_setup()
    g = torch.Generator().manual_seed(4)
    pts = (torch.rand(15, 2, generator=g, dtype=D) * 1.6 - 0.8)
    verts.requires_grad_(); vals.requires_grad_(); pts.requires_grad_()
    f = lambda v, f_, p: point_curve_distance(ImplicitCurve(m.with_verts(v), f_, validate=False), p)  # noqa: E731
    assert torch.autograd.gradcheck(f, (verts, vals, pts), eps=1e-6, atol=1e-6)


def test_area_gradient_is_boundary_integral():
    # d area / d value: independent route, perturb the values and re-measure the shoelace area
    m, verts, vals = _gc_setup()
    v = vals.clone().requires_grad_()
    c = ImplicitCurve(m.with_verts(verts), v)
    (g,) = torch.autograd.grad(area(c).sum(), v)
    for i in g.abs().argsort(descending=True)[:5].tolist():
        e = torch.zeros_like(vals); e[i] = 1e-6
        ap = sum(polygon_signed_area(p) for p in ImplicitCurve(m.with_verts(verts), vals + e).zero_set().polyline_list())
        am = sum(polygon_signed_area(p) for p in ImplicitCurve(m.with_verts(verts), vals - e).zero_set().polyline_list())
        assert abs((ap - am) / 2e-6 - float(g[i])) < 1e-6
