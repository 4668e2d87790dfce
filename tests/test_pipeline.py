"""The seams of the pipeline: the working set (drop finished items, follow a subdivision)
against naive per-item references, the sign sources, the stats recorder, the simplex kernel
against hand values, and the segment helpers against loops."""
import math

import numpy as np

import pytest
import torch

from torch_isc.core.locate import locate_grid
from torch_isc.core.mesh import MeshBatch, hexagon_mesh
from torch_isc.core.points import PointSetError, prepare_points
from torch_isc.core.segments import (first_index, hash_uniform, segment_max, segment_median, segment_min,
                                     segment_sum, sym2_eigvals, sym2_eigvec)
from torch_isc.core.simplex import TRIANGLES
from torch_isc.pipeline.config import ReconstructConfig
from torch_isc.pipeline.evidence import gather_evidence
from torch_isc.pipeline.loop import _start, initial_mesh, reconstruct_batch
from torch_isc.pipeline.signs import IsingSigns, OracleSigns
from torch_isc.pipeline.stats import StatsRecorder
from torch_isc.core.subdivide import subdivide
from torch_isc.pipeline.workset import WorkingSet


def _circle(n, r=1.0, c=(0.0, 0.0), phase=0.0):
    t = torch.arange(n, dtype=torch.float64) / n * 2 * math.pi + phase
    return torch.stack([c[0] + r * t.cos(), c[1] + r * t.sin()], 1)


def _working_set(sets, dtype=torch.float64):
    cfg = ReconstructConfig().replace(dtype="float64" if dtype == torch.float64 else "float32")
    batch = prepare_points(sets, dtype=dtype)
    ws = _start(batch, cfg, StatsRecorder("cpu", batch.num_items))
    # give every per-vertex and per-face field distinct content, so a wrong gather shows
    V, T = ws.mesh.verts.shape[0], ws.mesh.faces.shape[0]
    values = (torch.arange(V, dtype=dtype) + 1.0) * torch.where(torch.arange(V) % 3 == 0, -1.0, 1.0).to(dtype)
    marked = torch.arange(T) % 3 == 0
    return ws.replace(values=values, signs=torch.where(torch.arange(V) % 2 == 0, 1.0, -1.0).to(dtype),
                      marked=marked), batch


SETS = [_circle(40), _circle(25, 3.0, (5.0, 1.0)), _circle(60, 0.1, (-2.0, 0.0), 0.3), _circle(33, 2.0)]


@pytest.mark.parametrize("keep", [[0, 2], [1, 3], [3], [0, 1, 2, 3]])
def test_select_matches_a_per_item_reference(keep):
    """Each field of the selected working set equals the same item's rows of the full set,
    found item by item with plain slicing (the naive reference)."""
    ws, _ = _working_set(SETS)
    sub = ws.select(torch.tensor(keep))
    assert sub.num_items == len(keep)
    vf, ff = ws.mesh.verts_first_idx.tolist(), ws.mesh.faces_first_idx.tolist()
    nv, nf = ws.mesh.verts_per_item.tolist(), ws.mesh.faces_per_item.tolist()
    pi = ws.point_item.tolist()
    v_off = f_off = p_off = 0
    for j, b in enumerate(keep):
        sl_v = slice(vf[b], vf[b] + nv[b])
        sl_f = slice(ff[b], ff[b] + nf[b])
        rows = [i for i, x in enumerate(pi) if x == b]
        sv, sf = slice(v_off, v_off + nv[b]), slice(f_off, f_off + nf[b])
        sp = slice(p_off, p_off + len(rows))
        assert torch.equal(sub.mesh.verts[sv], ws.mesh.verts[sl_v])
        assert torch.equal(sub.mesh.faces[sf] - v_off, ws.mesh.faces[sl_f] - vf[b])
        assert torch.equal(sub.values[sv], ws.values[sl_v]) and torch.equal(sub.signs[sv], ws.signs[sl_v])
        assert torch.equal(sub.marked[sf], ws.marked[sl_f])
        for name in ("points", "bary", "frames"):
            assert torch.equal(getattr(sub, name)[sp], getattr(ws, name)[rows]), name
        assert sub.point_item[sp].tolist() == [j] * len(rows)
        # a point's triangle is the same triangle, renumbered
        assert (sub.face[sp] - f_off).tolist() == [f - ff[b] for f in ws.face[rows].tolist()]
        for name in WorkingSet.ITEM_FIELDS:
            assert torch.equal(getattr(sub, name)[j], getattr(ws, name)[b]), name
        v_off, f_off, p_off = v_off + nv[b], f_off + nf[b], p_off + len(rows)
    assert p_off == sub.points.shape[0]


