"""Fuzzing, ninth round (issue 18, the session-19 report): one fast regression test per failure.

=====================================================  ==========================================
case (what happened before)                            tests
=====================================================  ==========================================
a sign oracle answering numbers (a signed distance)    test_sign_oracle_numbers_are_refused
was read as bool: "inside" on both sides (area 10.42
for a unit disc)
one NaN query point gave NaN gradients to every vertex  test_non_finite_query_points_do_not_poison_gradients
(``c(P)``, ``point_curve_distance``, ``soft_inside``)
``centroid`` of an item with no inside region: NaN      test_centroid_of_an_empty_item_has_a_zero_gradient
gradients for the whole batch's vertices
arguments on another device (meta for a GPU), a result  test_arguments_on_another_device_or_of_another_kind_are_named
for a curve, a tensor tau of two numbers, float64
positions for a float32 curve: raw torch errors
queries of a curve at 1e200 or 1e-160 (float32: 1e20,   test_curve_queries_hold_at_every_scale
1e-18): centre "outside", length 8e7x too large,
"local" occupancy 0.5 everywhere
``c[0:1]``, ``pixel_centers`` and ``rasterize`` extents, test_indexing_and_image_arguments_are_checked
``render_curve(size=10**9)``: raw errors, a 2.6 EiB
allocation
``refit`` dropped NaN/Inf points silently               test_refit_refuses_non_finite_points
a directory where an output goes: the line named the    test_an_output_blocked_by_a_directory_is_named
folder or a temporary file, not the output
=====================================================  ==========================================
"""
from __future__ import annotations

import math

import pytest
import torch

from torch_isc import ImplicitCurve, hexagon_mesh, reconstruct_batch
from torch_isc.core.measures import area, centroid, point_curve_distance
from torch_isc.core.render import soft_inside
from torch_isc.pipeline.signs import SignOracleError


def _disc(r=0.5, res=3):
    m = hexagon_mesh(torch.zeros(1, 2, dtype=torch.float64), torch.ones(1), res)
    return m, m.verts.norm(dim=1) - r


def test_sign_oracle_numbers_are_refused():
    t = torch.linspace(0, 2 * math.pi, 41, dtype=torch.float64)[:-1]
    circ = torch.stack([t.cos(), t.sin()], 1)
    with pytest.raises(SignOracleError, match="returned torch.float64 values, not booleans"):
        reconstruct_batch([circ], sign_oracles=[lambda p: p.norm(dim=1) - 1.0])
    with pytest.raises(SignOracleError, match="not booleans"):
        reconstruct_batch([circ], sign_oracles=[lambda p: 2 * (p.norm(dim=1) < 1).long()])
    # booleans and integer 0/1 answers: the same curve, the unit disc (area within 2% of pi)
    a = reconstruct_batch([circ, circ], sign_oracles=[lambda p: p.norm(dim=1) < 1, lambda p: (p.norm(dim=1) < 1).long()])
    assert torch.equal(a[0].curve.values, a[1].curve.values)
    assert float(area(a[0].curve)[0]) == pytest.approx(math.pi, rel=0.02)


def test_non_finite_query_points_do_not_poison_gradients():
    m, v = _disc()
    vals = v.clone().requires_grad_()
    c = ImplicitCurve(m, vals)
    bad = torch.tensor([[float("nan"), 0.0], [float("inf"), 1.0]], dtype=torch.float64)
    good = torch.tensor([[0.0, 0.0], [0.3, 0.1]], dtype=torch.float64)
    P = torch.cat([bad, good])
    # the values for the good rows equal the all-good query's, bit for bit
    f, f_ref = c(P), c(good)
    assert torch.equal(f[2:], f_ref) and bool((f[:2] == float("inf")).all())
    d, d_ref = point_curve_distance(c, P), point_curve_distance(c, good)
    assert torch.equal(d[2:], d_ref) and math.isnan(float(d[0].detach())) and float(d[1].detach()) == float("inf")
    s, s_ref = soft_inside(c, P, 0.05), soft_inside(c, good, 0.05)
    assert torch.equal(s[2:], s_ref) and s[:2].tolist() == [0.0, 0.0]
    for fn in (lambda q: c(q), lambda q: point_curve_distance(c, q), lambda q: soft_inside(c, q, 0.05),
               lambda q: soft_inside(c, q, 0.05, mode="local")):
        g_all = torch.autograd.grad(fn(P)[2:].sum(), vals)[0]
        g_ref = torch.autograd.grad(fn(good).sum(), vals)[0]
        assert bool(torch.isfinite(g_all).all()) and torch.equal(g_all, g_ref)


