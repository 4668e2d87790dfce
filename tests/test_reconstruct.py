"""End-to-end tests of torch_isc.reconstruct: topology, accuracy, orientation, invariances,
batch independence, determinism, input errors and the result schema.

Ground truth is analytic (circles sampled densely); distances come from
torch_isc.metrics.hausdorff, orientation from a shoelace formula and winding numbers
written in conftest.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import torch_isc
from torch_isc import PointSetError, ReconstructConfig, reconstruct, reconstruct_batch
from torch_isc.io import read_points
from torch_isc.metrics import bbox_diagonal, hausdorff, point_distances

from conftest import find_intersections, polygon_signed_area, winding_number

NESTED = Path(torch_isc.__file__).parent / "data" / "nested.xy"
DOCUMENTED_STAT_KEYS = {"level", "triangles", "points", "delta1", "max_error", "tolerance", "noise", "marked",
                        "points_beyond_tolerance", "seconds"}


# ----------------------------------------------------------------------------- data


def circle(n, r, c=(0.0, 0.0), phase=0.0):
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n) + phase
    return torch.stack([c[0] + r * t.cos(), c[1] + r * t.sin()], 1)


def truth_circle(r, c=(0.0, 0.0)):
    return (circle(4000, r, c), True)


CASES = {
    "circle": (lambda: circle(200, 1.0), [truth_circle(1.0)]),
    "two": (lambda: torch.cat([circle(150, 1.0, (-1.5, 0.0)), circle(150, 1.0, (1.5, 0.0), 0.3)]),
            [truth_circle(1.0, (-1.5, 0.0)), truth_circle(1.0, (1.5, 0.0))]),
    "annulus": (lambda: torch.cat([circle(160, 1.0), circle(100, 0.5, phase=0.1)]),
                [truth_circle(1.0), truth_circle(0.5)]),
}

_CACHE = {}


def solved(name, device=torch.device("cpu")):
    """Each case reconstructed once per device (default config)."""
    key = (name, str(device))
    if key not in _CACHE:
        pts = CASES[name][0]().to(device)
        _CACHE[key] = (pts, reconstruct(pts, name=name))
    return _CACHE[key]


def polys_equal(a, b):
    return len(a) == len(b) and all(x["closed"] == y["closed"] and torch.equal(x["points"], y["points"])
                                    for x, y in zip(a, b))


def check_result_basics(res, pts):
    curve = res.curve
    curve.mesh.validate()
    assert not (curve.values == 0).any()
    # the mesh covers every input point (caller's coordinates)
    face, _ = curve.locate(pts.to(device=curve.device, dtype=curve.mesh.dtype))
    assert (face >= 0).all()
    assert res.converged and res.limit is None
    levels = [s.level for s in res.stats]
    assert levels == list(range(len(levels)))
    assert res.stats[-1].marked == 0
    for s in res.stats:
        assert DOCUMENTED_STAT_KEYS <= set(s.to_dict())
        assert s.points == pts.shape[0]
    # no two polylines cross, no polyline crosses itself
    assert find_intersections([(p["points"], p["closed"]) for p in res.polylines]) == []


# ----------------------------------------------------------------------------- topology and accuracy


def test_circle(device):
    pts, res = solved("circle", device)
    assert (res.num_closed, res.num_open) == (1, 0)
    check_result_basics(res, pts.cpu())
    truth = CASES["circle"][1]
    h = hausdorff(res.polylines, truth)
    assert h < 0.02 * 2.0
    loop = res.polylines[0]["points"]
    # f < 0 inside: the loop runs counter-clockwise and winds once around the centre
    assert polygon_signed_area(loop) > 0
    assert polygon_signed_area(loop) == pytest.approx(math.pi, rel=0.02)
    assert winding_number(loop, (0.0, 0.0)) == 1
    centre = torch.tensor([[0.0, 0.0], [1.3, 0.0]], dtype=res.curve.mesh.dtype, device=res.curve.mesh.device)
    f = res.curve(centre)
    assert float(f[0]) < 0 < float(f[1])


def test_two_disjoint_circles():
    pts, res = solved("two")
    assert (res.num_closed, res.num_open) == (2, 0)
    check_result_basics(res, pts)
    assert hausdorff(res.polylines, CASES["two"][1]) < 0.02 * 2.0
    boxes = sorted((p["points"].double().amin(0) + p["points"].double().amax(0)).tolist() for p in res.polylines)
    assert [0.5 * b[0] for b in boxes] == pytest.approx([-1.5, 1.5], abs=0.02)
    assert [0.5 * b[1] for b in boxes] == pytest.approx([0.0, 0.0], abs=0.02)
    for p in res.polylines:
        assert polygon_signed_area(p["points"]) == pytest.approx(math.pi, rel=0.02)


def test_annulus_inner_loop_is_a_hole():
    pts, res = solved("annulus")
    assert (res.num_closed, res.num_open) == (2, 0)
    check_result_basics(res, pts)
    assert hausdorff(res.polylines, CASES["annulus"][1]) < 0.02 * 2.0
    areas = sorted(polygon_signed_area(p["points"]) for p in res.polylines)
    # inner loop clockwise (a hole), outer loop counter-clockwise
    assert areas[0] == pytest.approx(-math.pi * 0.25, rel=0.03)
    assert areas[1] == pytest.approx(math.pi, rel=0.02)
    f = res.curve(torch.tensor([[0.0, 0.0], [0.75, 0.0], [0.0, -0.75], [1.3, 0.0]], dtype=res.curve.mesh.dtype))
    assert float(f[0]) > 0 and float(f[1]) < 0 and float(f[2]) < 0 and float(f[3]) > 0


def test_nested_example():
    pts = torch.as_tensor(read_points(NESTED))
    assert pts.shape == (600, 2)
    res = reconstruct(pts)
    assert (res.num_closed, res.num_open) == (4, 0)
    check_result_basics(res, pts)
    # nested: outer (ccw), two holes (cw), one island inside a hole (ccw)
    signs = sorted(polygon_signed_area(p["points"]) > 0 for p in res.polylines)
    assert signs == [False, False, True, True]
    # every point is close to the curve (relative to the diagonal)
    diag = bbox_diagonal(pts)
    from torch_isc.metrics import point_distances
    d = point_distances(pts, res.polylines)
    assert float(d.max()) < 0.02 * diag


# ----------------------------------------------------------------------------- batches


def test_batch_independence(device):
    names = ["annulus", "circle", "two"]
    pts = [solved(n, device)[0] for n in names]
    batch = reconstruct_batch(pts, names=names)
    assert [r.name for r in batch] == names
    for n, p, rb in zip(names, pts, batch):
        _, ra = solved(n, device)
        assert (rb.num_closed, rb.num_open) == (ra.num_closed, ra.num_open)
        assert hausdorff(rb.polylines, ra.polylines) < 1e-3 * bbox_diagonal(p.cpu())
        if device.type == "cpu":           # CUDA's atomic adds: equal to rounding only (the bound above)
            assert polys_equal(rb.polylines, ra.polylines), f"{n}: result depends on its batch"
        assert [s.triangles for s in rb.stats] == [s.triangles for s in ra.stats]
        assert torch.equal(rb.points, p)


def mixed_shapes(count, seed):
    """``count`` noisy point sets of 120-400 points: circles, ellipses, flowers, two circles
    and annuli in turn, each with its own scale (0.1-10), rotation and offset (+-100)."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for i in range(count):
        u = torch.rand(8, generator=g, dtype=torch.float64)
        n = int(120 + 280 * u[0])
        kind = i % 5
        t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n) + u[1]
        if kind == 0:
            p = torch.stack([t.cos(), t.sin()], 1)
        elif kind == 1:
            p = torch.stack([t.cos(), (0.3 + 0.4 * u[2]) * t.sin()], 1)
        elif kind == 2:
            r = 1 + 0.3 * torch.cos(5 * t)
            p = torch.stack([r * t.cos(), r * t.sin()], 1)
        elif kind == 3:
            h = n // 2
            p = torch.cat([circle(h, 1.0, (-1.4, 0.0)), circle(n - h, 0.8, (1.3, 0.2), float(u[2]))])
        else:
            h = (3 * n) // 5
            p = torch.cat([circle(h, 1.0), circle(n - h, 0.55, phase=float(u[2]))])
        p = p + 0.002 * torch.randn(p.shape, generator=g, dtype=torch.float64)
        a = 2 * math.pi * float(u[3])
        R = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=torch.float64)
        scale = 10 ** (2 * float(u[4]) - 1)
        out.append((p @ R.T) * scale + 200 * (u[5:7] - 0.5))
    return out


