"""soft_inside / rasterize: hard limits, finiteness off the mesh, gradcheck, a mask fit with Adam."""
import pytest
import torch

from torch_isc import ImplicitCurve, hexagon_mesh, square_mesh
from torch_isc.core.render import pixel_centers, rasterize, soft_inside

D = torch.float64


def disc_curve(device, dtype, c=(0.1, -0.05), r=0.4517, res=6):
    m = hexagon_mesh(torch.zeros(1, 2, device=device, dtype=dtype), torch.ones(1, device=device), res)
    return ImplicitCurve(m, (m.verts - torch.tensor(c, device=device, dtype=dtype)).norm(dim=1) - r)


@pytest.mark.parametrize("mode", ["distance", "local"])
def test_small_tau_is_hard_inside(mode, device, dtype):
    c = disc_curve(device, dtype)
    g = torch.Generator().manual_seed(0)
    p = (torch.rand(400, 2, generator=g) * 2.4 - 1.2).to(device=device, dtype=dtype)
    s = soft_inside(c, p, tau=1e-6, mode=mode)
    hard = c.inside(p)
    from torch_isc.core.measures import point_curve_distance
    far = point_curve_distance(c, p) > 1e-4
    assert torch.equal((s > 0.5)[far], hard[far])
    assert bool(((s > 0) & (s < 1) | (s == 0) | (s == 1)).all())


def test_distance_mode_value_by_hand(device):
    sq = square_mesh(torch.zeros(1, 2, device=device, dtype=D), torch.ones(1, device=device), 4)
    c = ImplicitCurve(sq, sq.verts.abs().amax(1) - 0.6)
    p = torch.tensor([[0.0, 0.0], [0.7, 0.0], [1.5, 0.0], [30.0, 0.0]], device=device, dtype=D)
    s = soft_inside(c, p, tau=0.1)
    exp = torch.sigmoid(torch.tensor([6.0, -1.0, -9.0, -294.0], dtype=D)).to(device)
    assert torch.allclose(s, exp, rtol=1e-12, atol=0)


@pytest.mark.parametrize("mode", ["distance", "local"])
def test_off_mesh_finite_grads_and_no_face_minus_one(mode):
    c = disc_curve("cpu", D)
    vals = c.values.clone().requires_grad_()
    verts = c.mesh.verts.clone().requires_grad_()
    p = torch.tensor([[3.0, 0.0], [0.0, -2.5], [0.2, 0.1], [0.99, 0.0]], dtype=D, requires_grad=True)
    cc = ImplicitCurve(c.mesh.with_verts(verts), vals)
    s = soft_inside(cc, p, tau=0.05, mode=mode)
    assert torch.isfinite(s).all()
    s.sum().backward()
    for t in (vals.grad, verts.grad, p.grad):
        assert torch.isfinite(t).all()
    if mode == "local":
        assert float(s[0]) == 0 and float(s[1]) == 0
        # the last triangle's values do not reach off-mesh points (no face = -1 indexing)
        v2 = c.values.clone(); v2[c.mesh.faces[-1]] = -5.0
        s2 = soft_inside(ImplicitCurve(c.mesh, v2), p[:2].detach(), tau=0.05, mode=mode)
        assert torch.equal(s2, torch.zeros(2, dtype=D))
    else:
        assert 0 < float(s[0]) < 1e-10


@pytest.mark.parametrize("mode", ["distance", "local"])
def test_soft_inside_gradcheck(mode):
    c = disc_curve("cpu", D, res=3)
    g = torch.Generator().manual_seed(2)
    verts = (c.mesh.verts + 0.02 * torch.randn(c.mesh.verts.shape, generator=g, dtype=D)).requires_grad_()
    vals = c.values.clone().requires_grad_()
    p = (torch.rand(12, 2, generator=g, dtype=D) * 1.4 - 0.7).requires_grad_()
    f = lambda v, f_, q: soft_inside(ImplicitCurve(c.mesh.with_verts(v), f_, validate=False), q, 0.2, mode=mode)  # noqa: E731
    assert torch.autograd.gradcheck(f, (verts, vals, p), eps=1e-6, atol=1e-6)


def test_rasterize_batch_layout(device):
    m = hexagon_mesh(torch.tensor([[0.0, 0.0], [4.0, 4.0]], device=device, dtype=D),
                     torch.tensor([1.0, 0.5], device=device, dtype=D), 5)
    cen = torch.tensor([[0.3, 0.0], [4.0, 4.2]], device=device, dtype=D)
    rad = torch.tensor([0.4017, 0.2013], device=device, dtype=D)
    c = ImplicitCurve(m, (m.verts - cen[m.vert_item]).norm(dim=1) - rad[m.vert_item])
    img = rasterize(c, 12, 10, tau=0.01)
    assert img.shape == (2, 12, 10)
    for b in range(2):
        assert torch.allclose(img[b], rasterize(c[b], 12, 10, tau=0.01)[0], rtol=0, atol=1e-14)
    # pixel centres: column j <-> x, row i <-> y
    ext = torch.tensor([[-1.0, -2.0, 1.0, 2.0]], dtype=D)
    pc = pixel_centers(2, 4, ext)
    assert torch.allclose(pc[0, 0, 0], torch.tensor([-0.75, -1.0], dtype=D))
    assert torch.allclose(pc[0, 1, 3], torch.tensor([0.75, 1.0], dtype=D))
    # item 0's disc is right of centre: more mass in the right half
    assert float(img[0, :, 5:].sum()) > float(img[0, :, :5].sum())


def iou(a, b):
    return float((a & b).sum()) / float((a | b).sum())


def test_fit_mask_with_adam():
    H = W = 24
    m = hexagon_mesh(torch.zeros(1, 2, dtype=D), torch.ones(1, dtype=D), 6)
    ext = (-0.9, -0.9, 0.9, 0.9)
    pc = pixel_centers(H, W, torch.tensor([ext], dtype=D))[0]
    target = ((pc - torch.tensor([0.2, 0.1], dtype=D)).norm(dim=-1) < 0.45)
    vals = ((m.verts - torch.tensor([-0.25, -0.1], dtype=D)).norm(dim=1) - 0.3017).requires_grad_()
    before = iou(rasterize(ImplicitCurve(m, vals.detach()), H, W, 0.02, ext)[0] > 0.5, target)
    opt = torch.optim.Adam([vals], lr=0.02)
    tgt = target.to(D)
    for _ in range(80):
        opt.zero_grad()
        img = rasterize(ImplicitCurve(m, vals, validate=False), H, W, 0.05, ext)[0]
        loss = torch.nn.functional.binary_cross_entropy(img.clamp(1e-6, 1 - 1e-6), tgt)
        loss.backward()
        opt.step()
    after = iou(rasterize(ImplicitCurve(m, vals.detach()), H, W, 0.02, ext)[0] > 0.5, target)
    print(f"IoU before {before:.3f} after {after:.3f}")
    assert before < 0.5 and after > 0.9, (before, after)
