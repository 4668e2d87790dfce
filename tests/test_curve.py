"""Tests of torch_isc.core.curve: evaluation, gradients, zero sets, inside/outside, deformation.

Expected values come from analytic curves (linear functions, circles), hand-computed
interpolation, float64 linear solves, brute-force point location and autograd.gradcheck.
"""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torch_isc.core.curve import ImplicitCurve, InvalidValuesError, check_values
from torch_isc.core.mesh import InvalidMeshError, MeshBatch, hexagon_mesh, square_mesh

from conftest import brute_locate, find_intersections, polygon_signed_area, ref_bary64, winding_number

SQ3 = math.sqrt(3.0)


def hexm(r, device, dtype, center=(0.0, 0.0), radius=1.0):
    return hexagon_mesh(torch.tensor([center], device=device, dtype=dtype),
                        torch.tensor([radius], device=device, dtype=dtype), r)


def sqm(n, device, dtype, center=(0.0, 0.0), hw=1.0):
    return square_mesh(torch.tensor([center], device=device, dtype=dtype),
                       torch.tensor([hw], device=device, dtype=dtype), n)


def away_from_zero(vals, floor):
    return torch.where(vals.abs() < floor, torch.where(vals < 0, -floor, floor) * torch.ones_like(vals), vals)


def hex_support(p, center, radius):
    """max over the six apothem directions of <n, p - c>, divided by the apothem: 1 on the boundary."""
    ang = torch.tensor([math.radians(30 + 60 * k) for k in range(6)], dtype=torch.float64)
    nrm = torch.stack([ang.cos(), ang.sin()], 1)
    q = p.double().cpu() - torch.tensor(center, dtype=torch.float64)
    return (q @ nrm.T).max(1).values / (radius * SQ3 / 2)


def jiggled(mesh, amount, gen):
    v = mesh.verts.detach().double().cpu()
    e = mesh.edges.cpu()
    h = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1).min()
    d = (torch.rand(v.shape, generator=gen, dtype=torch.float64) * 2 - 1) * amount * h
    d[mesh.is_boundary_vert.cpu()] = 0
    while not bool((mesh.signed_areas((v + d).to(mesh.verts)) > 0).all()):
        d = d / 2
    return mesh.with_verts((v + d).to(mesh.verts))


# ----------------------------------------------------------------------------- values


@pytest.mark.parametrize("bad", [0.0, -0.0, float("nan"), float("inf"), float("-inf")])
@pytest.mark.parametrize("where", [0, 5, -1])
def test_invalid_values_raise(bad, where, device, dtype):
    m = hexm(2, device, dtype)
    vals = torch.linspace(0.5, 2.0, m.verts.shape[0], device=device, dtype=dtype)
    vals[where] = bad
    with pytest.raises(InvalidValuesError):
        ImplicitCurve(m, vals)
    with pytest.raises(InvalidValuesError):
        check_values(vals, m.verts.shape[0])
    c = ImplicitCurve(m, torch.ones_like(vals))
    with pytest.raises(InvalidValuesError):
        c.rescale(vals.abs() if bad == bad else vals)
    # InvalidValuesError is a ValueError
    assert issubclass(InvalidValuesError, ValueError)


def test_invalid_value_shapes_and_mesh(device, dtype):
    m = hexm(2, device, dtype)
    V = m.verts.shape[0]
    for vals in (torch.ones(V - 1), torch.ones(V + 1), torch.ones(V, 1), torch.ones(1, V)):
        with pytest.raises(InvalidValuesError):
            ImplicitCurve(m, vals.to(device, dtype))
    c = ImplicitCurve(m, torch.ones(V, device=device, dtype=dtype))
    with pytest.raises(InvalidValuesError):
        c.rescale(-torch.ones(V, device=device, dtype=dtype))
    with pytest.raises(InvalidValuesError):
        c.rescale(torch.ones(V - 1, device=device, dtype=dtype))
    f = m.faces.clone()
    f[0] = f[0, [1, 0, 2]]
    bad = MeshBatch(m.verts, f, m.verts_per_item, m.faces_per_item)
    with pytest.raises(InvalidMeshError):
        ImplicitCurve(bad, torch.ones(V, device=device, dtype=dtype))
    ImplicitCurve(bad, torch.ones(V, device=device, dtype=dtype), validate=False)   # explicitly skipped


