"""images.find_contours against cv2.findContours (contour by contour, parent by parent) and the
grid curves' accuracy on antialiased analytic shapes."""
import numpy as np
import pytest
import torch

cv2 = pytest.importorskip("cv2")
from skimage.data import binary_blobs  # noqa: E402

from torch_isc import images, metrics  # noqa: E402
from torch_isc.images.shapes import SHAPES, shape_mask  # noqa: E402

MODES = [cv2.RETR_TREE, cv2.RETR_CCOMP, cv2.RETR_LIST, cv2.RETR_EXTERNAL]


def _hard_cases():
    out = []
    m = np.zeros((9, 9), np.uint8); m[4, 4] = 1; out.append(m)                      # single pixel
    m = np.ones((9, 9), np.uint8); m[4, 4] = 0; out.append(m)                       # single-pixel hole
    m = np.zeros((8, 8), np.uint8); m[2, 2] = m[3, 3] = m[4, 4] = 1; out.append(m)  # diagonal touches
    m = np.zeros((8, 8), np.uint8); m[2:4, 2:4] = 1; m[4:6, 4:6] = 1; out.append(m)
    m = np.ones((10, 12), np.uint8); m[:, 5] = 0; out.append(m)                      # 1-px channel to the border
    m = np.ones((10, 12), np.uint8); m[3:, 5] = 0; out.append(m)
    m = np.ones((6, 6), np.uint8); out.append(m)                                    # all foreground
    m = np.zeros((6, 6), np.uint8); out.append(m)                                   # empty
    m = np.zeros((12, 12), np.uint8); m[1:11, 1:11] = 1; m[3:9, 3:9] = 0; m[5:7, 5:7] = 1; out.append(m)
    m = np.zeros((7, 7), np.uint8); m[1:6, 1:6] = 1; m[2, 2] = m[3, 3] = m[4, 4] = 0; out.append(m)  # 4-conn holes
    rng = np.random.default_rng(0)
    out += [(rng.random((15, 17)) < p).astype(np.uint8) for p in (0.3, 0.5, 0.7)]
    return out


def _blobs():
    out = []
    for s in range(200):
        size = (32, 64, 128)[s % 3]
        out.append(binary_blobs(size, blob_size_fraction=0.05 + 0.05 * (s % 4), volume_fraction=0.2 + 0.05 * (s % 8),
                                rng=s).astype(np.uint8))
    return out


def _check(mask, mode, ours, tips=None):
    c, h = cv2.findContours(mask, mode, cv2.CHAIN_APPROX_NONE)
    oc, oh = ours
    assert len(oc) == len(c)
    if not c:
        assert oh is None
        return
    np.testing.assert_array_equal(oh, h)
    for q, (a, b) in enumerate(zip(oc, c)):
        A, Bp = a.reshape(-1, 2).astype(float), b.reshape(-1, 2).astype(float)
        # every sub-pixel point lies within a pixel (Chebyshev) of the chain, but near a corner
        # tip restored beyond the band (within 3 px of the chain), and the two contours have
        # the same orientation
        d = np.abs(A[:, None] - Bp[None]).max(2).min(1)
        far = d > 1.0 + 1e-6
        if far.any():
            assert tips is not None and len(tips), (q, d.max())
            near_tip = np.linalg.norm(A[far][:, None] - tips[None], axis=2).min(1) <= 5.5
            assert near_tip.all() and d.max() <= 3.0, (q, d.max())
        if len(Bp) > 2:
            assert np.sign(cv2.contourArea(a, True)) == np.sign(cv2.contourArea(b, True)) or \
                abs(cv2.contourArea(b, True)) == 0


@pytest.mark.parametrize("mode", MODES)
def test_same_contours_as_cv2(mode):
    masks = _hard_cases() + _blobs()
    res = images.find_contours_batch(masks, mode)
    gc = images.trace_masks([torch.from_numpy(m.astype(bool)) for m in masks])
    tips = gc.tips.numpy() - 0.5                      # OpenCV's pixel centres are integers
    for b, (m, r) in enumerate(zip(masks, res)):
        _check(m, mode, r, tips[gc.tip_item.numpy() == b])