def test_batch_of_64_mixed_items_equals_each_solved_alone():
    """Issue 5's rule: in a batch of 64 mixed items (sizes, shapes, scales and the levels
    they finish at all differ) every item has the components and, within 1e-3 of its
    diagonal, the curve it has when solved alone."""
    sets = mixed_shapes(64, seed=5)
    batch = reconstruct_batch(sets)
    levels = {len(r.stats) for r in batch}
    assert len(levels) >= 2                              # items leave the batch at different levels
    for i, (p, rb) in enumerate(zip(sets, batch)):
        ra = reconstruct(p)
        assert (rb.num_closed, rb.num_open) == (ra.num_closed, ra.num_open), f"item {i}"
        assert hausdorff(rb.polylines, ra.polylines) < 1e-3 * bbox_diagonal(p), f"item {i}"
        assert len(rb.stats) == len(ra.stats), f"item {i}"


@pytest.mark.parametrize("seed,item", [(3, 4), (3, 14), (3, 34), (3, 49), (4, 34), (5, 19)])
def test_sparse_annulus_is_not_cut_into_pieces(seed, item):
    """Annuli of 120-200 points (ring 0.45 of the radius wide) that came out as 6 pieces: a
    curvature-biased noise estimate (5-9x the true noise) stopped them at the first mesh, and
    walls of curve across the ring, which no data point is near, passed the data-to-curve
    test. (Of the 384 items of seeds 1-6, 2 still fail, against 11 before.)"""
    p = mixed_shapes(64, seed=seed)[item]
    res = reconstruct(p)
    assert (res.num_closed, res.num_open) == (2, 0)
    assert res.converged
    # both curves are near the data: every polyline vertex within 3% of the diagonal of a point
    diag = bbox_diagonal(p)
    for pl in res.polylines:
        d = torch.cdist(pl["points"].double(), p).min(1).values
        assert float(d.max()) < 0.03 * diag