# ----------------------------------------------------------------------------- evaluation


def test_eval_hand_computed(device, dtype):
    v = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], device=device, dtype=dtype)
    m = MeshBatch(v, torch.tensor([[0, 1, 2], [1, 3, 2]], device=device), torch.tensor([4]), torch.tensor([2]))
    c = ImplicitCurve(m, torch.tensor([1.0, -2.0, 3.0, -4.0], device=device, dtype=dtype))
    p = torch.tensor([[0.25, 0.25], [0.75, 0.75], [0.5, 0.5], [0.0, 0.0], [1.0, 1.0], [1.0, 0.5], [2.0, 2.0],
                      [-1e-3, 0.5]], device=device, dtype=dtype)
    # (.25,.25): bary (.5,.25,.25) in face 0 -> .5 - .5 + .75 = .75
    # (.75,.75): in (1,3,2) bary (.25,.5,.25) -> -.5 - 2 + .75 = -1.75
    # (.5,.5): on the diagonal, .5*(-2) + .5*3 = .5 from either face
    # (1, .5): on edge (1,3): .5*(-2) + .5*(-4) = -3 ; (2,2) and (-1e-3, .5) outside: +inf
    want = torch.tensor([0.75, -1.75, 0.5, 1.0, -4.0, -3.0, float("inf"), float("inf")], device=device, dtype=dtype)
    torch.testing.assert_close(c(p), want)
    assert c.inside(p).tolist() == [False, True, False, False, True, True, False, False]
    assert c.signs.tolist() == [1.0, -1.0, 1.0, -1.0]
    face, bary = c.locate(p)
    torch.testing.assert_close(c.eval_at(face[:6], bary[:6]), want[:6])


@pytest.mark.parametrize("kind", ["hex", "square"])
def test_linear_function_reproduced(kind, device, dtype):
    gen = torch.Generator().manual_seed(1)
    m = hexm(4, device, dtype) if kind == "hex" else sqm(5, device, dtype)
    m = jiggled(m, 0.4, gen)
    a, b, c0 = 1.3, -0.7, 0.21
    vals = a * m.verts[:, 0] + b * m.verts[:, 1] + c0
    assert bool((vals != 0).all())
    c = ImplicitCurve(m, vals)
    # face gradients are exactly (a, b)
    g = c.face_gradients()
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(g, torch.tensor([[a, b]], device=device, dtype=dtype).expand_as(g), rtol=tol, atol=tol)
    # f(p) = a x + b y + c at random points of the mesh
    rad = 0.85 * torch.rand(200, generator=gen, dtype=torch.float64).sqrt()   # inside the inscribed disc
    ang = 2 * math.pi * torch.rand(200, generator=gen, dtype=torch.float64)
    p = torch.stack([rad * ang.cos(), rad * ang.sin()], 1).to(device, dtype)
    f = c(p)
    torch.testing.assert_close(f, a * p[:, 0] + b * p[:, 1] + c0, rtol=tol, atol=tol)