def test_names_int32_drawcontours_min_area_simple():
    m = np.zeros((40, 40), np.uint8)
    m[5:35, 5:35] = 1; m[15:25, 15:25] = 0; m[2, 38] = 1
    c, h = images.find_contours(m, "RETR_TREE", "CHAIN_APPROX_NONE", dtype=np.int32)
    assert all(x.dtype == np.int32 for x in c)
    canvas = np.zeros_like(m)
    cv2.drawContours(canvas, c, -1, 1, -1, hierarchy=h)
    assert abs(int(canvas.sum()) - int(m.sum())) < 0.05 * m.sum()
    c2, h2 = images.find_contours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE, min_area=2.0)
    assert len(c2) == 2 and h2[0, :, 3].tolist() == [-1, 0]
    c3, _ = images.find_contours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE, epsilon=0.1)
    assert len(c3) == 2 and len(c3[1]) <= 12
    c4, _ = images.find_contours(m, cv2.RETR_TREE, offset=(10, 20))
    c5, _ = images.find_contours(m, cv2.RETR_TREE)
    np.testing.assert_allclose(c4[0] - c5[0], np.broadcast_to(np.array([[[10, 20]]], np.float32), c5[0].shape), atol=1e-4)
    with pytest.raises(ValueError):
        images.find_contours(m, cv2.RETR_FLOODFILL)


def test_connectivity_4():
    m = np.zeros((8, 8), np.uint8); m[2, 2] = m[3, 3] = 1
    assert len(images.find_contours(m, "list")[0]) == 1
    assert len(images.find_contours(m, "list", connectivity=4)[0]) == 2


def _dist(pls, truth):
    return metrics.distance_summary([(p, True) for p in pls], [(t, True) for t in truth], 0.05)


@pytest.mark.parametrize("name", [n for n in SHAPES if "square" not in n and "triangle" not in n and "star" not in n])
def test_accuracy_smooth_shapes(name):
    from skimage import measure
    m, _, truth = shape_mask(name)
    gc = images.trace_masks([torch.from_numpy(m)])
    ours = [p.numpy() for p in gc.polylines.polyline_list()]
    sk = [c[:, ::-1] + 0.5 for c in measure.find_contours(m.astype(float), 0.5)]
    cc, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    d, ds, dc = _dist(ours, truth), _dist(sk, truth), _dist([c.reshape(-1, 2) + 0.5 for c in cc], truth)
    assert d["a_to_b_mean"] < min(ds["a_to_b_mean"], dc["a_to_b_mean"])
    assert d["hausdorff"] <= 0.55
    H, W = m.shape
    P = np.concatenate(ours)
    assert P.min() >= 0 and (P[:, 0] <= W).all() and (P[:, 1] <= H).all()


@pytest.mark.parametrize("seed, name, bound", [(-1, "disc r=1.6 (3 px)", 0.52), (2, "square 3 px rot 293", 0.8)])
def test_tiny_loops_smoothed_lightly(seed, name, bound):
    """Loops under about 30 crossings (shapes of 2-4 px) get 2-7 smoothing iterations, not 6-12:
    on a 3-px square the filter rounded the corners inward beyond the crack-midpoint polygon
    (mean 0.200 px against skimage's 0.196, maximum 0.82), on the 3-px disc the maximum was
    0.55 px. Now the mean is below skimage's on both and the maximum below ``bound``."""
    from skimage import measure
    from torch_isc.images.shapes import corner_shapes, shape_mask_of
    m, _, truth = shape_mask(name) if seed < 0 else shape_mask_of(corner_shapes(seed)[name])
    d = _dist([p.numpy() for p in images.trace_masks([torch.from_numpy(m)]).polylines.polyline_list()], truth)
    ds = _dist([c[:, ::-1] + 0.5 for c in measure.find_contours(m.astype(float), 0.5)], truth)
    assert d["a_to_b_mean"] < ds["a_to_b_mean"]
    assert d["hausdorff"] <= bound


@pytest.mark.parametrize("name", [n for n in SHAPES if "square" in n or "triangle" in n or "star" in n])
def test_accuracy_corners_mean(name):
    """Sharp corners: the mean is below both peers'; the maximum stays within a pixel of
    marching squares' (the tips a mask cuts off cannot be recovered within 0.55 px)."""
    from skimage import measure
    m, _, truth = shape_mask(name)
    gc = images.trace_masks([torch.from_numpy(m)])
    ours = [p.numpy() for p in gc.polylines.polyline_list()]
    sk = [c[:, ::-1] + 0.5 for c in measure.find_contours(m.astype(float), 0.5)]
    d, ds = _dist(ours, truth), _dist(sk, truth)
    assert d["a_to_b_mean"] < ds["a_to_b_mean"] + 0.01
    assert d["hausdorff"] <= ds["hausdorff"] + 0.25


@pytest.mark.parametrize("name, bound", [("square 20 deg", 0.50), ("square axis", 0.05), ("triangle", 0.55),
                                         ("star (notches)", 0.55)])
