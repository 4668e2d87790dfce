"""torch_isc.images: masks and grayscale images to curves, checked against analytic shapes.

Pixel convention under test: x right, y down, pixel (i, j) covers [j, j+1] x [i, i+1]; an
OpenCV point (u, v) is (u + 0.5, v + 0.5) here.
"""
import math

import cv2
import numpy as np
import pytest
import torch

from torch_isc import images, metrics
from torch_isc.images import (ImageError, MaskOracle, edge_points, find_contours, load_contours, mask_crack_contours,
                              grid_results, mask_to_points, read_image, reconstruct_edges, reconstruct_masks,
                              resample_closed, to_cv_contours)
from torch_isc.io import render_overlay, write_contours

SHIFT = 8


def _cv_disc(img, c, r, value=255, aa=False, k=8):
    """Draw a filled disc of centre ``c`` (pixel convention) and radius ``r`` into ``img`` with
    ``cv2.circle``. OpenCV's rasterization rounds outward (a disc comes out about half a pixel
    too large), so it draws at ``k`` times the resolution and each pixel takes the majority of
    its ``k x k`` sub-pixels (``aa``: their mean, an anti-aliased gray disc)."""
    H, W = img.shape
    big = np.zeros((H * k, W * k), np.uint8)
    ctr = tuple(int(round((v * k - 0.5) * (1 << SHIFT))) for v in c)
    cv2.circle(big, ctr, int(round(r * k * (1 << SHIFT))), 1, -1, cv2.LINE_8, SHIFT)
    cover = big.reshape(H, k, W, k).mean((1, 3))
    if aa:
        img[:] = np.rint(img * (1 - cover) + value * cover).astype(img.dtype)
    else:
        img[cover > 0.5] = value
    return img


def _radial(pl, c):
    p = pl["points"].double().numpy() if isinstance(pl["points"], torch.Tensor) else np.asarray(pl["points"])
    return np.hypot(p[:, 0] - c[0], p[:, 1] - c[1])