def test_eval_against_brute_force(device, dtype):
    gen = torch.Generator().manual_seed(2)
    m = MeshBatch.cat([jiggled(hexm(3, device, dtype), 0.4, gen),
                       jiggled(sqm(4, device, dtype, center=(0.5, 0.0), hw=0.8), 0.4, gen)])
    vals = (torch.randn(m.verts.shape[0], generator=gen, dtype=torch.float64)).to(device, dtype)
    vals = away_from_zero(vals, 0.01)
    c = ImplicitCurve(m, vals)
    p = (torch.rand(300, 2, generator=gen, dtype=torch.float64) * 2.4 - 1.2).to(device, dtype)
    items = torch.randint(0, 2, (300,), generator=gen).to(device)
    f = c(p, items).double().cpu()
    ref = brute_locate(m.verts, m.faces, m.face_item.tolist(), p, items.tolist(), inside_tol=1e-9)
    V, F = m.verts.double().cpu(), m.faces.cpu()
    fv = vals.double().cpu()
    n_in = 0
    for n, (t, best, _) in enumerate(ref):
        if t < 0:
            if best < -1e-4:
                assert f[n] == float("inf")
            continue
        bc = torch.tensor(ref_bary64(V[F[t]].tolist(), p[n].tolist()), dtype=torch.float64)
        want = float((bc * fv[F[t]]).sum())
        assert abs(float(f[n]) - want) < (1e-4 if dtype == torch.float32 else 1e-10)
        n_in += 1
    assert n_in > 100
    # inside() matches the sign, outside points are not inside
    ins = c.inside(p, items).cpu()
    assert torch.equal(ins, f < 0)
    # at the vertices f is the nodal value and inside() is its sign
    fv_at = c(m.verts, m.vert_item)
    torch.testing.assert_close(fv_at, vals)
    assert torch.equal(c.inside(m.verts, m.vert_item), vals < 0)
    with pytest.raises(ValueError):
        c(p)                                                           # point_item required


def test_face_gradients_against_solve(device, dtype):
    gen = torch.Generator().manual_seed(3)
    m = jiggled(hexm(3, device, dtype, center=(2.0, -1.0), radius=1.5), 0.45, gen)
    vals = away_from_zero(torch.randn(m.verts.shape[0], generator=gen, dtype=torch.float64), 0.01).to(device, dtype)
    c = ImplicitCurve(m, vals)
    V, F, f = m.verts.double().cpu(), m.faces.cpu(), vals.double().cpu()
    A = torch.stack([V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]], 1)        # (T,2,2)
    rhs = torch.stack([f[F[:, 1]] - f[F[:, 0]], f[F[:, 2]] - f[F[:, 0]]], 1)
    ref = torch.linalg.solve(A, rhs)
    tol = 1e-3 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(c.face_gradients().double().cpu(), ref, rtol=tol, atol=tol)
    # autograd of f w.r.t. the point inside a triangle is the face gradient
    cent = m.verts[m.faces].mean(1).detach().requires_grad_(True)
    fc = c(cent)
    (g,) = torch.autograd.grad(fc.sum(), cent)
    torch.testing.assert_close(g.double().cpu(), ref, rtol=tol, atol=tol)


def interior_points(mesh, gen, n, lo=0.15):
    t = torch.randint(0, mesh.faces.shape[0], (n,), generator=gen)
    w = torch.rand(n, 3, generator=gen, dtype=torch.float64) + lo / (1 - 3 * lo)
    w = w / w.sum(1, keepdim=True)
    assert bool((w.min(1).values > 0.1).all())
    return (mesh.verts.detach()[mesh.faces[t]] * w[..., None].to(mesh.verts)).sum(1)