def test_corner_tips_restored(name, bound):
    """Sharp corners are drawn from their extended sides, to a vertex at their tip (the band
    stretched past tips that lie beyond it): the maximum distance is at most marching squares',
    and better than without the corner step. The star's 36-degree tips are only partly restored:
    its mask is the same with the tip cut 1.2-1.9 px short (see test_acute_tip_unrecoverable)."""
    from skimage import measure
    m, _, truth = shape_mask(name)
    d = _dist([p.numpy() for p in images.trace_masks([torch.from_numpy(m)]).polylines.polyline_list()], truth)
    d0 = _dist([p.numpy() for p in images.trace_masks([torch.from_numpy(m)], corners=False).polylines.polyline_list()],
               truth)
    ds = _dist([c[:, ::-1] + 0.5 for c in measure.find_contours(m.astype(float), 0.5)], truth)
    assert d["hausdorff"] <= bound and d["hausdorff"] <= ds["hausdorff"] + 1e-3
    assert d["hausdorff"] <= d0["hausdorff"] + 1e-3 and d["a_to_b_mean"] <= d0["a_to_b_mean"] + 0.002


def test_corner_step_leaves_smooth_shapes_alone():
    for name in [n for n in SHAPES if "square" not in n and "triangle" not in n and "star" not in n]:
        m, _, _ = shape_mask(name)
        a = images.trace_masks([torch.from_numpy(m)]).polylines.points
        b = images.trace_masks([torch.from_numpy(m)], corners=False).polylines.points
        assert torch.equal(a, b), name


def test_tip_vertices_keep_the_curve_a_zero_set():
    """With tip vertices inserted (several masks in one batch, corners in some): the mesh stays
    positively oriented, packed item by item, and its zero set is the returned curve, point for
    point (an independent extraction); the loops keep the cv2 count."""
    from torch_isc.core.extract import extract_zero_set
    names = ["square 20 deg", "disc r=4.3", "triangle", "star (notches)", "square axis"]
    ms = [torch.from_numpy(shape_mask(n)[0]) for n in names]
    gc = images.trace_masks(ms)
    plain = images.trace_masks(ms, corners=False)
    assert gc.mesh.verts.shape[0] > plain.mesh.verts.shape[0]           # tips were inserted
    assert bool((gc.mesh.signed_areas() > 0).all())
    vi = gc.mesh.vert_item
    assert bool((vi[gc.mesh.faces] == gc.mesh.face_item[:, None]).all())
    pl = extract_zero_set(gc.mesh, gc.values)
    assert pl.per_item_counts().tolist() == gc.polylines.per_item_counts().tolist()
    a, b = pl.points.numpy(), gc.polylines.points.numpy()
    assert a.shape == b.shape
    da = np.abs(a[:, None] - b[None]).max(2).min(1)
    assert da.max() < 1e-9
    for m, n in zip(ms, gc.polylines.per_item_counts().tolist()):
        assert n == len(cv2.findContours(m.numpy().astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)[-2])


WEDGES = [("wedge 30 deg rot 353 (seed 1)", 1), ("wedge 45 deg rot 359 (seed 0)", 0),
          ("wedge 90 deg rot 49 (seed 0)", 0), ("star 5 r=30/15 rot 289 (seed 1)", 1),
          # the tip lies in a triangle of the moved vertex outside its grid cell (0.67 px before
          # _insert_tips looked there too)
          ("star 6 r=100/60 rot 308 (seed 1)", 1), ("wedge 30 deg rot 233 (seed 0)", 0),
          ("wedge 60 deg rot 349 (seed 1)", 1)]


@pytest.mark.parametrize("name, seed", WEDGES)
def test_acute_tips_beyond_the_band(name, seed):
    """Acute convex tips whose apex lies beyond the band of pixel centres (truth more than a
    pixel from OpenCV's chain): with the band stretched to them the maximum distance to the
    analytic truth is at most 0.55 px, and no worse than without the stretch; the topology is
    cv2's, the mesh positively oriented, the curve inside the image frame."""
    from torch_isc.images.shapes import corner_shapes, shape_mask_of
    m, _, truth = shape_mask_of(corner_shapes(seed)[name.rsplit(" (seed", 1)[0]])
    gc = images.trace_masks([torch.from_numpy(m)])
    d = _dist([p.numpy() for p in gc.polylines.polyline_list()], truth)
    d0 = _dist([p.numpy() for p in images.trace_masks([torch.from_numpy(m)], stretch_tips=False).polylines.polyline_list()],
               truth)
    assert d["hausdorff"] <= 0.55
    assert d["hausdorff"] <= d0["hausdorff"] + 1e-3
    assert bool((gc.mesh.signed_areas() > 0).all())
    assert len(gc.polylines) == len(cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)[-2])
    P = gc.polylines.points.numpy()
    assert P.min() >= 0 and (P[:, 0] <= m.shape[1]).all() and (P[:, 1] <= m.shape[0]).all()