def test_centroid_of_an_empty_item_has_a_zero_gradient():
    m, v = _disc()
    c2 = ImplicitCurve.cat([ImplicitCurve(m, v), ImplicitCurve(m, m.verts.norm(dim=1) + 0.5)])   # item 1: all outside
    verts = c2.mesh.verts.clone().requires_grad_()
    cc = ImplicitCurve(c2.mesh.with_verts(verts), c2.values)
    cen = centroid(cc)
    assert torch.isnan(cen[1]).all() and cen[0].abs().max() < 1e-12          # the disc's centre is 0
    g = torch.autograd.grad(torch.nan_to_num(cen).sum(), verts)[0]
    assert bool(torch.isfinite(g).all())
    assert float(g[c2.mesh.vert_item == 1].abs().max()) == 0.0
    # item 0's gradient is its own alone: the same as for the disc by itself
    v0 = m.verts.clone().requires_grad_()
    g0 = torch.autograd.grad(centroid(ImplicitCurve(m.with_verts(v0), v)).sum(), v0)[0]
    torch.testing.assert_close(g[c2.mesh.vert_item == 0], g0, rtol=1e-12, atol=1e-15)


def test_arguments_on_another_device_or_of_another_kind_are_named():
    """meta tensors stand in for a GPU: each call raised a raw torch error (``Tensor.item()``
    on meta, a device RuntimeError, ``'ReconstructionResult' object has no attribute 'mesh'``)."""
    from torch_isc.core.curve import InvalidValuesError
    from torch_isc.core.mesh import InvalidMeshError
    from torch_isc.core.render import rasterize

    m, v = _disc()
    c = ImplicitCurve(m, v)
    with pytest.raises(InvalidValuesError, match="values are on meta, the mesh on cpu"):
        ImplicitCurve(m, v.to("meta"))
    with pytest.raises(ValueError, match="cat: curve 1 is on meta, curve 0 on cpu"):
        ImplicitCurve.cat([c, ImplicitCurve(m.to("meta"), v.to("meta"), validate=False)])
    with pytest.raises(InvalidMeshError, match="deform: verts are on meta, the curve on cpu"):
        c.deform(m.verts.to("meta"))
    with pytest.raises(InvalidMeshError, match="deform: verts must be a real floating tensor, got a torch.bool"):
        c.deform(m.verts > 0)
    with pytest.raises(InvalidValuesError, match="magnitudes are on meta, the curve on cpu"):
        c.rescale(v.abs().to("meta"))
    with pytest.raises(ValueError, match="tau is on meta, the curve on cpu"):
        soft_inside(c, torch.zeros(1, 2, dtype=torch.float64), torch.tensor(0.1, device="meta"))
    with pytest.raises(ValueError, match=r"tau must be one real floating number, got a \(2,\)"):
        rasterize(c, 4, 4, torch.tensor([0.1, 0.2]))
    res = reconstruct_batch([m.verts[m.vert_item == 0] * 3.0])[0]      # any result object
    for fn in (area, centroid, lambda x: point_curve_distance(x, torch.zeros(1, 2)), lambda x: rasterize(x, 4, 4, 0.1)):
        with pytest.raises(TypeError, match=r"expected an ImplicitCurve \(use result.curve\), got ReconstructionResult"):
            fn(res)
    # float64 positions for a float32 curve: both float64 in the clamped and the strict motion
    c32 = c.to(dtype=torch.float32)
    target = c32.mesh.verts.double()
    k = int(m.verts.norm(dim=1).argmin())                   # the centre: an interior vertex
    target[k] += 0.01
    moved, t = c32.deform(target, clamp=True)
    assert moved.mesh.verts.dtype == torch.float64 and float(t) == 1.0
    torch.testing.assert_close(moved.mesh.verts, target, rtol=0, atol=1e-15)
    assert torch.equal(c32.deform(target).mesh.verts, target)