def test_follow_subdivision_matches_a_fresh_location():
    """After a subdivision, values are the old ones (new vertices: the mean of their edge's
    ends), signs follow the values, and every point's triangle and barycentrics are those a
    fresh global location on the new mesh finds."""
    ws, _ = _working_set(SETS)
    sd = subdivide(ws.mesh, ws.marked)
    new = ws.follow(sd)
    assert new.mesh is sd.mesh and not new.marked.any()
    old_v, new_v = ws.mesh.verts, new.mesh.verts
    for i in range(old_v.shape[0]):                          # old vertices keep their value
        j = int(sd.old_to_new_vert[i])
        assert torch.equal(new_v[j], old_v[i]) and new.values[j] == ws.values[i]
    e = ws.mesh.edges
    for j in (sd.new_vert_edge >= 0).nonzero().squeeze(1).tolist():
        a, b = e[sd.new_vert_edge[j]].tolist()
        assert new.values[j] == 0.5 * (ws.values[a] + ws.values[b])
        assert torch.allclose(new_v[j], 0.5 * (old_v[a] + old_v[b]))
    assert torch.equal(new.signs, torch.where(new.values < 0, -1.0, 1.0).to(new.dtype))
    face, bary = locate_grid(new.mesh, new.points, new.point_item)
    assert torch.equal(new.face, face)
    torch.testing.assert_close(new.bary, bary, rtol=0, atol=1e-12)
    for name in ("items", "tol", "noise", "points", "frames"):
        assert torch.equal(getattr(new, name), getattr(ws, name))


def test_select_then_follow_equals_follow_of_each_item():
    """Dropping items and subdividing commute with solving each item alone."""
    ws, _ = _working_set(SETS)
    keep = torch.tensor([1, 3])
    a = ws.select(keep)
    a = a.follow(subdivide(a.mesh, a.marked))
    for j, b in enumerate(keep.tolist()):
        one = ws.select(torch.tensor([b]))
        one = one.follow(subdivide(one.mesh, one.marked))
        aj = a.select(torch.tensor([j]))
        assert torch.equal(aj.mesh.verts, one.mesh.verts) and torch.equal(aj.mesh.faces, one.mesh.faces)
        assert torch.equal(aj.values, one.values) and torch.equal(aj.face, one.face)


def test_oracle_signs_read_the_oracle_in_caller_coordinates():
    """The oracle is asked at the vertices in the caller's frame (normalized * scale + centre),
    boundary vertices are outside, and a batched and a per-item oracle agree."""
    sets = [_circle(50, 2.0, (10.0, -3.0)), _circle(30, 0.5, (0.0, 7.0))]
    ws, batch = _working_set(sets)
    centres = [(10.0, -3.0), (0.0, 7.0)]
    radii = [1.0, 0.25]

    def per_item(b):
        return lambda x: ((x - torch.tensor(centres[b], dtype=x.dtype)).norm(dim=1) < radii[b])

    def batched(x, item):
        c = torch.tensor(centres, dtype=x.dtype)[item]
        return (x - c).norm(dim=1) < torch.tensor(radii, dtype=x.dtype)[item]

    ev = gather_evidence(ws)
    s1 = OracleSigns([per_item(0), per_item(1)]).signs(ws, ev, 0)
    s2 = OracleSigns(batched).signs(ws, ev, 0)
    assert torch.equal(s1, s2)
    xc = ws.mesh.verts.double() * ws.scale[ws.mesh.vert_item, None] + ws.center[ws.mesh.vert_item]
    want = torch.where(batched(xc, ws.mesh.vert_item), -1.0, 1.0).double()
    want[ws.mesh.is_boundary_vert] = 1.0
    assert torch.equal(s1, want) and (s1 < 0).any()
    with pytest.raises(PointSetError, match="returned 1 values"):
        OracleSigns(lambda x, item: torch.ones(1, dtype=torch.bool)).signs(ws, ev, 0)