def test_acute_tip_unrecoverable():
    """The bound is out of reach from the mask alone where a tip is thinner than a pixel: cutting
    the star's tip 1.2 px short of its apex gives the same mask, so any curve drawn from it is
    at least 0.6 px from one of the two truths (skimage: 1.54 px from the full star)."""
    from torch_isc.images.shapes import _polys, _star
    H, W, inside, truth = SHAPES["star (notches)"]
    poly = truth[0]
    k = int(np.argmin(poly[:, 1]))                        # the top tip (54.6, 8.9), 36 degrees
    v, u, w = poly[k], poly[k - 1] - poly[k], poly[(k + 1) % len(poly)] - poly[k]
    u, w = u / np.linalg.norm(u), w / np.linalg.norm(w)
    r = 1.2
    s = r / np.cos(np.arccos(np.clip(u @ w, -1, 1)) / 2)
    cut = np.concatenate([poly[:k], [v + s * u, v + s * w], poly[k + 1:]])
    from torch_isc.images.shapes import shape_mask_of
    m_full = shape_mask_of((H, W, inside, truth))[0]
    m_cut = shape_mask_of((H, W, *_polys([cut])))[0]
    assert (m_full == m_cut).all()
    dd = _dist([cut], [poly])
    assert dd["b_to_a_max"] >= r - 0.05                    # the two truths are 1.2 px apart at the tip


def _random_masks(seed=0):
    """Noise masks (single pixels, diagonal touches, components on the border), a checkerboard,
    thin lines along the border, and blobs of several sizes and densities."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(30):
        H, W = int(rng.integers(1, 30)), int(rng.integers(1, 30))
        out.append((rng.random((H, W)) < rng.uniform(0.05, 0.95)).astype(np.uint8))
    chk = (np.add.outer(np.arange(12), np.arange(15)) % 2 == 0).astype(np.uint8)
    out += [chk, chk & (rng.random(chk.shape) < 0.8)]
    m = np.zeros((9, 11), np.uint8); m[0, :] = 1; m[:, -1] = 1; m[4, 3:7] = 1; out.append(m)
    for s in range(8):
        out.append(binary_blobs(int((16, 40, 64, 100)[s % 4]), blob_size_fraction=float(rng.uniform(0.03, 0.3)),
                                volume_fraction=float(rng.uniform(0.1, 0.9)), rng=s).astype(np.uint8))
    return out


@pytest.mark.parametrize("mode", MODES)
def test_int32_chains_are_cv2s(mode):
    """dtype=np.int32 gives OpenCV's chains point for point (its start pixel: the crack left of
    the first pixel of an outer border, right of it for a hole; a pixel visited twice on a 1-px
    bridge taken at the right visit), with cv2's order and hierarchy."""
    masks = _hard_cases() + _random_masks()
    for m, (oc, oh) in zip(masks, images.find_contours_batch(masks, mode, dtype=np.int32)):
        c, h = cv2.findContours(m, mode, cv2.CHAIN_APPROX_NONE)
        assert len(oc) == len(c)
        assert (oh is None and h is None) or np.array_equal(oh, h)
        for a, b in zip(oc, c):
            assert a.dtype == np.int32 and np.array_equal(a, b)


def test_otsu_images_like_cv2():
    """Real images thresholded by Otsu (skimage's coins and text, and their inverses): the same
    contours, chains and hierarchy as cv2 in RETR_TREE."""
    from skimage import data, filters
    masks = []
    for im in (data.coins(), data.text()):
        m = (im > filters.threshold_otsu(im)).astype(np.uint8)
        masks += [m, 1 - m]
    for m, (oc, oh) in zip(masks, images.find_contours_batch(masks, cv2.RETR_TREE, dtype=np.int32)):
        c, h = cv2.findContours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
        assert len(oc) == len(c) > 10 and np.array_equal(oh, h)
        assert all(np.array_equal(a, b) for a, b in zip(oc, c))


