"""pipeline/channels.py (channel filling) against hand-worked sign patterns on a square grid."""
import math

import torch

from torch_isc.core.mesh import square_mesh
from torch_isc.pipeline.channels import axis_walks, channel_vertices, enclosed_across

N = 6                                    # 7 x 7 vertices on [-1, 1]^2, spacing h = 1/3
H = 1.0 / 3.0


def _mesh(items=1):
    return square_mesh(torch.zeros(items, 2, dtype=torch.float64), torch.ones(items, dtype=torch.float64), N)


def _vid(i, j, item=0):                  # column i (x), row j (y)
    return item * (N + 1) ** 2 + j * (N + 1) + i


def _stroke(cut, items=1, item=0, s=None):
    """+1 everywhere but a stroke along x (row 3, x = 1..5) negative, cut (+) at columns ``cut``."""
    s = torch.ones(items * (N + 1) ** 2, dtype=torch.float64) if s is None else s
    for i in range(1, N):
        s[_vid(i, 3, item)] = -1.0
    for i in cut:
        s[_vid(i, 3, item)] = 1.0
    return s


def _along_x(V, angle=0.0):
    return torch.tensor([[math.cos(angle), math.sin(angle)]], dtype=torch.float64).expand(V, 2).clone()


def test_walks_match_hand_lengths():
    mesh = _mesh()
    V = mesh.verts.shape[0]
    s = _stroke([3, 4])                  # a cut two vertices long
    cap = torch.full((V,), 10.0, dtype=torch.float64)
    f, b = axis_walks(mesh, s, _along_x(V), 35.0, cap, 8)
    # from (3,3): forward over (4,3) (+) onto (5,3) (-): 2h; backward onto (2,3): h
    assert math.isclose(f[_vid(3, 3)].item(), 2 * H) and math.isclose(b[_vid(3, 3)].item(), H)
    assert math.isclose(f[_vid(4, 3)].item(), H) and math.isclose(b[_vid(4, 3)].item(), 2 * H)
    # (3,2), below the stroke: along x it stays + to the mesh's side, never meeting the other sign
    assert f[_vid(3, 2)].item() == 10.0 and b[_vid(3, 2)].item() == 10.0
    # a reversed axis at one vertex walks on with that vertex's other distance: same lengths
    d = _along_x(V)
    d[_vid(4, 3)] *= -1
    f2, b2 = axis_walks(mesh, s, d, 35.0, cap, 8)
    assert math.isclose(f2[_vid(3, 3)].item(), 2 * H) and math.isclose(b2[_vid(3, 3)].item(), H)
    # the same walk limited to one round cannot see past (4,3)
    f1, _ = axis_walks(mesh, s, _along_x(V), 35.0, cap, 0)
    assert f1[_vid(3, 3)].item() == 10.0


def test_cut_across_a_stroke_fills_within_its_length():
    mesh = _mesh()
    V = mesh.verts.shape[0]
    s = _stroke([3, 4])
    d = _along_x(V)
    everyone = ~mesh.is_boundary_vert & (s > 0)
    # walks of the cut's vertices total 3h: filled at a length of 3h, not below
    got = channel_vertices(mesh, s, d, everyone, torch.full((V,), 3 * H + 1e-9, dtype=torch.float64), 35.0, 8)
    assert sorted(got.nonzero().squeeze(1).tolist()) == [_vid(3, 3), _vid(4, 3)]
    got = channel_vertices(mesh, s, d, everyone, torch.full((V,), 3 * H - 1e-3, dtype=torch.float64), 35.0, 8)
    assert not bool(got.any())
    # across the data (axis along y) the cut is no channel: its walks along y find no other sign
    # on the outside... except through the stroke itself, which is not along y
    got = channel_vertices(mesh, s, _along_x(V, math.pi / 2), everyone,
                           torch.full((V,), 3 * H + 1e-9, dtype=torch.float64), 35.0, 8)
    assert not bool(got.any())


def _gap_signs():
    """Two strokes (rows 2 and 4, x = 1..5) of the inside sign with a gap (row 3, +) between them,
    bridged at (2,3) and (4,3): the gap vertex (3,3) sees the inside sign both ways along x."""
    s = torch.ones((N + 1) ** 2, dtype=torch.float64)
    for i in range(1, N):
        s[_vid(i, 2)] = -1.0
        s[_vid(i, 4)] = -1.0
    s[_vid(2, 3)] = -1.0
    s[_vid(4, 3)] = -1.0
    return s


def test_gap_between_two_curves_is_not_filled():
    mesh = _mesh()
    V = mesh.verts.shape[0]
    d = _along_x(V)
    wall = torch.full((V,), H / 2, dtype=torch.float64)          # walls half-way between rows
    L = torch.full((V,), 3 * H, dtype=torch.float64)
    gap = _gap_signs()
    enc = enclosed_across(mesh, gap, d, wall, -wall)
    assert bool(enc[_vid(3, 3)])                                  # the other sign above and below
    # without the test the gap vertex would go (its walks total 2h); with it, nothing does
    el = ~mesh.is_boundary_vert & (gap > 0)
    assert bool(channel_vertices(mesh, gap, d, el, L, 35.0, 8)[_vid(3, 3)])
    assert not bool(channel_vertices(mesh, gap, d, el, L, 35.0, 8, enc).any())
    # a cut through a stroke has its own sign beyond both walls: not enclosed, filled
    cut = _stroke([3])
    enc = enclosed_across(mesh, cut, d, wall, -wall)
    assert not bool(enc[_vid(3, 3)])
    el = ~mesh.is_boundary_vert & (cut > 0)
    assert channel_vertices(mesh, cut, d, el, L, 35.0, 8, enc).nonzero().squeeze(1).tolist() == [_vid(3, 3)]


def test_an_items_channels_do_not_depend_on_the_batch():
    one = _mesh(1)
    two = _mesh(2)
    V1 = one.verts.shape[0]
    s1 = _stroke([3, 4])
    s2 = _stroke([2], items=2, item=1, s=_stroke([3, 4], items=2))
    L1 = torch.full((V1,), 3 * H + 1e-9, dtype=torch.float64)
    a = channel_vertices(one, s1, _along_x(V1), ~one.is_boundary_vert & (s1 > 0), L1, 35.0, 8)
    V2 = two.verts.shape[0]
    b = channel_vertices(two, s2, _along_x(V2), ~two.is_boundary_vert & (s2 > 0), L1.repeat(2), 35.0, 8)
    assert torch.equal(a, b[:V1])
    assert b[V1:].nonzero().squeeze(1).tolist() == [_vid(2, 3)]
