"""Safe motion (deform clamp=True), band refinement and simple-vertex flips."""
import pytest
import torch

from torch_isc import ImplicitCurve, InvalidMeshError, hexagon_mesh, square_mesh
from torch_isc.core.measures import area, length, point_curve_distance

D = torch.float64


def make(kind, res, device, dtype=D, B=1):
    c = torch.zeros(B, 2, device=device, dtype=dtype)
    r = torch.ones(B, device=device, dtype=dtype)
    m = hexagon_mesh(c, r, res) if kind == "hex" else square_mesh(c, r, res)
    vals = (m.verts - torch.tensor([0.05, 0.02], device=device, dtype=dtype)).norm(dim=1) - 0.4517
    return ImplicitCurve(m, vals)


def first_flat_t(mesh, disp, n=20001):
    """Independent route: scan t in [0, 1.2] for the first t with a non-positive determinant."""
    ts = torch.linspace(0, 1.2, n, dtype=D)
    for t in ts.tolist():
        if bool((mesh.signed_areas(mesh.verts + t * disp) <= 0).any()):
            return t
    return float("inf")


@pytest.mark.parametrize("kind", ["hex", "square"])
def test_clamp_fraction_matches_scan(kind):
    c = make(kind, 3, "cpu")
    g = torch.Generator().manual_seed(5)
    disp = 0.6 * torch.randn(c.mesh.verts.shape, generator=g, dtype=D)
    disp = c.admissible_displacement(disp)
    moved, t = c.deform(c.mesh.verts + disp, clamp=True, safety=0.9)
    tf = first_flat_t(c.mesh, disp)
    assert tf < 1 / 0.9                       # the move is big enough to be clamped
    assert abs(float(t) / 0.9 - tf) < 1.2 / 20000 + 1e-9
    assert bool((moved.mesh.signed_areas() > 0).all())


def test_boundary_slides_corners_fixed(device):
    c = make("square", 4, device)
    m = c.mesh
    disp = 0.05 * torch.randn(m.verts.shape, device=device, dtype=D)
    moved, t = c.deform(m.verts + disp, clamp=True)
    mv = moved.mesh.verts - m.verts
    assert float(mv[m.is_corner_vert].abs().max()) == 0
    side = m.is_boundary_vert & ~m.is_corner_vert
    d = m.boundary_edge_dir
    off = (mv[:, 0] * d[:, 1] - mv[:, 1] * d[:, 0])[side]
    assert float(off.abs().max()) < 1e-15
    assert float(mv[side].abs().max()) > 0           # they do slide
    # the clamped result passes the strict check
    c.deform(moved.mesh.verts)


def test_per_item_fraction_independent(device):
    c = make("hex", 3, device, B=3)
    m = c.mesh
    g = torch.Generator().manual_seed(1)
    disp = torch.randn(m.verts.shape, generator=g, dtype=D).to(device)
    scale = torch.tensor([1e-3, 2.0, 0.3], device=device, dtype=D)[m.vert_item]
    disp = disp * scale[:, None]
    _, t = c.deform(m.verts + disp, clamp=True)
    assert float(t[0]) == 1.0 and float(t[1]) < 1.0
    for b in range(3):
        _, tb = c[b].deform(c[b].mesh.verts + disp[m.vert_item == b], clamp=True)
        assert float(tb) == float(t[b])
    # a non-finite displacement freezes its item only
    d2 = disp.clone(); d2[m.vert_item == 2] = float("nan")
    mv, t2 = c.deform(m.verts + d2, clamp=True)
    assert float(t2[2]) == 0 and torch.isfinite(mv.mesh.verts).all() and float(t2[0]) == 1.0


def test_strict_still_raises(device):
    c = make("hex", 2, device)
    v = c.mesh.verts.clone(); v[c.mesh.is_corner_vert.nonzero()[0]] += 0.1
    with pytest.raises(InvalidMeshError, match="corner"):
        c.deform(v)


def test_adam_loop_never_breaks():
    # push the curve hard (grow the area, with a strong step) through the vertex positions
    c = make("hex", 4, "cpu")
    verts = c.mesh.verts.clone().requires_grad_()
    opt = torch.optim.Adam([verts], lr=0.2)
    cur = c
    clamped = 0
    for _ in range(150):
        opt.zero_grad()
        new, t = cur.deform(verts, clamp=True)
        noise = torch.randn(verts.shape, dtype=D)           # a noisy objective, as in training loops
        loss = -area(new).sum() + length(new).sum() * 0.1 + (new.mesh.verts * noise).sum()
        loss.backward()
        opt.step()
        with torch.no_grad():                            # the step, made safe
            cur, t = cur.deform(verts.detach(), clamp=True)
            clamped += int(float(t) < 1)
            verts.copy_(cur.mesh.verts)
        assert bool((cur.mesh.signed_areas() > 0).all())
        assert cur.num_components().tolist() == [1]
    assert clamped > 0                               # the clamp was exercised