def test_distinct_points_packed_against_a_loop():
    """Exact repeats are merged per item, first occurrences kept in input order (-0.0 equals
    0.0; integer and float32 inputs compared exactly in float64), each with its row in the
    caller's set; a set left with fewer than 3 distinct points is named in the error."""
    from torch_isc.core.points import distinct_points as _distinct
    g = torch.Generator().manual_seed(0)
    a = torch.randint(0, 4, (50, 2), generator=g)
    b = torch.tensor([[0.0, 1.0], [-0.0, 1.0], [2.0, 2.0], [3.0, 1.0], [2.0, 2.0]])
    c = torch.randn(20, 2, generator=g).float().repeat(2, 1)
    d = torch.randn(30, 2, generator=g, dtype=torch.float64)

    def first_occurrences(x):
        seen, out, rows = set(), [], []
        for i, r in enumerate(x.double().tolist()):
            key = (r[0] + 0.0, r[1] + 0.0)
            if key not in seen:
                seen.add(key)
                out.append(r)
                rows.append(i)
        return torch.tensor(out, dtype=torch.float64), rows

    sets = [a, b, c, d]
    pts, item, counts, source = _distinct(sets, ["a", "b", "c", "d"])
    assert pts.dtype == torch.float64
    assert counts.tolist() == [first_occurrences(x)[0].shape[0] for x in sets]
    for k, x in enumerate(sets):
        want, rows = first_occurrences(x)
        assert torch.equal(pts[item == k], want), k
        assert source[item == k].tolist() == rows, k
    # no repeat at all: every row kept, its own index
    _, _, _, src = _distinct([d, d[:7]], ["d", "e"])
    assert src.tolist() == list(range(30)) + list(range(7))
    with pytest.raises(PointSetError, match="^two: needs at least 3 distinct points, got 2$"):
        _distinct([d, torch.tensor([[1.0, 1.0], [1.0, 1.0], [2.0, 0.0]])], ["one", "two"])