@pytest.mark.parametrize("dtype,scales", [(torch.float64, (1e-300, 1e-200, 1e-160, 1e160, 1e200, 1e300)),
                                          (torch.float32, (1e-30, 1e-20, 1e20, 1e30))])
def test_curve_queries_hold_at_every_scale(dtype, scales):
    """A unit circle's curve scaled by k (exactly: the same mesh and values, positions times k)
    answers every query as the unit one does, times k: the centre was "outside" at 1e200
    (triangle areas overflowed), the length 8e7 times too large at 1e-160 (squared lengths
    floored at the smallest normal), soft_inside 0.5 everywhere in "local" mode."""
    from torch_isc.core.measures import length
    from torch_isc.core.render import rasterize

    m, v = _disc(0.6, 4)
    m, v = m.to(dtype=dtype), v.to(dtype)
    c1 = ImplicitCurve(m, v)
    q1 = torch.tensor([[0.0, 0.0], [0.9, 0.1], [0.5, -0.2], [3.0, 0.0]], dtype=dtype)
    rtol = 1e-12 if dtype == torch.float64 else 1e-5
    ref = dict(inside=c1.inside(q1), f=c1(q1), length=length(c1), centroid=centroid(c1),
               dist=point_curve_distance(c1, q1), soft=soft_inside(c1, q1, 0.05),
               local=soft_inside(c1, q1, 0.05, mode="local"), raster=rasterize(c1, 8, 8, 0.05))
    for k in scales:
        ck = ImplicitCurve(m.with_verts(m.verts * k), v * k)        # values scale with the distances
        qk = q1 * k
        assert torch.equal(ck.inside(qk), ref["inside"]), k
        torch.testing.assert_close(ck(qk)[:3] / k, ref["f"][:3], rtol=rtol, atol=0)
        torch.testing.assert_close(length(ck) / k, ref["length"], rtol=rtol, atol=0)
        torch.testing.assert_close(centroid(ck) / k, ref["centroid"], rtol=rtol, atol=rtol)
        torch.testing.assert_close(point_curve_distance(ck, qk) / k, ref["dist"], rtol=rtol, atol=0)
        torch.testing.assert_close(soft_inside(ck, qk, 0.05 * k), ref["soft"], rtol=rtol, atol=rtol)
        torch.testing.assert_close(soft_inside(ck, qk, 0.05 * k, mode="local"), ref["local"], rtol=rtol, atol=rtol)
        torch.testing.assert_close(rasterize(ck, 8, 8, 0.05 * k), ref["raster"], rtol=rtol, atol=rtol)
    # the area scales by k^2: representable at 1e100 (float64), an honest inf / 0 beyond
    if dtype == torch.float64:
        ck = ImplicitCurve(m.with_verts(m.verts * 1e100), v * 1e100)
        torch.testing.assert_close(area(ck) / 1e200, area(c1), rtol=1e-12, atol=0)
        assert float(area(ImplicitCurve(m.with_verts(m.verts * 1e200), v * 1e200))[0]) == float("inf")