def test_eval_gradcheck():
    gen = torch.Generator().manual_seed(4)
    m = jiggled(hexm(2, "cpu", torch.float64), 0.3, gen)
    vals = away_from_zero(torch.randn(m.verts.shape[0], generator=gen, dtype=torch.float64), 0.1)
    p = interior_points(m, gen, 12)

    def f(verts, values, points):
        return ImplicitCurve(m.with_verts(verts), values, validate=False)(points)

    inputs = (m.verts.clone().requires_grad_(True), vals.clone().requires_grad_(True), p.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(f, inputs)
    # f is linear in the values: df/dF_i is the barycentric coordinate of vertex i
    c = ImplicitCurve(m, inputs[1])
    c(p[:1]).sum().backward()
    face, bary = c.locate(p[:1])
    g = inputs[1].grad
    torch.testing.assert_close(g[m.faces[face[0]]], bary[0])
    assert int((g != 0).sum()) == 3


def test_zero_set_gradcheck():
    gen = torch.Generator().manual_seed(5)
    m = jiggled(hexm(3, "cpu", torch.float64), 0.3, gen)
    vals = m.verts.norm(dim=1) - 0.55 + 0.05 * torch.randn(m.verts.shape[0], generator=gen, dtype=torch.float64)
    vals = away_from_zero(vals, 0.05)

    def pts(verts, values):
        return ImplicitCurve(m.with_verts(verts), values, validate=False).zero_set().points

    inputs = (m.verts.clone().requires_grad_(True), vals.clone().requires_grad_(True))
    assert pts(*inputs).shape[0] > 10
    assert torch.autograd.gradcheck(pts, inputs)


def test_zero_set_gradient_by_hand():
    # one triangle, values (-1, 1, 1): p = v0 + t (v1 - v0) with t = f0 / (f0 - f1)
    # dt/df0 = -f1 / (f0 - f1)^2 = -1/4, dt/df1 = f0 / (f0 - f1)^2 = -1/4
    v = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]], dtype=torch.float64, requires_grad=True)
    vals = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64, requires_grad=True)
    m = MeshBatch(v, torch.tensor([[0, 1, 2]]), torch.tensor([3]), torch.tensor([1]))
    p = ImplicitCurve(m, vals).zero_set().points
    torch.testing.assert_close(p.detach(), torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64))
    p[0, 0].backward()
    torch.testing.assert_close(vals.grad, torch.tensor([-0.5, -0.5, 0.0], dtype=torch.float64))
    # x of the first point = t * x1 (x0 = 0): d/dx1 = t = 1/2, d/dx0 = 1 - t = 1/2
    torch.testing.assert_close(v.grad, torch.tensor([[0.5, 0.0], [0.5, 0.0], [0.0, 0.0]], dtype=torch.float64))


# ----------------------------------------------------------------------------- zero sets


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("kind", ["hex", "square"])
def test_linear_function_single_chain(seed, kind, device, dtype):
    gen = torch.Generator().manual_seed(100 + seed)
    r = 3 + seed
    th = float(torch.rand(1, generator=gen)) * 2 * math.pi
    s = 0.5 + 2 * float(torch.rand(1, generator=gen))
    a, b = s * math.cos(th), s * math.sin(th)
    off = (float(torch.rand(1, generator=gen)) * 2 - 1) * 0.6 * s      # |c|/|(a,b)| < 0.6 < apothem
    if kind == "hex":
        m = hexm(r, device, dtype)
    else:
        m = sqm(r, device, dtype)
    vals = a * m.verts[:, 0] + b * m.verts[:, 1] + off
    assert bool((vals.abs() > 1e-6).all())
    c = ImplicitCurve(m, vals)
    assert c.num_components().tolist() == [1]
    pl = c.zero_set()
    assert len(pl) == 1 and not bool(pl.closed[0])
    p = pl.points.double().cpu()
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    # every point on the line a x + b y + c = 0
    assert float((a * p[:, 0] + b * p[:, 1] + off).abs().max()) / s < tol
    # both ends on the boundary of the mesh, the other points strictly inside
    if kind == "hex":
        sup = hex_support(p, (0.0, 0.0), 1.0)
    else:
        sup = p.abs().max(1).values
    assert abs(float(sup[0]) - 1) < tol and abs(float(sup[-1]) - 1) < tol
    assert bool((sup[1:-1] < 1 - 1e-7).all())
    # the chain advances monotonically along the line, with f < 0 on its left
    d = torch.tensor([-b, a], dtype=torch.float64)               # left of d is -grad: negative
    if float((p[-1] - p[0]) @ d) < 0:
        pytest.fail("chain runs with the positive side on its left")
    proj = p @ d
    assert bool((proj[1:] > proj[:-1]).all())
    # f vanishes at the extracted points
    assert float(c(pl.points).abs().max()) / s < 10 * tol