def test_connectivity_4_is_cv2_on_the_inverse():
    """connectivity=4 (4-connected foreground, 8-connected holes) against cv2 on the inverted
    mask inside a 1-px foreground frame, whose 8-connected foreground is our background: one
    cv2 border per border of ours (an outer border starting at pixel p is cv2's hole starting at
    p - 1, a hole starting at p is cv2's outer border starting at p + 1), one level deeper, with
    the same parents (the frame standing for none)."""
    for m in _hard_cases() + _random_masks(1):
        oc, oh = images.find_contours(m, cv2.RETR_TREE, dtype=np.int32, connectivity=4)
        c, h = cv2.findContours(np.pad(1 - m, 1, constant_values=1), cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
        assert len(oc) == len(c) - 1
        if not oc:
            continue

        def depth(hh, q):
            d = 0
            while hh[q, 3] >= 0:
                d, q = d + 1, hh[q, 3]
            return d

        by_start = {tuple(x.reshape(-1, 2)[0] - 1): q for q, x in enumerate(c)}
        ours_d = [depth(oh[0], q) for q in range(len(oc))]
        cv_of = []
        for q, x in enumerate(oc):
            s = x.reshape(-1, 2)[0] + np.array([-1 if ours_d[q] % 2 == 0 else 1, 0])
            k = by_start[tuple(s)]
            assert depth(h[0], k) == ours_d[q] + 1
            cv_of.append(k)
        for q in range(len(oc)):
            assert h[0, cv_of[q], 3] == (0 if oh[0, q, 3] < 0 else cv_of[oh[0, q, 3]])


def test_dropin_input_forms_and_errors():
    """Any 2D bool/integer/float mask, of any strides or memory order, numpy or torch, gives
    cv2's contours (integers: nonzero is foreground, negative values too, as OpenCV); 1xN,
    Nx1, empty and full masks included; bad input raises one-line ValueErrors."""
    rng = np.random.default_rng(3)
    m = (rng.random((30, 40)) < 0.5).astype(np.uint8)
    ref = cv2.findContours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)

    def same(x, r=ref):
        oc, oh = images.find_contours(x, cv2.RETR_TREE, dtype=np.int32)
        assert len(oc) == len(r[0]) and all(np.array_equal(a, b) for a, b in zip(oc, r[0]))
        assert (oh is None and r[1] is None) or np.array_equal(oh, r[1])

    for x in (m.astype(bool), m.astype(np.float32), m * 255.0, m.astype(np.int16) * -7, m.astype(np.uint16) * 300,
              m.astype(np.uint32), m.astype(np.int64), np.asfortranarray(m), torch.from_numpy(m),
              torch.from_numpy(m).bool(), torch.from_numpy(m.astype(np.float64))):
        same(x)
    for x in (m[::-1], m[:, ::-1], m[::2, ::3], m.T, torch.from_numpy(m).T):
        same(x, cv2.findContours(np.ascontiguousarray(np.asarray(x)), cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE))
    for x in (np.zeros((5, 5), np.uint8), np.ones((5, 5), np.uint8), np.ones((1, 1), np.uint8),
              np.array([[1, 0, 1, 1, 0, 1]], np.uint8), np.array([[1, 0, 1, 1, 0, 1]], np.uint8).T.copy()):
        same(x, cv2.findContours(x, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE))
    bad = [(dict(mask=m.astype(np.complex64)), "bool, integer or float array, got dtype complex64"),
           (dict(mask=np.array([["a"]])), "got dtype <U1"), (dict(mask=None), "got dtype object"),
           (dict(mask=np.zeros((3, 4, 5))), "expected a 2D"), (dict(mask=np.zeros((0, 5, 2))), "expected a 2D"),
           (dict(mask=m, dtype=np.float16), "dtype must be"), (dict(mask=m, dtype=np.int64), "dtype must be"),
           (dict(mask=m, offset=(1,)), "offset must be"), (dict(mask=m, min_area=-1), "min_area must be"),
           (dict(mask=m, threshold="x"), "threshold must be"), (dict(mask=m, connectivity=6), "connectivity must be")]
    for kw, msg in bad:
        with pytest.raises(ValueError, match=msg) as e:
            images.find_contours(kw.pop("mask"), cv2.RETR_TREE, **kw)
        assert "\n" not in str(e.value)


