"""pipeline/notches.py (tangent notches) and denoise.refine_knn, against hand-worked meshes and
brute force."""
import math

import torch

from torch_isc.core.mesh import square_mesh
from torch_isc.pipeline.denoise import refine_knn
from torch_isc.pipeline.noise import approximate_knn
from torch_isc.pipeline.notches import tangent_notches, vertex_orientation

N = 6                                    # 7 x 7 vertices on [-1, 1]^2, spacing 1/3


def _mesh():
    return square_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1, dtype=torch.float64), N)


def _vid(i, j):                          # column i (x), row j (y)
    return j * (N + 1) + i


def _stripe_signs():
    """+1 everywhere but row 3 (x = 1..5) negative, with a notch (+) at the centre (3, 3)."""
    s = torch.ones((N + 1) ** 2, dtype=torch.float64)
    for i in range(1, N):
        s[_vid(i, 3)] = -1.0
    s[_vid(3, 3)] = 1.0
    return s


def _flips(mesh, s, angle, coherence=None):
    V = mesh.verts.shape[0]
    d = torch.tensor([[math.cos(angle), math.sin(angle)]], dtype=torch.float64).expand(V, 2)
    coh = torch.ones(V, dtype=torch.float64) if coherence is None else coherence
    n = torch.full((V,), 10.0, dtype=torch.float64)
    f = tangent_notches(mesh, s, d, coh, n, mesh.is_boundary_vert, 0.6, 35.0, 3)
    return sorted(f.nonzero().squeeze(1).tolist())


def test_notch_along_the_data_flips_and_nothing_else():
    # data running along x: only (3, 3) has both x-neighbours of the other sign; (2, 3) and
    # (4, 3) each have one x-neighbour of their own sign; rows 2 and 4 see + along x
    mesh = _mesh()
    assert _flips(mesh, _stripe_signs(), 0.0) == [_vid(3, 3)]
    assert _flips(mesh, _stripe_signs(), math.pi) == [_vid(3, 3)]      # an orientation, not a direction


def test_stripe_across_the_data_flips_its_vertices():
    # data running along y: every negative vertex of the stripe has + above and below (a curve
    # crossing the data at right angles); the + notch has + above and below, it stays
    mesh = _mesh()
    assert _flips(mesh, _stripe_signs(), math.pi / 2) == sorted(_vid(i, 3) for i in (1, 2, 4, 5))


def test_oblique_direction_counts_every_neighbour_in_the_cone():
    # at 20 degrees the x axis (20 deg off) and the cells' diagonals through (3, 3) (25 deg off)
    # both lie within 35 degrees: the diagonal neighbours (2, 2) and (4, 4) are +, as (3, 3)
    # is, so it is no notch; each stripe vertex has a stripe neighbour along x
    mesh = _mesh()
    assert _flips(mesh, _stripe_signs(), math.radians(20.0)) == []
    # with a 22-degree cone only the x axis is along: the notch flips again
    V = mesh.verts.shape[0]
    d = torch.tensor([[math.cos(math.radians(20.0)), math.sin(math.radians(20.0))]], dtype=torch.float64).expand(V, 2)
    one = torch.ones(V, dtype=torch.float64)
    f = tangent_notches(mesh, _stripe_signs(), d, one, one * 10, mesh.is_boundary_vert, 0.6, 22.0, 3)
    assert f.nonzero().squeeze(1).tolist() == [_vid(3, 3)]
    # below 20 degrees no neighbour is along: nothing flips
    f = tangent_notches(mesh, _stripe_signs(), d, one, one * 10, mesh.is_boundary_vert, 0.6, 15.0, 3)
    assert not bool(f.any())


def test_incoherent_or_empty_stars_and_pinned_vertices_never_flip():
    mesh = _mesh()
    V = mesh.verts.shape[0]
    assert _flips(mesh, _stripe_signs(), 0.0, torch.full((V,), 0.5, dtype=torch.float64)) == []
    d = torch.tensor([[1.0, 0.0]], dtype=torch.float64).expand(V, 2)
    one = torch.ones(V, dtype=torch.float64)
    assert not bool(tangent_notches(mesh, _stripe_signs(), d, one, one * 2, mesh.is_boundary_vert, 0.6, 35.0, 3).any())
    # a boundary vertex whose x-neighbours are both negative is pinned
    s = torch.ones(V, dtype=torch.float64)
    s[_vid(1, 0)] = s[_vid(N - 1, 0)] = -1.0
    pinned = mesh.is_boundary_vert.clone()
    assert not bool(tangent_notches(mesh, s, d, one, one * 10, pinned, 0.6, 35.0, 3).any())