@pytest.mark.parametrize("r", [1, 2, 3])
def test_negative_centre_gives_ccw_loop(r, device, dtype):
    m = hexm(r, device, dtype, center=(0.5, -0.25), radius=2.0)
    ci = int((m.verts - torch.tensor([0.5, -0.25], device=device, dtype=dtype)).norm(dim=1).argmin())
    vals = torch.ones(m.verts.shape[0], device=device, dtype=dtype)
    vals[ci] = -1.0
    c = ImplicitCurve(m, vals)
    assert c.num_components().tolist() == [1]
    pl = c.zero_set()
    assert bool(pl.closed[0]) and pl.points.shape == (6, 2)
    assert polygon_signed_area(pl.points) > 0
    assert winding_number(pl.points, (0.5, -0.25)) == 1
    # the six points are the midpoints of the spokes: a hexagon of radius 1/r
    cen = torch.tensor([0.5, -0.25], dtype=torch.float64)
    q = pl.points.double().cpu() - cen
    torch.testing.assert_close(q.norm(dim=1), torch.full((6,), 1.0 / r, dtype=torch.float64), rtol=1e-5, atol=1e-5)
    ang = torch.atan2(q[:, 1], q[:, 0])
    steps = torch.remainder(torch.roll(ang, -1) - ang, 2 * math.pi)
    torch.testing.assert_close(steps, torch.full((6,), math.pi / 3, dtype=torch.float64), rtol=1e-5, atol=1e-5)
    assert bool(c.inside(torch.tensor([[0.5, -0.25]], device=device, dtype=dtype)))


def annulus_values(m, r_in=0.3, r_out=0.7):
    rr = m.verts.norm(dim=1)
    mid, half = (r_in + r_out) / 2, (r_out - r_in) / 2
    return away_from_zero((rr - mid).abs() - half, 1e-3)


def two_discs_values(m, c1=(-0.45, 0.0), c2=(0.45, 0.0), rad=0.25):
    v = m.verts
    d1 = (v - torch.tensor(c1, device=v.device, dtype=v.dtype)).norm(dim=1)
    d2 = (v - torch.tensor(c2, device=v.device, dtype=v.dtype)).norm(dim=1)
    return away_from_zero(torch.minimum(d1, d2) - rad, 1e-3)


def test_annulus_two_loops_hole_clockwise(device, dtype):
    m = hexm(10, device, dtype)
    c = ImplicitCurve(m, annulus_values(m))
    assert c.num_components().tolist() == [2]
    pl = c.zero_set()
    assert bool(pl.closed.all())
    areas = sorted((polygon_signed_area(p), p) for p in pl.polyline_list())
    (a_hole, hole), (a_out, outer) = areas[0], areas[1]
    assert a_hole < 0 < a_out                                    # hole clockwise, outer CCW
    assert abs(a_out - math.pi * 0.49) < 0.1 * math.pi * 0.49
    assert abs(-a_hole - math.pi * 0.09) < 0.2 * math.pi * 0.09
    assert winding_number(outer, (0.0, 0.0)) == 1 and winding_number(hole, (0.0, 0.0)) == -1
    assert float((outer.norm(dim=1) - 0.7).abs().max()) < 0.03
    assert float((hole.norm(dim=1) - 0.3).abs().max()) < 0.03
    pts = torch.tensor([[0.0, 0.0], [0.5, 0.0], [0.0, -0.5], [0.9, 0.0]], device=device, dtype=dtype)
    assert c.inside(pts).tolist() == [False, True, True, False]