@pytest.mark.parametrize("seed, name, k, cut, ext", [(1, "wedge 120 deg rot 330", 1, 2.0, 0.0),
                                                     (0, "wedge 20 deg rot 10", 0, 1.2, 0.3),
                                                     (0, "wedge 120 deg rot 112", 2, 1.9, 0.0),
                                                     # the out-of-reach misses of seeds 2-5
                                                     (2, "square 6 px rot 262", 3, 1.15, 0.1),
                                                     (2, "square 12 px rot 99", 3, 1.1, 0.1),
                                                     (2, "wedge 20 deg rot 125", 0, 1.65, 0.0),
                                                     (2, "wedge 150 deg rot 310", 1, 3.7, 0.05),
                                                     (3, "square 6 px rot 156", 0, 1.0, 0.15),
                                                     (3, "wedge 150 deg rot 260", 1, 3.9, 0.1),
                                                     (3, "wedge 60 deg small rot 173", 2, 1.1, 0.2),
                                                     (4, "square 6 px rot 136", 1, 1.35, 0.1),
                                                     (4, "wedge 20 deg rot 254", 0, 1.7, 0.0),
                                                     (4, "wedge 30 deg rot 48", 0, 1.9, 0.0),
                                                     (4, "wedge 120 deg rot 335", 1, 2.2, 0.0),
                                                     (4, "wedge 60 deg small rot 266", 1, 1.25, 0.0),
                                                     (4, "L 10 px rot 155", 5, 1.15, 0.0),
                                                     (5, "square 3 px rot 186", 0, 1.1, 0.2),
                                                     (5, "square 6 px rot 138", 0, 1.0, 0.3),
                                                     (5, "wedge 90 deg rot 181", 1, 1.2, 0.0),
                                                     (5, "wedge 150 deg rot 54", 1, 2.85, 0.1),
                                                     (5, "wedge 60 deg small rot 31", 1, 1.15, 0.3)])
def test_thin_tips_out_of_reach(seed, name, k, cut, ext):
    """A documented limit: the 0.55 px bound cannot hold on every shape. Corner ``k`` of these
    polygons can be cut ``cut`` px short (chamfered across its bisector) or extended ``ext`` px
    (the vertex moved out along its bisector, its sides pivoting on their other ends) and the
    thresholded mask stays the same; the two shapes are more than 2 x 0.55 px apart at the tip,
    so any curve drawn from that mask is more than 0.55 px from one of them
    (``scripts/evaluate_masks.py --shapes --tips`` lists 6 of the 9 misses of seeds 0, 1 so, and
    18 of the 29 of seeds 2-5: squares of 3-12 px, acute and 15-degree tips, 9-px wedges, a 10-px L)."""
    import math
    from torch_isc.images.shapes import _polys, corner_shapes, shape_mask_of
    H, W, inside, truth = corner_shapes(seed)[name]
    poly = truth[0]
    v, a, b = poly[k], poly[k - 1], poly[(k + 1) % len(poly)]
    u, w = (a - v) / np.linalg.norm(a - v), (b - v) / np.linalg.norm(b - v)
    half = 0.5 * math.acos(float(u @ w))
    s = cut / math.cos(half)
    short = np.concatenate([poly[:k], [v + s * u, v + s * w], poly[k + 1:]])
    long_ = poly.copy()
    long_[k] = v - ext * (u + w) / np.linalg.norm(u + w)
    m = shape_mask_of((H, W, inside, truth))[0]
    assert (shape_mask_of((H, W, *_polys([short])))[0] == m).all()
    assert (shape_mask_of((H, W, *_polys([long_])))[0] == m).all()
    assert metrics.hausdorff([(short, True)], [(long_, True)], 0.02) > 2 * 0.55


@pytest.mark.parametrize("name, seed", [("5-gon r=20 rot 307", 1), ("5-gon r=20 rot 116", 0), ("L 50 px rot 232", 1),
                                        ("5-gon r=20 rot 237", 3), ("square 290 px rot 246", 2)])
def test_obtuse_corners_on_long_chords(name, seed, monkeypatch):
    """Corners of 90-124 degrees that the 3-step chords of the staircase miss are found on
    chords 8 nodes long: the maximum distance to the analytic truth is at most 0.55 px, and
    above it without them."""
    import functools
    import torch_isc.images.grid as G
    from torch_isc.images.shapes import corner_shapes, shape_mask_of
    m, _, truth = shape_mask_of(corner_shapes(seed)[name])
    d = _dist([p.numpy() for p in images.trace_masks([torch.from_numpy(m)]).polylines.polyline_list()], truth)
    monkeypatch.setattr(G, "_corner_tips", functools.partial(G._corner_tips, long_span=0))
    d0 = _dist([p.numpy() for p in images.trace_masks([torch.from_numpy(m)]).polylines.polyline_list()], truth)
    assert d["hausdorff"] <= 0.55 < d0["hausdorff"]