def test_indexing_and_image_arguments_are_checked():
    """``c[0:1]`` raised a TypeError from ``int()``, ``c[0.5]`` torch's IndexError;
    ``pixel_centers`` with a 1-D extent an IndexError, a negative size torch's range error;
    ``rasterize(extent=['a'] * 4)`` "too many dimensions 'str'"; ``render_curve(size=10**9)``
    numpy's MemoryError (2.6 EiB), ``size=nan`` a ValueError from ``int()``."""
    from torch_isc.core.render import pixel_centers, rasterize
    from torch_isc.io.png import MAX_RENDER_SIZE, render_curve

    m, v = _disc()
    c = ImplicitCurve.cat([ImplicitCurve(m, v), ImplicitCurve(m, m.verts.norm(dim=1) - 0.3), ImplicitCurve(m, v + 0.1)])
    two = c[1:3]
    assert two.num_items == 2
    assert torch.equal(two.values, torch.cat([c[1].values, c[2].values]))
    assert torch.equal(two.mesh.verts, torch.cat([c[1].mesh.verts, c[2].mesh.verts]))
    assert torch.equal(c[0::2].values, torch.cat([c[0].values, c[2].values]))
    assert torch.equal(c[-1].values, c[2].values)
    for bad, err, why in ((0.5, TypeError, "integer or a slice, got float"), (3, IndexError, "out of range"),
                          (slice(2, 2), IndexError, "selects no item"), (slice(None, None, -1), IndexError, "item order")):
        with pytest.raises(err, match=why):
            c[bad]
    ext = torch.tensor([[0.0, 0.0, 1.0, 1.0]], dtype=torch.float64)
    assert pixel_centers(2, 2, ext)[0, 1, 0].tolist() == [0.25, 0.75]      # row 1 grows with y, column 0
    for h, e, why in ((-1, ext, "height must be an integer >= 0"), (2, ext[0], r"extent must be a \(B, 4\)"),
                      (2, [[0, 0, 1, 1]], r"extent must be a \(B, 4\) floating tensor, got list")):
        with pytest.raises(ValueError, match=why):
            pixel_centers(h, 2, e)
    for extent in (["a"] * 4, [None] * 4):
        with pytest.raises(ValueError, match="extent must be 4 numbers"):
            rasterize(c, 4, 4, 0.1, extent=extent)
    for size in (10 ** 9, float("nan"), 8.5, MAX_RENDER_SIZE + 1, 15):
        with pytest.raises(ValueError, match=f"size must be an integer of 16 to {MAX_RENDER_SIZE} pixels"):
            render_curve(c[0], size=size)
    assert render_curve(c[0], size=16).shape == (16, 16, 3)


def test_refit_refuses_non_finite_points():
    """refit dropped NaN and Inf points without a word (reconstruct raises for them)."""
    from torch_isc import PointSetError
    from torch_isc.pipeline.refit import refit

    m, v = _disc()
    c = ImplicitCurve(m, v)
    t = torch.linspace(0, 2 * math.pi, 25, dtype=torch.float64)[:-1]
    p = 0.5 * torch.stack([t.cos(), t.sin()], 1)
    for bad in (float("nan"), float("inf")):
        q = p.clone()
        q[3, 1] = bad
        with pytest.raises(PointSetError, match=r"refit: points: 1 row\(s\) hold NaN or Inf \(first at row 3\)"):
            refit(c, q)
    assert torch.isfinite(refit(c, p).values).all()


def test_an_output_blocked_by_a_directory_is_named(tmp_path, capsys):
    """A directory where ``a.json`` goes: the line said "cannot write outputs in out (Is a
    directory)", or named the temporary file, not the output."""
    import numpy as np
    from torch_isc.cli import main

    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    np.savetxt(tmp_path / "a.xy", np.stack([np.cos(t), np.sin(t)], 1))
    (tmp_path / "out" / "a.json").mkdir(parents=True)
    assert main(["reconstruct", str(tmp_path / "a.xy"), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert f"cannot write outputs in {tmp_path / 'out' / 'a.json'} (Is a directory)" in err, err