def test_two_separated_regions(device, dtype):
    m = hexm(10, device, dtype)
    c = ImplicitCurve(m, two_discs_values(m))
    assert c.num_components().tolist() == [2]
    pl = c.zero_set()
    assert bool(pl.closed.all())
    loops = pl.polyline_list()
    for p in loops:
        assert polygon_signed_area(p) > 0
    w = sorted((winding_number(p, (-0.45, 0.0)), winding_number(p, (0.45, 0.0))) for p in loops)
    assert w == [(0, 1), (1, 0)]
    assert find_intersections([(p, True) for p in loops]) == []


def test_batch_components_and_indexing(device, dtype):
    ms = [hexm(10, device, dtype), hexm(10, device, dtype), hexm(2, device, dtype), sqm(4, device, dtype)]
    lin = ms[3].verts[:, 0] + 0.5 * ms[3].verts[:, 1] + 0.1
    vals = [annulus_values(ms[0]), two_discs_values(ms[1]), torch.ones(ms[2].verts.shape[0], device=device, dtype=dtype), lin]
    c = ImplicitCurve(MeshBatch.cat(ms), torch.cat(vals))
    assert c.num_components().tolist() == [2, 2, 0, 1]
    assert len(c) == c.num_items == 4
    zs = c.zero_set()
    assert zs.num_closed().tolist() == [2, 2, 0, 0] and zs.num_open().tolist() == [0, 0, 0, 1]
    for b in range(4):
        alone = ImplicitCurve(ms[b], vals[b])
        assert torch.equal(c[b].values, alone.values) and torch.equal(c[b].mesh.faces, alone.mesh.faces)
        za, zb = alone.zero_set(), c[b].zero_set()
        assert torch.equal(za.points, zb.points) and torch.equal(za.closed, zb.closed)
    assert torch.equal(c[-1].values, vals[3])
    # points of several items
    p = torch.tensor([[0.5, 0.0], [0.5, 0.0], [0.5, 0.0], [0.5, 0.0], [-0.45, 0.0]], device=device, dtype=dtype)
    it = torch.tensor([0, 1, 2, 3, 1], device=device)
    assert c.inside(p, it).tolist() == [True, True, False, False, True]


# ----------------------------------------------------------------------------- deformation


def corner_and_side(m):
    corner = m.is_corner_vert.nonzero().squeeze(1)
    side = (m.is_boundary_vert & ~m.is_corner_vert).nonzero().squeeze(1)
    return corner, side


@pytest.mark.parametrize("kind", ["hex", "square"])
def test_deform_refusals(kind, device, dtype):
    m = hexm(4, device, dtype, center=(1.0, 2.0), radius=3.0) if kind == "hex" else sqm(4, device, dtype, center=(1.0, 2.0), hw=3.0)
    cen = torch.tensor([1.0, 2.0], device=device, dtype=dtype)
    c = ImplicitCurve(m, annulus_values(m.with_verts((m.verts - cen) / 3)))
    V = m.verts
    corner, side = corner_and_side(m)
    assert corner.numel() == (6 if kind == "hex" else 4)
    h = 3.0 / 4                                                      # lattice spacing scale
    # an interior vertex pushed across its neighbours: inverted triangles
    inner = (~m.is_boundary_vert).nonzero().squeeze(1)
    i = int(inner[0])
    nv = V.clone()
    nv[i] += torch.tensor([2.5 * h, 0.3 * h], device=device, dtype=dtype)
    assert bool((m.signed_areas(nv) <= 0).any())
    with pytest.raises(InvalidMeshError, match="orientation"):
        c.deform(nv)
    # each corner moved slightly inward (the triangles stay positive)
    for k in corner.tolist():
        nv = V.clone()
        nv[k] += 0.05 * h * (cen - V[k]) / (cen - V[k]).norm()
        assert bool((m.signed_areas(nv) > 0).all())
        with pytest.raises(InvalidMeshError, match="corner"):
            c.deform(nv)
    # a side vertex moved off its side, inward and outward (perpendicular to the side)
    for k in side.tolist()[::3]:
        out = (V[k] - cen)
        if kind == "hex":
            ang = math.atan2(float(out[1]), float(out[0]))
            mid = (math.floor(ang / (math.pi / 3)) + 0.5) * math.pi / 3
            nrm = torch.tensor([math.cos(mid), math.sin(mid)], device=device, dtype=dtype)
        else:
            nrm = torch.where(out.abs() >= out.abs().max() - 1e-4, out.sign(), torch.zeros_like(out))
        for sgn in (-1.0, 1.0):
            nv = V.clone()
            nv[k] += sgn * 0.05 * h * nrm
            assert bool((m.signed_areas(nv) > 0).all())
            with pytest.raises(InvalidMeshError, match="boundary"):
                c.deform(nv)
    # NaN and wrong shape
    nv = V.clone()
    nv[int(inner[1])] = float("nan")
    with pytest.raises(InvalidMeshError):
        c.deform(nv)
    with pytest.raises(InvalidMeshError):
        c.deform(V[:-1])