@pytest.mark.parametrize("name, seed, n_corners", [("6-gon r=30 rot 141", 0, 6),
                                                   ("6-gon r=30 rot 302", 1, 6),
                                                   ("star 6 r=100/60 rot 162", 0, 12),
                                                   ("wedge 60 deg small rot 246", 1, 3),
                                                   ("wedge 60 deg small rot 253", 2, 3)])
def test_every_corner_found(name, seed, n_corners):
    """Every corner of these polygons gets a tip within 0.6 px of the analytic vertex, and the
    maximum distance to the truth is at most 0.55 px (0.56-0.91 px before): 120-degree corners
    and 124-degree notches whose mask rounds them (chords through the corner read 45-50 degrees
    of turn; the chords either side of it read 55-62), near-axis sides fitted beyond their
    first run (a window of 24 crossings on a side 2.4 degrees off an axis holds no step, and
    its line came out 2.4 degrees off), and 9-px wedges on loops of fewer than 64 crossings
    (corners are looked for on loops of 24 or more by default: the wedges fail with
    ``_corner_tips(min_loop=64)``, 0.91 and 0.81 px). The topology is cv2's and the mesh
    positively oriented."""
    from torch_isc.images.shapes import corner_shapes, shape_mask_of
    m, _, truth = shape_mask_of(corner_shapes(seed)[name])
    gc = images.trace_masks([torch.from_numpy(m)])
    d = _dist([p.numpy() for p in gc.polylines.polyline_list()], truth)
    assert d["hausdorff"] <= 0.55
    tips = gc.tips.numpy()
    assert len(tips) == n_corners
    near = np.linalg.norm(np.asarray(truth[0])[:, None] - tips[None], axis=2).min(1)
    assert near.max() < 0.6, near
    assert bool((gc.mesh.signed_areas() > 0).all())
    assert len(gc.polylines) == len(cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)[-2])


def test_small_loops_keep_discs_smooth():
    """Corners are looked for on loops of 24 crossings or more (the default ``min_loop=24``),
    below 64 only with both sides straight over 11 crossings: discs of radius 2.3-5 px at
    sub-pixel offsets get no tip (their staircase turns by 60 degrees over a few crossings;
    without the rule the 4.3-px disc got corners; with 7 crossings 17 of 32 such discs got tips,
    max up to 0.92 px)."""
    from torch_isc.images.shapes import _discs, shape_mask_of
    rng = np.random.default_rng(5)
    for r in (2.3, 3.1, 3.8, 4.3, 5.0):
        for _ in range(3):
            c = 8 + rng.uniform(-0.5, 0.5, 2)
            m = shape_mask_of((16, 16, *_discs([(c[0], c[1], r, 1)])))[0]
            gc = images.trace_masks([torch.from_numpy(m)])
            assert gc.tips.shape[0] == 0, (r, c)


def test_separating_lines_middle_of_the_allowed_lines():
    """_separating_lines against a brute-force reference: pixel centres classed by a known line
    (y = 0.043 x + 0.31, a near-axis side: one step every 23 px), searched about a horizontal
    guess: the result separates every centre, its slope is the middle of the slopes of all
    separating lines (found on a grid 100 times finer), and the line passes within the band
    they leave; a guess that already separates the centres is returned as it is."""
    from torch_isc.images.grid import _separating_lines
    xs = np.arange(0, 60) + 0.5
    m_true, c_true = 0.043, 0.31
    ys = np.floor(m_true * xs + c_true - 0.5) + 0.5              # the last centre below the line (y down: foreground)
    fg = np.c_[xs, ys + 1.0]                                       # below the line: y larger
    bg = np.c_[xs, ys]
    assert (fg[:, 1] > m_true * xs + c_true).all() and (bg[:, 1] < m_true * xs + c_true).all()
    # travel direction with background on its right: nrm = (v_y, -v_x) points to smaller y
    v = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    mu = torch.tensor([[30.0, 1.2]], dtype=torch.float64)
    F, Bk = torch.from_numpy(fg)[None], torch.from_numpy(bg)[None]
    valid = torch.ones((1, len(xs)), dtype=torch.bool)
    mu2, v2, margin = _separating_lines(F, Bk, valid, mu, v)
    slope = float(v2[0, 1] / v2[0, 0])
    off = float(mu2[0, 1] - slope * mu2[0, 0])
    assert margin.item() > 0
    assert (fg[:, 1] > slope * xs + off).all() and (bg[:, 1] < slope * xs + off).all()
    bs = np.linspace(-0.1, 0.1, 200001)
    lo = (fg[None, :, 1] - bs[:, None] * xs[None]).min(1)          # the line's offset must lie below every fg
    hi = (bg[None, :, 1] - bs[:, None] * xs[None]).max(1)
    ok = lo > hi
    mid = 0.5 * (bs[ok].min() + bs[ok].max())
    assert abs(slope - mid) < 2e-4 and bs[ok].min() <= m_true <= bs[ok].max()
    k = np.argmin(np.abs(bs - slope))
    assert hi[k] - 1e-3 <= off <= lo[k] + 1e-3
    # a guess inside the allowed lines is kept
    mu3 = torch.tensor([[0.0, c_true]], dtype=torch.float64)
    v3 = torch.tensor([[1.0, m_true]], dtype=torch.float64)
    v3 = v3 / v3.norm()
    mu4, v4, _ = _separating_lines(F, Bk, valid, mu3, v3)
    assert torch.equal(mu4, mu3) and torch.equal(v4, v3)