def test_ising_signs_depend_on_the_item_alone():
    cfg = ReconstructConfig()
    ws, _ = _working_set(SETS, torch.float32)
    src = IsingSigns(cfg.topology, cfg.evidence, seed=0)
    s_all = src.signs(ws, gather_evidence(ws), 0)
    for b in range(ws.num_items):
        one = ws.select(torch.tensor([b]))
        s_one = src.signs(one, gather_evidence(one), 0)
        v0, n = int(ws.mesh.verts_first_idx[b]), int(ws.mesh.verts_per_item[b])
        assert torch.equal(s_all[v0:v0 + n], s_one)
    assert (s_all[ws.mesh.is_boundary_vert] == 1).all()


def test_stats_recorder_writes_one_record_per_item_and_level():
    rec = StatsRecorder("cpu", 3)
    cols = {k: torch.tensor([1, 2]) for k in ("triangles", "points", "marked", "points_beyond_tolerance")}
    cols.update({k: torch.tensor([0.5, 0.25], dtype=torch.float64) for k in ("delta1", "max_error", "tolerance",
                                                                              "noise")})
    rec.tick("topology")
    rec.record(0, torch.tensor([2, 0]), cols)
    rec.close_level()
    rec.record(1, torch.tensor([2]), {k: v[1:] for k, v in cols.items()})
    rec.close_level()
    assert [len(x) for x in rec.per_item] == [0, 0, 0]          # read from the device at flush only
    rec.flush()
    assert [len(x) for x in rec.per_item] == [1, 0, 2]
    a, b, a1 = rec.per_item[2][0], rec.per_item[0][0], rec.per_item[2][1]
    assert (a.level, a.triangles, a.delta1, b.triangles, b.noise) == (0, 1, 0.5, 2, 0.25)
    assert (a1.level, a1.triangles, a1.marked, a1.noise) == (1, 2, 2, 0.25)
    assert type(a.triangles) is int and type(a.delta1) is float
    assert a.seconds >= 0 and set(a.stage_seconds) >= {"topology", "relax"} and a.seconds == b.seconds
    assert a1.stage_seconds["topology"] == 0.0                  # level 1's own (untimed) stages
    assert list(a.to_dict(timings=False)) == ["level", "triangles", "points", "delta1", "max_error", "tolerance",
                                              "noise", "marked", "points_beyond_tolerance"]


def test_initial_mesh_covers_the_normalized_data():
    """Normalized data lie in the disc of radius 1/2: every point of it is inside the mesh,
    with the margin to spare, for both shapes."""
    for shape in ("hexagon", "square"):
        cfg = ReconstructConfig().replace(initial_mesh=shape, margin=0.15).mesh
        m = initial_mesh(cfg, 2, "cpu", torch.float64)
        t = torch.linspace(0, 2 * math.pi, 721)
        ring = 0.64 * torch.stack([t.cos(), t.sin()], 1).double()    # radius 0.5 + 0.15 - a little
        face, _ = locate_grid(m, torch.cat([ring, ring]), torch.repeat_interleave(torch.arange(2), 721))
        assert (face >= 0).all(), shape


# ----------------------------------------------------------------------------- the 2D kernel
def test_triangle_kernel_hand_values():
    tri = torch.tensor([[[0.0, 0.0], [2.0, 0.0], [0.0, 1.0]]], dtype=torch.float64)
    assert TRIANGLES.volumes(tri).tolist() == [2.0]
    G = TRIANGLES.bary_gradients(tri)[0]                     # x0 = 1 - x/2 - y, x1 = x/2, x2 = y
    assert G.tolist() == [[-0.5, -1.0], [0.5, 0.0], [0.0, 1.0]]
    assert TRIANGLES.longest_edge(tri).tolist() == [math.sqrt(5.0)]
    assert TRIANGLES.quality(tri).item() == pytest.approx(2 * math.sqrt(3) * 2 / (4 + 5 + 1))
    # f = x - 1 on the corners (-1, 1, -1): crossings at (1, 0) on edge 0-1 and (1, 0.5)... on edge 1-2
    seg, has = TRIANGLES.zero_set_pieces(tri, torch.tensor([[-1.0, 1.0, -1.0]], dtype=torch.float64))
    assert has.tolist() == [True]
    assert sorted(map(tuple, seg[0].tolist())) == [(1.0, 0.0), (1.0, 0.5)]
    d2 = TRIANGLES.piece_distance2(seg, has, torch.tensor([[3.0, 0.25]], dtype=torch.float64), torch.tensor([[0]]))
    assert d2.tolist() == [4.0]
    eps, normal = TRIANGLES.hyperplane_fit(torch.tensor([[[4.0, 0.0], [0.0, 0.25]]], dtype=torch.float64))
    assert eps.tolist() == [0.25] and normal.abs().tolist() == [[0.0, 1.0]]