@pytest.mark.parametrize("kind", ["hex", "square"])
def test_deform_accepts_sliding_along_side(kind, device, dtype):
    m = hexm(4, device, dtype, radius=2.0) if kind == "hex" else sqm(4, device, dtype, hw=2.0)
    c = ImplicitCurve(m, two_discs_values(m.with_verts(m.verts / 2)))
    V = m.verts
    corner, side = corner_and_side(m)
    nv = V.clone()
    h = 2.0 / 4
    for j, k in enumerate(side.tolist()):
        out = V[k]
        if kind == "hex":
            ang = math.atan2(float(out[1]), float(out[0]))
            mid = (math.floor(ang / (math.pi / 3)) + 0.5) * math.pi / 3
            tang = torch.tensor([-math.sin(mid), math.cos(mid)], device=device, dtype=dtype)
        else:
            tang = torch.where(out.abs() >= out.abs().max() - 1e-4, torch.zeros_like(out), torch.ones_like(out))
        nv[k] += (0.3 if j % 2 else -0.3) * h * tang
    assert bool((m.signed_areas(nv) > 0).all())
    d = c.deform(nv)
    assert d.mesh.verts is nv and d.values is c.values
    assert torch.equal(d.mesh.faces, m.faces)
    assert d.num_components().tolist() == c.num_components().tolist() == [2]
    # the curve moved with the mesh: the zero set is the same combinatorially, not geometrically
    z0, z1 = c.zero_set(), d.zero_set()
    assert torch.equal(z0.edge, z1.edge)
    # interior moves with autograd reach the vertex positions
    nv2 = nv.clone().requires_grad_(True)
    d2 = c.deform(nv2)
    d2(torch.tensor([[0.1, 0.05]], device=device, dtype=dtype)).sum().backward()
    assert nv2.grad is not None and int((nv2.grad.abs().sum(1) > 0).sum()) == 3


def test_rescale_keeps_signs_and_topology(device, dtype):
    m = hexm(8, device, dtype)
    vals = annulus_values(m)
    c = ImplicitCurve(m, vals)
    gen = torch.Generator().manual_seed(7)
    mags = (torch.rand(vals.shape[0], generator=gen, dtype=torch.float64) * 4.8 + 0.2).to(device, dtype)
    r = c.rescale(mags)
    assert torch.equal(r.signs, c.signs)
    torch.testing.assert_close(r.values.abs(), mags)
    assert r.num_components().tolist() == [2]
    assert not torch.equal(r.zero_set().points, c.zero_set().points)
    assert torch.equal(r.zero_set().edge, c.zero_set().edge)


# ----------------------------------------------------------------------------- property test


def random_field(m, gen, n_bumps):
    v = m.verts.detach().double().cpu()
    lo, hi = v.min(0).values, v.max(0).values
    f = torch.full((v.shape[0],), 0.3, dtype=torch.float64)
    for _ in range(n_bumps):
        cen = lo + (hi - lo) * torch.rand(2, generator=gen, dtype=torch.float64)
        w = (0.15 + 0.3 * float(torch.rand(1, generator=gen))) * float((hi - lo).max())
        amp = 1.5 * (1 if float(torch.rand(1, generator=gen)) < 0.7 else -1)
        f = f - amp * torch.exp(-((v - cen) ** 2).sum(1) / (w * w))
    scale = float(f.abs().max())
    return away_from_zero(f, 0.05 * scale)