def test_deform_gradcheck_unclamped():
    c = make("hex", 2, "cpu")
    g = torch.Generator().manual_seed(0)
    v = (c.mesh.verts + 1e-3 * torch.randn(c.mesh.verts.shape, generator=g, dtype=D)).requires_grad_()
    f = lambda x: area(c.deform(x, clamp=True)[0])  # noqa: E731
    assert float(c.deform(v, clamp=True)[1]) == 1.0
    assert torch.autograd.gradcheck(f, (v,), eps=1e-7, atol=1e-6)


def test_refine_band_keeps_zero_set():
    c = make("hex", 4, "cpu")
    r = c.refine_band(rings=1)
    assert r.mesh.faces.shape[0] > c.mesh.faces.shape[0]
    # old vertices keep their values (so their signs)
    n_old = c.mesh.verts.shape[0]
    from torch_isc.core.subdivide import subdivide  # noqa: F401 (same rule)
    old_pos = c.mesh.verts
    idx = torch.cdist(old_pos, r.mesh.verts).argmin(1)
    assert torch.equal(r.values[idx], c.values)
    assert r.mesh.verts.shape[0] > n_old
    # zero set unchanged as a set: both ways, distances at rounding level
    assert float(point_curve_distance(c, r.zero_set().points).max()) < 1e-13
    assert float(point_curve_distance(r, c.zero_set().points).max()) < 1e-13
    assert abs(float(area(r) - area(c))) < 1e-13 and abs(float(length(r) - length(c))) < 1e-13
    assert r.num_components().tolist() == c.num_components().tolist()


def sup_area_fixed_signs(c):
    """Supremum of the inside area over all magnitudes with the signs fixed: the total area of
    the triangles that touch a negative vertex."""
    neg = (c.values[c.mesh.faces] < 0).any(1)
    return float(0.5 * c.mesh.signed_areas()[neg].sum())


def fit_area(c, target, steps=40):
    s = torch.log(c.values.abs()).clone().requires_grad_()
    opt = torch.optim.LBFGS([s], lr=1, max_iter=steps, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        a = area(c.rescale(torch.exp(s), validate=False))
        loss = ((a - target) / target) ** 2
        loss.sum().backward()
        return loss.sum()
    opt.step(closure)
    return c.rescale(torch.exp(s.detach()))


def test_flip_simple_reaches_unreachable_area():
    m = hexagon_mesh(torch.zeros(1, 2, dtype=D), torch.ones(1, dtype=D), 6)
    c = ImplicitCurve(m, m.verts.norm(dim=1) - 0.2017)
    target = 0.6
    bound = sup_area_fixed_signs(c)
    assert bound < target
    fixed = fit_area(c, target)
    assert float(area(fixed)) < bound < target      # the fixed sign pattern cannot get there
    cur = fixed
    for _ in range(6):
        if abs(float(area(cur)) - target) < 1e-4:
            break
        if sup_area_fixed_signs(cur) < target * 1.05:
            cur, flipped = cur.flip_simple(grow=True)
            assert int(flipped.sum()) > 0
            assert cur.num_components().tolist() == [1] and bool(cur.zero_set().closed.all())
        cur = fit_area(cur, target)
        assert cur.num_components().tolist() == [1]
    assert abs(float(area(cur)) - target) < 1e-4
    # the inside region has no hole: Euler characteristic of {f<0}'s vertex set via loops
    assert len(cur.zero_set()) == 1


def test_simple_vertices_hand():
    m = hexagon_mesh(torch.zeros(1, 2, dtype=D), torch.ones(1, dtype=D), 2)
    # one negative vertex next to the centre: the centre's link has one negative run -> simple;
    # a vertex whose link alternates (two negative runs) is not
    vals = torch.ones(m.verts.shape[0], dtype=D)
    centre = int(m.verts.norm(dim=1).argmin())
    nb = torch.cdist(m.verts[centre:centre + 1], m.verts)[0]
    ring = ((nb > 0.4) & (nb < 0.6)).nonzero().squeeze(1)
    ang = torch.atan2(m.verts[ring, 1], m.verts[ring, 0]).argsort()
    ring = ring[ang]
    vals[ring[0]] = -1
    assert bool(ImplicitCurve(m, vals).simple_vertices()[centre])
    vals[ring[3]] = -1                                # opposite: two runs, flipping would join two regions
    assert not bool(ImplicitCurve(m, vals).simple_vertices()[centre])
    vals[:] = 1; vals[centre] = -1                    # an isolated negative vertex: flipping deletes a component
    assert not bool(ImplicitCurve(m, vals).simple_vertices()[centre])