def _centre_sampled_disc(shape, c, r):
    """Exact rendering: a pixel is foreground when its centre is inside the circle."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]] + 0.5
    return ((xx - c[0]) ** 2 + (yy - c[1]) ** 2 < r * r).astype(np.uint8)


# ----------------------------------------------------------------------------- the three shapes
def test_disc_annulus_two_discs_counts_nesting_and_radii():
    c = (40.3, 38.7)
    disc = _cv_disc(np.zeros((80, 84), np.uint8), c, 22.4)
    ann = _cv_disc(np.zeros((90, 90), np.uint8), (45.2, 44.6), 34.0)
    _cv_disc(ann, (45.2, 44.6), 15.5, 0)
    two = _cv_disc(np.zeros((70, 110), np.uint8), (30.5, 35.0), 18.0)
    _cv_disc(two, (80.0, 34.5), 20.0)
    res = reconstruct_masks([disc, ann, two])
    assert [(r.num_closed, r.num_open) for r in res] == [(1, 0), (2, 0), (2, 0)]
    assert all(r.converged for r in res)
    # within a pixel of the analytic circles
    assert np.abs(_radial(res[0].polylines[0], c) - 22.4).max() < 1.0
    rad = sorted((_radial(pl, (45.2, 44.6)).mean(), pl) for pl in res[1].polylines)
    assert np.abs(_radial(rad[0][1], (45.2, 44.6)) - 15.5).max() < 1.0
    assert np.abs(_radial(rad[1][1], (45.2, 44.6)) - 34.0).max() < 1.0
    for pl in res[2].polylines:
        cc, r = ((30.5, 35.0), 18.0) if pl["points"][:, 0].mean() < 55 else ((80.0, 34.5), 20.0)
        assert np.abs(_radial(pl, cc) - r).max() < 1.0
    # nesting as OpenCV reports it
    for mode, cvmode in (("tree", cv2.RETR_TREE), ("ccomp", cv2.RETR_CCOMP)):
        for r, m in zip(res, (disc, ann, two)):
            ours, h = to_cv_contours(r, mode)
            theirs, h_cv = cv2.findContours(m, cvmode, cv2.CHAIN_APPROX_NONE)[-2:]
            assert h.shape == h_cv.shape
            # the same contours (matched by centroid and size; the order may differ), the same parents
            cen = np.array([[*a.reshape(-1, 2).mean(0), math.sqrt(cv2.contourArea(a))] for a in ours])
            cen_cv = np.array([[*b.reshape(-1, 2).mean(0), math.sqrt(cv2.contourArea(b))] for b in theirs])
            match = np.linalg.norm(cen[:, None] - cen_cv[None], axis=2).argmin(1)
            assert sorted(match.tolist()) == list(range(len(ours)))
            for k, a in enumerate(ours):
                b, par, par_cv = theirs[match[k]], h[0, k, 3], h_cv[0, match[k], 3]
                assert par_cv == (match[par] if par >= 0 else -1), (mode, k, par, par_cv)
                assert np.sign(cv2.contourArea(a, True)) == np.sign(cv2.contourArea(b, True))   # orientation


def test_subpixel_beats_pixel_tracers_on_a_disc():
    c, r = (32.37, 30.81), 20.3
    m = _centre_sampled_disc((64, 64), c, r)
    res = reconstruct_masks([m])[0]
    ours = np.abs(_radial(res.polylines[0], c) - r).mean()
    cvp = cv2.findContours(m, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)[-2][0].reshape(-1, 2) + 0.5
    theirs = np.abs(np.hypot(*(cvp - c).T) - r).mean()
    # the marching-squares polyline through the crack midpoints (what skimage's find_contours gives)
    ms = [(q, True) for q in mask_crack_contours(m)[0]]
    truth = [(np.stack([c[0] + r * np.cos(t), c[1] + r * np.sin(t)], 1), True)
             for t in [np.linspace(0, 2 * np.pi, 2000, endpoint=False)]]
    ch = {name: metrics.chamfer(pl, truth, 0.05) for name, pl in
          (("ours", res.polylines), ("cv2", [(cvp, True)]), ("marching squares", ms))}
    assert ours < 0.2 and ours < theirs, (ours, theirs)
    assert ch["ours"] < 0.15 and ch["ours"] < ch["cv2"] and ch["ours"] < ch["marching squares"], ch


def test_thin_stroke_and_close_curves_keep_the_mask_topology():
    m = np.zeros((60, 60), np.uint8)
    cv2.rectangle(m, (10, 10), (49, 49), 1, 2)               # a square ring 2 px wide
    cv2.rectangle(m, (20, 20), (39, 21), 1, -1)              # a bar 2 px high inside it
    res = reconstruct_masks([m])[0]
    assert (res.num_closed, res.num_open) == (3, 0)
    _, h = to_cv_contours(res, "tree")
    assert sorted(h[0, :, 3].tolist()) == [-1, 0, 1] or sorted((h[0, :, 3] >= 0).tolist()) == [False, True, True]


def test_oracle_refines_where_a_stroke_passes_between_vertices():
    """Strokes 2-3 px wide between coarse mesh vertices: the vertex signs miss them, the
    points near them still lie near some piece of curve, so only the oracle's midpoint check
    (reconstruct marks triangles whose edge midpoints disagree with f) recovers them, with no
    retry. One diagonal line crosses the ring: cv2 counts the contours to expect."""
    for th in (2, 3):
        m = np.zeros((128, 128), np.uint8)
        cv2.circle(m, (64, 64), 40, 255, th)
        cv2.line(m, (10, 120), (120, 100), 255, th)
        n = len(cv2.findContours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)[0])
        res = reconstruct_masks([m], retry=False)[0]
        assert (res.num_closed, res.num_open) == (n, 0), th


# ----------------------------------------------------------------------------- edges
def test_edges_mode_recovers_a_drawn_circle():
    c, r = (40.6, 38.2), 24.0
    img = _cv_disc(np.full((80, 80), 30, np.uint8), c, r, 220, aa=True)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    res = reconstruct_edges([img])[0]
    assert (res.num_closed, res.num_open) == (1, 0)
    d = _radial(res.polylines[0], c) - r
    assert np.abs(d).max() < 1.0 and abs(d.mean()) < 0.3


@pytest.mark.parametrize("centre", [(120.0, 120.0), (119.7, 120.2)])
def test_edges_mode_keeps_a_thin_ring_whole(centre):
    # a ring 5 px wide: its two edges, each a pixel-spaced sampling, lie 5 px apart; walls across
    # it are split below the data's reach (EDGE_CONFIG's transverse_noisy 0): two loops (with the
    # point-set default, noisy items only, 14 and 4 pieces). Rings 3-4 px wide still fail at some
    # offsets (scripts/evaluate_edges.py)
    R, w = 100.0, 5.0
    yy, xx = np.mgrid[:240, :240] + 0.5
    d = np.hypot(xx - centre[0], yy - centre[1])
    img = cv2.GaussianBlur((((d < R) & (d > R - w)) * 200 + 30).astype(np.uint8), (0, 0), 0.7)
    res = reconstruct_edges([img])[0]
    assert (res.num_closed, res.num_open) == (2, 0) and res.converged
    radii = sorted(float(np.median(_radial(p, centre))) for p in res.polylines)
    assert abs(radii[0] - (R - w)) < 1.0 and abs(radii[1] - R) < 1.0, radii
    cfg = images.image_config(images.EDGE_CONFIG | {"transverse_noisy": 0.5}, mode="edges")
    assert cfg.test.transverse_noisy == 0.5                          # a user's value is kept


def test_edge_points_subpixel_on_a_step_and_batch_of_sizes():
    im = np.zeros((40, 50), np.float32)
    im[:, 20:] = 1.0                                          # a vertical step at x = 20
    p = edge_points([im])[0]
    inner = p[(p[:, 1] > 5) & (p[:, 1] < 35)]
    assert inner.shape[0] >= 25 and torch.allclose(inner[:, 0], torch.full_like(inner[:, 0], 20.0), atol=0.05)
    im2 = np.zeros((30, 30), np.float32)
    im2[10:20, 10:20] = 1.0
    batch = edge_points([im, im2, im])
    for got, alone in zip(batch, [p, edge_points([im2])[0], p]):
        assert torch.equal(got, alone)


# ----------------------------------------------------------------------------- batching
def test_batch_of_different_sizes_equals_each_alone():
    a = _cv_disc(np.zeros((50, 60), np.uint8), (30.2, 25.1), 15.0)
    b = _cv_disc(np.zeros((72, 40), np.uint8), (20.0, 36.0), 14.0)
    _cv_disc(b, (20.0, 36.0), 6.0, 0)
    c = np.zeros((30, 30), np.uint8)
    c[8:22, 5:25] = 255
    together = reconstruct_masks([a, b, c])
    for r, m in zip(together, (a, b, c)):
        alone = reconstruct_masks([m])[0]
        assert len(r.polylines) == len(alone.polylines)
        for p, q in zip(r.polylines, alone.polylines):
            assert p["closed"] == q["closed"] and torch.allclose(p["points"], q["points"], atol=1e-5)


def test_mask_to_points_inputs_device_dtype():
    m = np.zeros((12, 12), bool)
    m[3:9, 2:10] = True
    ref = mask_to_points([m])[0]
    assert ref.dtype == torch.get_default_dtype()
    assert torch.equal(mask_to_points(torch.from_numpy(m)[None])[0], ref)             # (B, H, W) tensor
    assert torch.equal(mask_to_points([m.astype(np.uint8) * 255])[0], ref)            # uint8 nonzero
    assert mask_to_points([m.astype(np.float64)])[0].dtype == torch.float64           # float dtype followed
    assert torch.equal(mask_to_points([m.astype(np.float32) * 0.8], threshold=0.7)[0], ref)
    assert mask_to_points([np.zeros((5, 5))])[0].shape == (0, 2)
    full = mask_to_points([np.ones((4, 6), bool)], spacing=0)[0]                       # the image frame
    assert full[:, 0].min() == 0 and full[:, 0].max() == 6 and full[:, 1].max() == 4


# ----------------------------------------------------------------------------- cracks, resampling, oracle
def _naive_cracks(m):
    out = []
    H, W = m.shape
    for i in range(H):
        for j in range(W):
            if not m[i, j]:
                continue
            for di, dj in ((0, 1), (1, 0), (0, -1), (-1, 0)):
                ii, jj = i + di, j + dj
                if not (0 <= ii < H and 0 <= jj < W) or not m[ii, jj]:
                    out.append((j + 0.5 + 0.5 * dj, i + 0.5 + 0.5 * di))
    return sorted(out)


@pytest.mark.parametrize("seed", range(6))
def test_crack_contours_cover_every_crack_once_in_order(seed):
    rng = np.random.default_rng(seed)
    m = rng.random((9, 11)) < 0.45
    contours, h = mask_crack_contours(m)
    got = sorted(map(tuple, np.concatenate(contours).tolist()))
    assert got == _naive_cracks(m)
    assert h.shape == (len(contours), 4)
    for q in contours:                    # consecutive crack midpoints are neighbours (a closed chain)
        steps = np.linalg.norm(np.diff(np.vstack([q, q[:1]]), axis=0), axis=1)
        assert len(q) == 1 or steps.max() <= 1.0 + 1e-12


def test_crack_contours_orientation():
    m = np.zeros((10, 10), bool)
    m[1:9, 1:9] = True
    m[4:6, 4:6] = False
    contours, h = mask_crack_contours(m)

    def area(q):
        return 0.5 * float((q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1]).sum())
    outer = [q for q, par in zip(contours, h[:, 3]) if par < 0]
    holes = [q for q, par in zip(contours, h[:, 3]) if par >= 0]
    assert len(outer) == 1 and len(holes) == 1
    assert area(outer[0]) > 0 and area(holes[0]) < 0          # foreground on the left
    assert abs(area(outer[0]) - (64 - 0.5)) < 1e-9             # 4 corners cut by 1/8 pixel each
    assert abs(area(holes[0]) + (4 - 0.5)) < 1e-9


def test_resample_closed_uniform():
    t = torch.linspace(0, 2 * math.pi, 400, dtype=torch.float64)[:-1]
    circ = torch.stack([10 * t.cos(), 10 * t.sin()], 1)
    sq = torch.tensor([[0.0, 0], [3, 0], [3, 3], [0, 3]], dtype=torch.float64)
    q, n = resample_closed(torch.cat([circ, sq]), torch.tensor([399, 4]), 0.5)
    assert n.tolist() == [round(2 * 399 * 10 * math.sin(math.pi / 399) / 0.5), 24]
    a, b = q[:n[0]], q[n[0]:]
    steps = (a - a.roll(-1, 0)).norm(dim=1)
    assert torch.allclose(steps, steps.mean().expand_as(steps), rtol=1e-3)
    assert torch.allclose((b - b.roll(-1, 0)).norm(dim=1), torch.full((24,), 0.5, dtype=torch.float64))


def test_mask_oracle_matches_pixel_lookup():
    rng = np.random.default_rng(1)
    masks = [rng.random((7, 9)) < 0.5, rng.random((12, 5)) < 0.5]
    o = MaskOracle(masks, interpolation="nearest")
    pts = torch.from_numpy(rng.uniform(-2, 14, (400, 2)))
    item = torch.from_numpy(rng.integers(0, 2, 400))
    got = o(pts, item).tolist()
    for (x, y), b, g in zip(pts.tolist(), item.tolist(), got):
        H, W = masks[b].shape
        i, j = math.floor(y), math.floor(x)
        assert g == (0 <= i < H and 0 <= j < W and bool(masks[b][i, j]))
    # bilinear: 1/2 at a crack midpoint between a foreground and a background pixel
    ob = MaskOracle([np.array([[1, 0]], bool)])
    v = ob.values(torch.tensor([[1.0, 0.5], [0.5, 0.5], [1.5, 0.5]]), torch.zeros(3, dtype=torch.long))
    assert v.tolist() == [0.5, 1.0, 0.0]


def test_without_oracle_the_topology_is_estimated():
    m = _cv_disc(np.zeros((80, 80), np.uint8), (40.0, 40.0), 30.0)
    _cv_disc(m, (40.0, 40.0), 15.0, 0)
    r = reconstruct_masks([m], use_oracle=False)[0]
    assert (r.num_closed, r.num_open) == (2, 0)


# ----------------------------------------------------------------------------- OpenCV contours
def test_to_cv_contours_tree_and_ccomp_on_nested_squares():
    def sq(a, b):
        return np.array([[a, a], [b, a], [b, b], [a, b]], float)
    squares = [sq(0, 20), sq(2, 18), sq(4, 16), sq(22, 30), sq(6, 8), sq(10, 12)]
    polys = [{"closed": True, "points": q} for q in squares]
    # outer 0 holds the ring hole 1, which holds the island 2, which holds the holes 4 and 5; 3 is apart
    tree_parent = [-1, 0, 1, -1, 2, 2]
    ccomp_parent = [-1, 0, -1, -1, 2, 2]          # two levels: the island is a component again
    m = np.zeros((32, 32), np.uint8)
    cv2.fillPoly(m, [np.rint((p - 0.5)).astype(np.int32) for p in squares[:1] + squares[3:4]], 1)
    for mode, want in (("tree", tree_parent), ("ccomp", ccomp_parent)):
        c, h = to_cv_contours(polys, mode)
        # each contour is one square shifted by -1/2 (OpenCV coordinates): find which by its lower corner
        which = [next(i for i, q in enumerate(squares) if np.allclose(cc.reshape(-1, 2).min(0), q.min(0) - 0.5))
                 for cc in c]
        assert sorted(which) == list(range(6))
        got = [which[p] if p >= 0 else -1 for p in h[0, :, 3]]
        assert [got[which.index(i)] for i in range(6)] == want, mode
    _, h = to_cv_contours(polys, "tree")
    _, hc = to_cv_contours(polys, "ccomp")
    # next/prev are consistent sibling lists, first_child points to a child
    for hh in (h[0], hc[0]):
        for k, (nx, pv, ch, par) in enumerate(hh.tolist()):
            assert nx < 0 or (hh[nx, 1] == k and hh[nx, 3] == par)
            assert ch < 0 or hh[ch, 3] == k
    assert to_cv_contours([]) == ([], None)
    ci, _ = to_cv_contours(polys, dtype=np.int32)
    out = cv2.drawContours(np.zeros((40, 40), np.uint8), ci, -1, 255, 1)
    assert out.any()


def test_find_contours_drop_in_and_contour_file(tmp_path):
    m = np.zeros((50, 50), np.uint8)
    m[5:45, 5:45] = 255
    m[15:35, 15:35] = 0
    m[22:28, 22:28] = 255
    c, h = find_contours(m, "tree")
    cv_c, cv_h = cv2.findContours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_SIMPLE)[-2:]
    assert len(c) == len(cv_c) == 3 and np.array_equal(h, cv_h)
    # areas: those of the pixel squares' union (OpenCV's own contours, through the boundary pixels'
    # centres, enclose half a pixel less all around), signs as OpenCV's
    for a, b, side in zip(c, cv_c, (40, 20, 6)):
        assert np.sign(cv2.contourArea(a, True)) == np.sign(cv2.contourArea(b, True))
        assert abs(cv2.contourArea(a) - side * side) < 0.05 * side * side + 1
    res = reconstruct_masks([m])[0]
    write_contours(tmp_path / "x.contours.npz", res)
    c2, h2 = load_contours(tmp_path / "x.contours.npz")
    c1, h1 = to_cv_contours(res)
    assert np.array_equal(h1, h2) and all(np.array_equal(a, b) for a, b in zip(c1, c2))


def test_overlay_draws_in_the_pixel_convention():
    res = {"polylines": [{"closed": True, "points": np.array([[2.0, 2.0], [18.0, 2.0], [18.0, 18.0], [2.0, 18.0]])}]}
    img = render_overlay(np.zeros((20, 20), np.uint8), res)
    g = img[:, :, 1]
    # the line x = 2 runs along the crack between columns 1 and 2: both get half of the ink
    assert g[10, 1] > 100 and g[10, 2] > 100 and g[10, 0] < 20 and g[10, 3] < 20 and g[10, 10] == 0


# ----------------------------------------------------------------------------- files and bad input
def test_read_image_formats(tmp_path):
    g16 = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000)
    cv2.imwrite(str(tmp_path / "a.tif"), g16)
    a = read_image(tmp_path / "a.tif")
    assert a.dtype == np.float32 and a.shape == (3, 4) and np.allclose(a, g16 / 65535.0, atol=1e-6)
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[..., :3] = 255
    rgba[1:3, 1:3, 3] = 255                             # opaque square on a transparent background
    cv2.imwrite(str(tmp_path / "b.png"), rgba)
    b = read_image(tmp_path / "b.png")
    assert b[1:3, 1:3].min() > 0.99 and b[0].max() == 0
    cv2.imwrite(str(tmp_path / "c.bmp"), np.dstack([np.zeros((3, 3), np.uint8)] * 2 + [np.full((3, 3), 255, np.uint8)]))
    assert 0.25 < read_image(tmp_path / "c.bmp").mean() < 0.35       # red -> gray 0.299


@pytest.mark.parametrize("kind,expect", [
    ("missing", "no such file"), ("empty", "empty file"), ("text", "not a readable image"),
    ("truncated", "not a readable image"), ("folder", "is a directory"),
])
def test_read_image_errors_are_one_line(tmp_path, kind, expect):
    p = tmp_path / "x.png"
    if kind == "empty":
        p.write_bytes(b"")
    elif kind == "text":
        p.write_text("this is not a png\n")
    elif kind == "truncated":
        _, buf = cv2.imencode(".png", np.random.default_rng(0).integers(0, 255, (32, 32), dtype=np.uint8))
        p.write_bytes(buf.tobytes()[:200])
    elif kind == "folder":
        p.mkdir()
    with pytest.raises(ImageError) as e:
        read_image(p)
    msg = str(e.value)
    assert msg.startswith(str(p)) and expect in msg and "\n" not in msg


def test_empty_mask_has_no_curve_and_full_mask_gives_the_frame():
    # as cv2.findContours: an empty mask has no contour; the other masks of the batch are solved
    ring = np.zeros((30, 30), np.uint8)
    ring[5:25, 5:25], ring[12:18, 12:18] = 255, 0
    assert len(cv2.findContours(np.zeros((20, 20), np.uint8), cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)[0]) == 0
    for solve in (reconstruct_masks, grid_results):
        e, r = solve([np.zeros((20, 20), np.uint8), ring], names=["empty", "ring"])
        assert (e.name, e.num_closed, e.num_open, r.num_closed, r.num_open) == ("empty", 0, 0, 2, 0)
    r = reconstruct_masks([np.full((20, 30), 255, np.uint8)], names=["white"])[0]
    assert (r.num_closed, r.num_open) == (1, 0)
    x0, y0, x1, y1 = r.bbox()
    assert abs(x0) < 1 and abs(y0) < 1 and abs(x1 - 30) < 1 and abs(y1 - 20) < 1     # the image frame
    with pytest.raises(ImageError, match="no edges"):
        reconstruct_edges([np.full((20, 20), 0.5, np.float32)])


def test_reconstruct_masks_options_are_image_errors_before_any_work():
    """Fuzzing round 11: ``spacing=nan`` and ``interpolation="cubic"`` raised a bare ValueError,
    ``retry="yes"`` passed; each is now an ImageError naming the option."""
    from torch_isc.images import ImageError, reconstruct_masks
    m = np.zeros((12, 12), np.uint8)
    m[3:9, 3:9] = 1
    for kw, word in ((dict(spacing=float("nan")), "spacing"), (dict(interpolation="cubic"), "interpolation"),
                     (dict(retry="yes"), "retry"), (dict(use_oracle=1), "use_oracle")):
        with pytest.raises(ImageError, match=word):
            reconstruct_masks([m], **kw)
    assert len(reconstruct_masks([m], retry=np.bool_(False))[0].polylines) == 1