def random_deformation(m, gen, amount, slide):
    v = m.verts.detach().double().cpu()
    e = m.edges.cpu()
    el = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1)
    h = torch.full((v.shape[0],), float("inf"), dtype=torch.float64)
    h = h.scatter_reduce(0, e[:, 0], el, "amin").scatter_reduce(0, e[:, 1], el, "amin")
    d = (torch.rand(v.shape, generator=gen, dtype=torch.float64) * 2 - 1) * amount * h[:, None]
    bv = m.is_boundary_vert.cpu()
    d[bv] = 0
    if slide:
        side = bv & ~m.is_corner_vert.cpu()
        t = m.boundary_edge_dir.double().cpu()
        d[side] = t[side] * ((torch.rand(int(side.sum()), generator=gen, dtype=torch.float64) * 2 - 1) * 0.45 * h[side])[:, None]
    s = 1.0
    while not bool((m.signed_areas((v + s * d).to(m.verts)) > 0).all()):
        s /= 2
        assert s > 1e-12
    return (v + s * d).to(m.verts)


def structure(pl):
    out = []
    for e, c in zip(torch.split(pl.edge.cpu(), pl.counts.tolist()), pl.closed.tolist()):
        seq = e.tolist()
        if c:
            k = seq.index(min(seq))
            seq = seq[k:] + seq[:k]
        out.append((tuple(seq), bool(c)))
    return sorted(out)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2 ** 31 - 1), kind=st.sampled_from(["hex", "square"]), res=st.integers(2, 6),
       n_bumps=st.integers(1, 4), amount=st.floats(0.05, 1.0), slide=st.booleans(), steps=st.integers(1, 3))
def test_random_deformations_keep_topology(seed, kind, res, n_bumps, amount, slide, steps, dtype):
    gen = torch.Generator().manual_seed(seed)
    m = hexm(res, "cpu", dtype, center=(0.3, -0.2), radius=1.7) if kind == "hex" else \
        sqm(res, "cpu", dtype, center=(0.3, -0.2), hw=1.2)
    c = ImplicitCurve(m, random_field(m, gen, n_bumps).to(dtype))
    n0 = c.num_components().tolist()
    s0 = structure(c.zero_set())
    assert find_intersections([(p, bool(k)) for p, k in zip(c.zero_set().polyline_list(), c.zero_set().closed)]) == []
    for _ in range(steps):
        nv = random_deformation(c.mesh, gen, amount, slide)
        c = c.deform(nv)                                              # must be accepted
        f = torch.exp((torch.rand(nv.shape[0], generator=gen, dtype=torch.float64) * 2 - 1) * math.log(5.0)).to(dtype)
        c = c.rescale(c.values.abs() * f)
        assert c.num_components().tolist() == n0
        pl = c.zero_set()
        assert structure(pl) == s0
        bad = find_intersections([(p, bool(k)) for p, k in zip(pl.polyline_list(), pl.closed)])
        assert bad == [], bad
    # the deformed mesh is still a valid ISC mesh
    c.mesh.validate()


@pytest.mark.slow
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2 ** 31 - 1), kind=st.sampled_from(["hex", "square"]), res=st.integers(2, 10),
       n_bumps=st.integers(1, 6), amount=st.floats(0.05, 1.5), slide=st.booleans(), steps=st.integers(1, 5))
def test_random_deformations_keep_topology_long(seed, kind, res, n_bumps, amount, slide, steps, dtype):
    test_random_deformations_keep_topology.hypothesis.inner_test(seed, kind, res, n_bumps, amount, slide, steps, dtype)