def glyph_four(thickness):
    """The outlines of a '4' in OpenCV's Hershey simplex font (outer boundary and the
    triangular counter, whose corners are acute wedges), unit height, from a 1024 px render."""
    import cv2
    img = np.zeros((1024, 1024), np.uint8)
    (w, h), _ = cv2.getTextSize("4", cv2.FONT_HERSHEY_SIMPLEX, 18.0, thickness)
    cv2.putText(img, "4", ((1024 - w) // 2, (1024 + h) // 2), cv2.FONT_HERSHEY_SIMPLEX, 18.0, 255, thickness,
                cv2.LINE_AA)
    contours, _ = cv2.findContours((img > 127).astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    out = []
    for c in contours:
        if cv2.contourArea(c) >= 400:
            c = cv2.approxPolyDP(c, 1.0, True)[:, 0, :].astype(np.float64)
            out.append(np.stack([c[:, 0], 1024 - c[:, 1]], 1) / 1024)
    return out


def resample_closed(poly, n, phase=0.3):
    q = np.concatenate([poly, poly[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*(q[1:] - q[:-1]).T))])
    u = (phase + np.arange(n)) / n * s[-1]
    return np.stack([np.interp(u, s, q[:, 0]), np.interp(u, s, q[:, 1])], 1)


@pytest.mark.parametrize("thickness", [40, 70])
def test_glyph_with_acute_counter_has_no_pinched_off_loop(thickness):
    """The counter of a '4' ends in acute corners; the wedge tip used to be cut off as a third
    loop (a single inside vertex whose star the data cannot resolve): 2 curves now."""
    outlines = glyph_four(thickness)
    assert len(outlines) == 2
    pts = torch.as_tensor(np.concatenate([resample_closed(o, 300) for o in outlines]))
    res = reconstruct(pts)
    assert (res.num_closed, res.num_open) == (2, 0)
    truth = [(torch.as_tensor(resample_closed(o, 4000, 0.0)), True) for o in outlines]
    assert hausdorff(res.polylines, truth) < 0.02 * bbox_diagonal(pts)
    # the rules alone, without the crust coupling (pipeline/crust.py), which keeps this tip on
    # its body by itself on clean data (with it, the rules off still give 2 loops)
    off = reconstruct(pts, ReconstructConfig().replace(min_island_vertices=0, open_tolerances=0.0, crust_weight=0.0))
    assert off.num_closed == 3                          # the rules are what removes the third loop
    # either rule alone removes it (the speck rule: pipeline/simplify.py)
    assert reconstruct(pts, ReconstructConfig().replace(min_island_vertices=0, crust_weight=0.0)).num_closed == 2
    assert reconstruct(pts, ReconstructConfig().replace(open_tolerances=0.0)).num_closed == 2


def test_empty_batch():
    assert reconstruct_batch([]) == []


# ----------------------------------------------------------------------------- invariances


@pytest.mark.parametrize("scale,offset,dtype", [(1000.0, (5e3, -2e3), torch.float64),
                                                (1000.0, (5e3, -2e3), torch.float32),
                                                (1e-3, (0.0, 0.0), torch.float64),
                                                (1.0, (1e4, -1e4), torch.float64)])
def test_translation_scale_invariance(scale, offset, dtype):
    pts, ref = solved("annulus")
    off = torch.tensor(offset, dtype=torch.float64)
    q = (pts * scale + off).to(dtype)
    res = reconstruct(q)
    assert (res.num_closed, res.num_open) == (ref.num_closed, ref.num_open)
    back = [{"closed": p["closed"], "points": (p["points"].double() - off) / scale} for p in res.polylines]
    assert hausdorff(back, ref.polylines) < 1e-3 * bbox_diagonal(pts)
    # stats are in the caller's units
    for a, b in zip(res.stats, ref.stats):
        assert a.tolerance == pytest.approx(b.tolerance * scale, rel=1e-3)
        assert a.triangles == b.triangles


def test_large_offset_keeps_precision():
    """float64 input far from the origin, float32 solve: the outputs keep the input's precision."""
    pts, ref = solved("annulus")
    off = torch.tensor([1e7, -1e7], dtype=torch.float64)
    res = reconstruct(pts + off)
    assert (res.num_closed, res.num_open) == (ref.num_closed, ref.num_open)
    back = [{"closed": p["closed"], "points": p["points"].double() - off} for p in res.polylines]
    assert hausdorff(back, ref.polylines) < 1e-3 * bbox_diagonal(pts)


def test_large_offset_float64_config():
    pts, ref = solved("annulus")
    off = torch.tensor([1e7, -1e7], dtype=torch.float64)
    res = reconstruct(pts + off, ReconstructConfig().replace(dtype="float64"))
    assert (res.num_closed, res.num_open) == (ref.num_closed, ref.num_open)
    back = [{"closed": p["closed"], "points": p["points"].double() - off} for p in res.polylines]
    assert hausdorff(back, CASES["annulus"][1]) < 0.02 * 2.0


@pytest.mark.parametrize("name", ["two", "annulus"])
def test_float64_same_topology(name):
    pts, ref = solved(name)
    res = reconstruct(pts, ReconstructConfig().replace(dtype="float64"))
    assert res.curve.mesh.dtype == torch.float64
    assert (res.num_closed, res.num_open) == (ref.num_closed, ref.num_open)
    # the refinement may take another path; both are accurate
    assert hausdorff(res.polylines, CASES[name][1]) < 0.02 * 2.0
    assert hausdorff(res.polylines, ref.polylines) < 0.01 * bbox_diagonal(pts)


def test_absolute_tolerance_matches_relative():
    pts, ref = solved("annulus")
    diag = bbox_diagonal(pts)
    res = reconstruct(pts * 7.0, ReconstructConfig().replace(tolerance_mode="absolute", tolerance=0.004 * diag * 7.0))
    assert (res.num_closed, res.num_open) == (ref.num_closed, ref.num_open)
    back = [{"closed": p["closed"], "points": p["points"].double() / 7.0} for p in res.polylines]
    assert hausdorff(back, ref.polylines) < 1e-3 * diag


def test_input_types_agree():
    pts, ref = solved("circle")
    for inp in (pts.numpy(), pts.tolist()):
        res = reconstruct(inp)
        assert polys_equal(res.polylines, ref.polylines)


def test_determinism_and_seed():
    pts, ref = solved("annulus")
    again = reconstruct(pts)
    assert polys_equal(again.polylines, ref.polylines)
    other = reconstruct(pts, ReconstructConfig().replace(seed=12345))
    assert (other.num_closed, other.num_open) == (2, 0)


# ----------------------------------------------------------------------------- sign oracle


def test_sign_oracle_disc():
    pts = circle(150, 2.0, (1.0, -3.0), 0.2)
    calls = []

    def oracle(v):
        calls.append(v.shape[0])
        assert v.shape[1] == 2
        return ((v - torch.tensor([1.0, -3.0], dtype=v.dtype)) ** 2).sum(1) < 4.0

    res = reconstruct(pts, sign_oracle=oracle)
    assert calls
    assert (res.num_closed, res.num_open) == (1, 0)
    assert hausdorff(res.polylines, [truth_circle(2.0, (1.0, -3.0))]) < 0.02 * 4.0
    assert polygon_signed_area(res.polylines[0]["points"]) > 0


def test_sign_oracle_boundary_is_outside():
    """An oracle that calls everything outside a disc 'inside': the outer boundary is still held
    outside, so the zero set is the disc (a hole, clockwise) plus a loop inside the mesh boundary."""
    pts = circle(120, 1.0)
    res = reconstruct(pts, sign_oracle=lambda v: (v ** 2).sum(1) > 1.0)
    assert (res.num_closed, res.num_open) == (2, 0)
    areas = sorted(polygon_signed_area(p["points"]) for p in res.polylines)
    assert areas[0] == pytest.approx(-math.pi, rel=0.05)
    assert areas[1] > 4.0
    f = res.curve(torch.tensor([[0.0, 0.0], [1.2, 0.0]], dtype=res.curve.mesh.dtype))
    assert float(f[0]) > 0 > float(f[1])


def test_batched_sign_oracle_equals_per_item_oracles():
    """One batched oracle ``(points, item)`` gives the same result as per-item callables."""
    a, b = circle(120, 1.0), circle(90, 3.0, (10.0, 0.0))
    centres = torch.tensor([[0.0, 0.0], [10.0, 0.0]], dtype=torch.float64)
    radii = torch.tensor([1.0, 3.0], dtype=torch.float64)
    seen = []

    def batched(v, item):
        seen.append(sorted(set(item.tolist())))
        return ((v - centres[item]) ** 2).sum(1) < radii[item] ** 2

    per_item = [lambda v: ((v - centres[0].to(v.dtype)) ** 2).sum(1) < 1.0,
                lambda v: ((v - centres[1].to(v.dtype)) ** 2).sum(1) < 9.0]
    r1 = reconstruct_batch([a, b], sign_oracles=batched)
    r2 = reconstruct_batch([a, b], sign_oracles=per_item)
    assert seen[0] == [0, 1]
    for x, y in zip(r1, r2):
        assert torch.equal(x.curve.values, y.curve.values)
        assert torch.equal(x.curve.mesh.verts, y.curve.mesh.verts)


def test_batched_sign_oracle_wrong_length():
    pts = circle(60, 1.0)
    with pytest.raises(PointSetError, match="returned"):
        reconstruct_batch([pts], sign_oracles=lambda v, item: torch.ones(3, dtype=torch.bool))


def test_sign_oracle_must_cover_every_item():
    pts = circle(60, 1.0)
    with pytest.raises(PointSetError):
        reconstruct_batch([pts, pts], sign_oracles=[lambda v: (v ** 2).sum(1) < 1, None])


# ----------------------------------------------------------------------------- errors and schema


@pytest.mark.parametrize("bad,fragment", [
    ([[0.0, 0.0], [1.0, 1.0], [0.0, 0.0]], "3 distinct"),
    ([[0.0, 0.0], [1.0, 1.0]], "3 distinct"),
    ([[0.0, 0.0]] * 10, "3 distinct"),
    ([[0.0, 0.0], [1.0, float("nan")], [2.0, 2.0], [3.0, 1.0]], "NaN"),
    ([[0.0, 0.0], [1.0, float("inf")], [2.0, 2.0], [3.0, 1.0]], "Inf"),
    (np.zeros((5, 3)), "shape"),
    (np.zeros(6), "shape"),
    (np.zeros((4, 2, 1)), "shape"),
    (np.zeros((0, 2)), "no points"),
    ([["a", "b"], ["c", "d"], ["e", "f"]], "number"),
    (torch.zeros(4, 2, dtype=torch.complex64), "real"),
])
def test_point_set_errors(bad, fragment):
    with pytest.raises(PointSetError) as ei:
        reconstruct(bad)
    msg = str(ei.value)
    assert "\n" not in msg and msg.strip() == msg and msg
    assert fragment in msg
    assert isinstance(ei.value, ValueError)


def test_point_set_error_names_the_item():
    good = circle(50, 1.0)
    with pytest.raises(PointSetError, match=r"^point set 1: ") as ei:
        reconstruct_batch([good, good[:2]])
    assert "\n" not in str(ei.value)
    with pytest.raises(PointSetError, match=r"^spiral: "):
        reconstruct(good[:1], name="spiral")


@pytest.mark.parametrize("pts", [[[0, 0], [1, 0], [2, 0]], [[0.0, 0.0], [0.0, 1.0], [0.0, 2.0], [0.0, 3.0]],
                                 [[0, 0], [5, 0], [0, 5]]])
def test_degenerate_but_valid_inputs_do_not_fail(pts):
    res = reconstruct(pts)
    d = res.to_json_dict()
    json.dumps(d, allow_nan=False)                    # strict JSON: a no-curve result's max_error inf is null
    assert d["num_components"] == res.num_components == len(d["polylines"])
    res.curve.mesh.validate()


def test_json_schema():
    pts, res = solved("annulus")
    d = res.to_json_dict(with_stats=False)
    assert set(d) == {"polylines", "num_components", "bbox"}
    json.dumps(d)
    assert d["num_components"] == 2 == len(d["polylines"])
    for p, q in zip(d["polylines"], res.polylines):
        assert set(p) == {"closed", "points"}
        assert p["closed"] is True
        assert isinstance(p["points"], list) and all(len(xy) == 2 and all(isinstance(c, float) for c in xy)
                                                     for xy in p["points"])
        np.testing.assert_allclose(np.array(p["points"]), q["points"].double().numpy())
    allp = np.concatenate([np.array(p["points"]) for p in d["polylines"]])
    np.testing.assert_allclose(d["bbox"], [*allp.min(0), *allp.max(0)])
    assert d["bbox"] == pytest.approx([-1.0, -1.0, 1.0, 1.0], abs=0.02)
    full = res.to_json_dict()
    assert set(full) == {"polylines", "num_components", "bbox", "stats"}
    json.dumps(full, allow_nan=False)
    assert full["stats"]["converged"] is True and full["stats"]["limit"] is None
    assert full["stats"]["num_closed"] == 2 and full["stats"]["num_open"] == 0
    for s in full["stats"]["levels"]:
        assert DOCUMENTED_STAT_KEYS <= set(s)
        assert s["tolerance"] >= 0.004 * bbox_diagonal(pts) * (1 - 1e-6)
        assert s["max_error"] >= 0 and s["delta1"] >= 0 and s["noise"] >= 0 and s["seconds"] >= 0


# ----------------------------------------------------------------------------- noise and limits


@pytest.mark.parametrize("seed", [0, 1])
def test_noisy_circle(seed):
    """Gaussian noise of 1% of the diameter: still one closed loop, within 3% of the diameter."""
    g = torch.Generator().manual_seed(seed)
    pts = circle(300, 1.0) + 0.02 * torch.randn(300, 2, generator=g, dtype=torch.float64)
    res = reconstruct(pts)
    assert (res.num_closed, res.num_open) == (1, 0)
    assert hausdorff(res.polylines, [truth_circle(1.0)]) < 0.03 * 2.0
    # the noise estimate (caller's units) is of the right size
    assert 0.5 * 0.02 < res.stats[-1].noise < 1.5 * 0.02
    assert polygon_signed_area(res.polylines[0]["points"]) > 0


def test_level_and_triangle_limits():
    pts = CASES["two"][0]()
    # a coarse initial mesh, so the run takes several levels
    cfg = ReconstructConfig().replace(initial_resolution=2)
    full = reconstruct(pts, cfg)
    assert len(full.stats) >= 3
    res = reconstruct(pts, cfg.replace(max_level=1))
    assert len(res.stats) == 2 and res.stats[-1].marked > 0
    assert res.converged is False and res.limit == "max_level"
    assert [s.triangles for s in res.stats] == [s.triangles for s in full.stats[:2]]
    n0 = full.stats[0].triangles
    res2 = reconstruct(pts, cfg.replace(max_triangles=n0 + 1))
    assert len(res2.stats) == 1
    assert res2.converged is False and res2.limit == "max_triangles"
    assert res2.curve.mesh.faces.shape[0] <= n0 + 1


def test_outliers_are_counted_in_the_stats():
    """A circle with 3 far outliers: one loop, the outliers excused by the test (too few points
    to split their triangles) but counted as points beyond the tolerance; without them, 0."""
    pts = circle(200, 1.0)
    out = torch.tensor([[0.1, 0.05], [-0.3, 0.2], [1.6, 1.5]], dtype=torch.float64)
    clean = reconstruct(pts)
    dirty = reconstruct(torch.cat([pts, out]))
    assert clean.stats[-1].points_beyond_tolerance == 0
    assert (dirty.num_closed, dirty.num_open) == (1, 0)
    last = dirty.stats[-1]
    assert last.points_beyond_tolerance == 3
    # the count is the independent distance to the extracted curve, thresholded by hand
    d = point_distances(torch.cat([pts, out]), dirty.polylines)
    assert int((d > last.tolerance).sum()) == 3