@pytest.mark.parametrize("deg", [2.5, 3.0, -3.0])
def test_near_axis_sides_fitted_across_their_steps(deg, monkeypatch):
    """A 100-px square a few degrees off the axes: its sides step once every 19-23 px, so the
    least-squares windows (up to 64 crossings, gated by their RMS) hold one run and come out
    flat, and the corners land 0.47-0.63 px from the truth (max 0.46-0.62 px). Refitted to the
    pixel centres over the longest window whose classes a line separates, every corner tip is
    within 0.1 px of the analytic vertex and the maximum distance at most 0.55 px; the topology
    is cv2's."""
    import functools
    import torch_isc.images.grid as G
    from torch_isc.images.shapes import _polys, _rot_square, shape_mask_of
    m, _, truth = shape_mask_of((116, 116, *_polys([_rot_square(58.23, 57.81, 50.0, deg)])))
    gc = images.trace_masks([torch.from_numpy(m)])
    d = _dist([p.numpy() for p in gc.polylines.polyline_list()], truth)
    near = np.linalg.norm(np.asarray(truth[0])[:, None] - gc.tips.numpy()[None], axis=2).min(1)
    assert len(gc.tips) == 4 and near.max() < 0.1, near
    assert d["hausdorff"] <= 0.55
    assert len(gc.polylines) == len(cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)[-2])
    monkeypatch.setattr(G, "_corner_tips", functools.partial(G._corner_tips, separate=0))
    gc0 = images.trace_masks([torch.from_numpy(m)])
    near0 = np.linalg.norm(np.asarray(truth[0])[:, None] - gc0.tips.numpy()[None], axis=2).min(1)
    assert near0.max() > 0.4


def test_batches_pad_within_a_budget(monkeypatch):
    # a batch pads every mask to its largest height and width: a 1 x N mask beside an N x 1 one
    # would cost N x N pixels each; the solves are split so that their padded grids stay bounded
    from torch_isc.images import grid, masks as masks_mod
    from torch_isc.images.grid import padded_groups
    assert padded_groups([(1, 1000), (1000, 1), (1000, 1)], budget=10_000) == [(0, 1), (1, 3)]
    assert padded_groups([(5, 5)] * 4, budget=49 * 4) == [(0, 4)]
    assert padded_groups([(5, 5)] * 4, budget=49 * 4 - 1) == [(0, 3), (3, 4)]
    assert padded_groups([(100, 100)], budget=10) == [(0, 1)]           # a mask alone may exceed it
    seen = []
    real = grid.trace_masks

    def spy(ts, *a, **k):
        seen.append(len(ts) * max(t.shape[0] + 2 for t in ts) * max(t.shape[1] + 2 for t in ts))
        return real(ts, *a, **k)
    monkeypatch.setattr(grid, "trace_masks", spy)
    n = 3000
    h = np.tile(np.array([[1, 1, 0]], np.uint8), (1, n // 3))
    v = h.T.copy()
    small = np.zeros((9, 9), np.uint8)
    small[2:6, 3:7] = 1
    batch = [small, h, v, small]
    got = images.find_contours_batch(batch, "tree", "none", batch_pixels=1 << 16)
    assert max(seen) <= max(1 << 16, (n + 2) * 3)                        # never (n + 2) ** 2
    want = [cv2.findContours(np.pad(m, 1), cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)[0] for m in batch]
    assert [len(c) for c, _ in got] == [len(w) for w in want] == [1, n // 3, n // 3, 1]
    seen.clear()
    res = masks_mod.grid_results(batch)
    assert max(seen) <= max(grid.TRACE_PIXELS, (n + 2) * 3)
    assert [r.boundaries for r in res] == [1, n // 3, n // 3, 1]