def test_vertex_orientation_by_hand():
    mesh = _mesh()
    # two points in triangle 0 with tangents along x, one with a tangent along y
    t = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    face = torch.tensor([0, 0, 0])
    d, coh, n = vertex_orientation(mesh, t, face)
    for v in mesh.faces[0].tolist():
        assert n[v] == 3
        # tensor diag(2, 1): coherence (2 - 1) / (2 + 1), major axis x
        assert abs(float(coh[v]) - 1.0 / 3.0) < 1e-12
        assert abs(abs(float(d[v, 0])) - 1.0) < 1e-12
    other = [v for v in range(mesh.verts.shape[0]) if v not in mesh.faces[0].tolist()]
    assert float(n[other].abs().sum()) == 0 and float(coh[other].abs().sum()) == 0
    # points outside every triangle (face -1) count nowhere
    _, _, n2 = vertex_orientation(mesh, t, torch.tensor([-1, -1, -1]))
    assert float(n2.sum()) == 0


def test_refine_knn_against_brute_force():
    g = torch.Generator().manual_seed(3)
    # two items of a noisy band (a dense stroke wall) each: the Morton candidates miss many
    # true neighbours there
    pts, item = [], []
    for b in range(2):
        x = torch.rand(600, generator=g, dtype=torch.float64) * 1.6 - 0.8
        y = 0.3 * x + 0.02 * torch.randn(600, generator=g, dtype=torch.float64) + 0.1 * b
        pts.append(torch.stack([x, y], 1))
        item.append(torch.full((600,), b))
    p, it = torch.cat(pts), torch.cat(item)
    k = 24
    nbr, d2 = approximate_knn(p, it, k, 12)
    nbr2, d22 = refine_knn(p, nbr, d2, 8)
    D = torch.cdist(p, p) ** 2
    D = torch.where(it[:, None] == it[None, :], D, torch.full_like(D, float("inf")))
    D.fill_diagonal_(float("inf"))
    exact = torch.topk(D, k, 1, largest=False).indices

    def recall(n):
        return sum(len(set(a.tolist()) & set(b.tolist())) for a, b in zip(n, exact)) / exact.numel()

    assert bool((it[nbr2] == it[:, None]).all())                      # items never mix
    fin = torch.isfinite(d22)
    # the point itself only where a neighbour is missing (approximate_knn's convention, inf)
    assert bool(((nbr2 != torch.arange(p.shape[0])[:, None]) == fin).all())
    assert all(len(set(r[f].tolist())) == int(f.sum()) for r, f in zip(nbr2, fin))   # no repeats
    assert torch.allclose(d22[fin], D.gather(1, nbr2)[fin])           # distances are the true ones
    assert int((~fin).sum()) <= int((~torch.isfinite(d2)).sum())
    assert bool((d22[:, 1:] >= d22[:, :-1]).all())                     # ascending
    assert bool((d22 <= d2).all())                                     # the j-th nearest only gets nearer
    r0, r1 = recall(nbr), recall(nbr2)
    assert r1 > r0 and r1 > 0.9, (r0, r1)
    # hops 0 is the identity
    n0, dd0 = refine_knn(p, nbr, d2, 0)
    assert torch.equal(n0, nbr) and torch.equal(dd0, d2)


def _face_of(mesh, p):
    """Brute-force point location (barycentric signs), an independent route to the triangle."""
    v = mesh.verts[mesh.faces]                                        # (T, 3, 2)
    out = []
    for q in p:
        a, b, c = v[:, 0], v[:, 1], v[:, 2]

        def cross(u, w):
            return u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]
        d1, d2, d3 = cross(b - a, q - a), cross(c - b, q - b), cross(a - c, q - c)
        inside = ((d1 >= 0) & (d2 >= 0) & (d3 >= 0)) | ((d1 <= 0) & (d2 <= 0) & (d3 <= 0))
        out.append(int(inside.nonzero()[0, 0]))
    return torch.tensor(out)


def test_between_walls_by_hand():
    from torch_isc.pipeline.notches import SIDE_SEPARATION, between_walls
    mesh = _mesh()
    V = mesh.verts.shape[0]
    d = torch.tensor([[1.0, 0.0]], dtype=torch.float64).expand(V, 2)
    centre = _vid(3, 3)                                               # at (0, 0)
    xs = torch.tensor([-0.2, -0.1, 0.1, 0.2], dtype=torch.float64)
    two = torch.cat([torch.stack([xs, torch.full_like(xs, 0.1)], 1), torch.stack([xs, torch.full_like(xs, -0.1)], 1)])
    one = torch.stack([xs, torch.full_like(xs, 0.1)], 1)
    noise = torch.full((V,), 0.05, dtype=torch.float64)
    # two walls 0.2 apart = 4 noise widths >= 2: between
    assert bool(between_walls(mesh, d, two, _face_of(mesh, two), noise)[centre])
    # one wall: all points on one side
    assert not bool(between_walls(mesh, d, one, _face_of(mesh, one), noise)[centre])
    # walls 0.2 apart with noise 0.11: 1.8 noise widths < SIDE_SEPARATION
    assert 0.2 / 0.11 < SIDE_SEPARATION
    assert not bool(between_walls(mesh, d, two, _face_of(mesh, two), torch.full((V,), 0.11, dtype=torch.float64))[centre])
    # the same walls seen along y (direction rotated): the offsets are along x, both sides again
    d_y = torch.tensor([[0.0, 1.0]], dtype=torch.float64).expand(V, 2)
    assert bool(between_walls(mesh, d_y, two, _face_of(mesh, two), noise)[centre])