def test_split_rule_of_fig7():
    f = torch.tensor([[0, 1, 2]] * 3)
    mids = torch.tensor([[10, 11, 12]] * 3)                  # midpoint of edge k (opposite corner k)
    marked = torch.tensor([[True, True, True], [True, True, False], [True, False, False]])
    cand, n = TRIANGLES.split_children(f, mids, marked)
    assert n.tolist() == [4, 2, 1]
    assert cand[0].tolist() == [[0, 12, 11], [1, 10, 12], [2, 11, 10], [10, 11, 12]]
    assert cand[1, :2].tolist() == [[2, 0, 12], [2, 12, 1]]  # through the midpoint of edge 0-1
    assert cand[2, 0].tolist() == [0, 1, 2]


# ----------------------------------------------------------------------------- segment helpers
def test_segment_helpers_against_loops():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(200, generator=g, dtype=torch.float64)
    seg = torch.randint(0, 7, (200,), generator=g)
    seg[seg == 4] = 5                                        # segment 4 empty
    for b in range(7):
        xs = x[seg == b]
        assert segment_sum(x, seg, 7)[b].item() == pytest.approx(float(xs.sum()) if xs.numel() else 0.0)
        assert segment_max(x, seg, 7)[b].item() == (float(xs.max()) if xs.numel() else -math.inf)
        assert segment_min(x, seg, 7)[b].item() == (float(xs.min()) if xs.numel() else math.inf)
        assert segment_median(x, seg, 7)[b].item() == (float(xs.sort().values[(xs.numel() - 1) // 2])
                                                       if xs.numel() else 0.0)
    assert first_index(torch.tensor([3, 0, 2])).tolist() == [0, 3, 3]
    a, b, d = torch.tensor([2.0, 1.0]), torch.tensor([1.0, 0.0]), torch.tensor([2.0, 3.0])
    lo, hi = sym2_eigvals(a, b, d)
    assert lo.tolist() == [1.0, 1.0] and hi.tolist() == [3.0, 3.0]
    v = sym2_eigvec(a, b, d, hi)
    M = torch.stack([torch.stack([a, b], 1), torch.stack([b, d], 1)], 1)
    torch.testing.assert_close((M @ v[..., None])[..., 0], hi[:, None] * v)
    u = hash_uniform(torch.arange(1000), dtype=torch.float64)
    assert 0 < float(u.min()) and float(u.max()) < 1 and abs(float(u.mean()) - 0.5) < 0.05


@pytest.mark.parametrize("mode", ["no_grad", "inference_mode"])
def test_a_caller_without_autograd_gets_the_same_result(mode):
    """The relaxation differentiates its energy: under the caller's ``torch.no_grad`` it raised
    "element 0 of tensors does not require grad", and ``inference_mode`` forbids autograd even
    under ``enable_grad`` (fuzzing round 11). Two circles, so the loop relaxes past level 0."""
    t = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    P = torch.as_tensor(np.r_[np.c_[np.cos(t), np.sin(t)], np.c_[3 + 0.4 * np.cos(t), 0.4 * np.sin(t)]])
    want = reconstruct_batch([P, P * 2])
    assert len(want[0].stats) > 1                                   # past level 0: relaxed
    with getattr(torch, mode)():
        got = reconstruct_batch([P.clone(), P * 2])
    for a, b in zip(got, want):
        assert len(a.polylines) == len(b.polylines) == 2
        assert all(torch.equal(x["points"], y["points"]) for x, y in zip(a.polylines, b.polylines))
