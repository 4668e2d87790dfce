"""Fuzzing round 11, the defects left open in session 21 and fixed in session 22 (each test
fails on the commit before its fix)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from torch_isc import reconstruct, reconstruct_batch
from torch_isc.core.points import check_points
from torch_isc.images import ImageError, contour_arrays, contour_hierarchy, load_contours, to_cv_contours

SQ = np.array([[1.0, 1], [5, 1], [5, 5], [1, 5]])
INNER = SQ[::-1] * 0.5 + 1.5          # inside SQ, the other orientation


def _square_and_hole(scale):
    return [{"closed": True, "points": SQ * scale}, {"closed": True, "points": INNER * scale}]


@pytest.mark.parametrize("scale, dtype, held", [(1e10, np.int32, "int32"), (1e39, np.float32, "float32"),
                                                (1e10, np.int64, "int32"), (1e300, np.float32, "float32")])
def test_to_cv_contours_refuses_coordinates_its_dtype_cannot_hold(scale, dtype, held):
    # float32 turned 1e39 into inf and int32 wrapped 1e10 to INT_MIN, with only numpy's warning
    with pytest.raises(ImageError, match=rf"to_cv_contours: contour coordinates up to 5e\+\d+ are beyond what {held} holds"):
        to_cv_contours(_square_and_hole(scale), dtype=dtype)


@pytest.mark.parametrize("dtype", [np.float32, np.int32])
def test_load_contours_refuses_coordinates_its_dtype_cannot_hold(tmp_path, dtype):
    f = tmp_path / "far.npz"
    np.savez(f, **contour_arrays(_square_and_hole(1e39)))       # a point set's file: float64 points
    with pytest.raises(ImageError, match=r"far\.npz: contour coordinates up to 5e\+39 are beyond what"):
        load_contours(f, dtype=dtype)
    c, _ = load_contours(f, dtype=np.float64)                   # the hint of the message works
    assert c[0].dtype == np.float64 and np.isfinite(c[0]).all()


@pytest.mark.parametrize("scale", [1.0, 1e150, 1e300, 1e-300])
def test_orientation_and_nesting_hold_over_the_float64_range(scale):
    # the shoelace products overflowed to NaN near 1e300 and the outer square came out reversed
    with warnings.catch_warnings():
        warnings.simplefilter("error")                          # no overflow on the way either
        c, h = to_cv_contours(_square_and_hole(scale), dtype=np.float64)
        h2 = contour_hierarchy([SQ * scale, INNER * scale])
    assert h.tolist() == [[[-1, -1, 1, -1], [-1, -1, -1, 0]]] and h2.tolist() == h[0].tolist()
    if scale < 1:
        return                     # OpenCV's half-pixel shift leaves nothing of these coordinates
    # OpenCV's orientation (hand): the outer contour from the top-left corner down its left side
    # (negative shoelace area with y down), the hole the other way
    assert np.allclose((c[0].reshape(-1, 2) + 0.5) / scale, [[1, 1], [1, 5], [5, 5], [5, 1]])
    assert np.allclose((c[1].reshape(-1, 2) + 0.5) / scale, [[2, 2], [4, 2], [4, 4], [2, 4]])


def _ring(n=80):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([np.cos(t), np.sin(t)], 1) * 30 + 5


@pytest.mark.parametrize("np_dtype, torch_dtype, out", [(np.float32, torch.float32, torch.float32),
                                                        (np.float64, torch.float64, torch.float64),
                                                        (np.int32, torch.int32, torch.float32),
                                                        (np.uint16, torch.uint16, torch.float32)])
def test_a_numpy_array_is_solved_as_the_equal_tensor(np_dtype, torch_dtype, out):
    # numpy float32 and integer arrays were solved in float64 (their outputs float64) while the
    # equal tensors gave float32; torch's uint16 was refused and numpy's accepted
    a = np.rint(_ring() + 40).astype(np_dtype)              # positive, for the unsigned type
    t = torch.from_numpy(a.astype(np.int64)).to(torch_dtype)
    r_np, r_t = reconstruct(a), reconstruct(t)
    assert r_np.curve.dtype == r_t.curve.dtype == out
    assert torch.equal(r_np.curve.mesh.verts, r_t.curve.mesh.verts)
    assert torch.equal(r_np.curve.values, r_t.curve.values) and r_np.num_closed == r_t.num_closed == 1


def test_the_top_half_of_uint64_is_taken_as_float64():
    a = _ring().astype(np.uint64) + np.uint64(2 ** 63)                 # beyond int64
    assert check_points(a, "a").dtype == torch.float64
    assert check_points(torch.from_numpy(a), "t").dtype == torch.float64
    assert check_points(a[:3] - np.uint64(2 ** 63), "b").dtype == torch.int64


LATTICE = np.array([[4, 0], [4, 1], [3, 1], [3, 2], [3, 3], [2, 3], [1, 3], [0, 3], [-1, 3], [-2, 2], [-2, 1],
                    [-2, 0], [-2, -1], [-2, -2], [-1, -2], [0, -3], [1, -3], [2, -3], [2, -2], [3, -2], [3, -1]],
                   float)


def test_a_lattice_set_does_not_depend_on_its_place_in_the_batch():
    # exactly equal distances: the nearest neighbours were picked by place in the batch, and the
    # two copies came back 0.35 apart (the noise estimate 0.5438 against 0.5401)
    alone = reconstruct(LATTICE)
    first, second = reconstruct_batch([LATTICE, _ring(), LATTICE])[::2]
    for r in (first, second):
        assert torch.equal(r.curve.mesh.verts, alone.curve.mesh.verts)
        assert torch.equal(r.curve.values, alone.curve.values)
        assert r.stats[-1].noise == alone.stats[-1].noise


def test_window_candidates_are_the_same_points_wherever_the_item_sits():
    from torch_isc.pipeline.noise import morton_orders, window_candidates
    pts = torch.tensor(LATTICE / 8)
    other = torch.rand(13, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    offs = torch.tensor([-3, -2, -1, 1, 2, 3])
    rows = []
    for before in (0, 13):             # the lattice first, then after 13 other points
        x = torch.cat([other[:before], pts, other[before:]])
        item = torch.cat([torch.zeros(before, dtype=torch.long), torch.ones(21, dtype=torch.long),
                          torch.full((13 - before,), 2)]) if before else torch.cat([torch.zeros(21, dtype=torch.long),
                                                                                      torch.ones(13, dtype=torch.long)])
        own = torch.arange(before, before + 21)
        c, _ = window_candidates(morton_orders(x, item), own, offs, item)
        assert (item[c] == item[own][:, None]).all()          # never another item's point
        rows.append(c - before)
    assert torch.equal(rows[0], rows[1])


@pytest.mark.parametrize("window", [2, 5, 12])
def test_window_repeats_leave_each_point_once(window):
    """``window_candidates`` marks repeats instead of sorting rows: each point a row holds, the
    row's own point aside, is left unmarked exactly once (checked row by row against the row's
    distinct points, the old sorted rows' content), on items smaller and larger than the window."""
    from torch_isc.pipeline.noise import morton_orders, window_candidates, window_offsets
    g = torch.Generator().manual_seed(window)
    sizes = [1, 2, 3, window, 2 * window + 1, 40]
    x = torch.rand(sum(sizes), 2, generator=g, dtype=torch.float64) * 2 - 1
    item = torch.cat([torch.full((n,), i, dtype=torch.long) for i, n in enumerate(sizes)])
    idx = torch.arange(x.shape[0])
    c, repeat = window_candidates(morton_orders(x, item), idx, window_offsets(window, x.device), item)
    assert c.shape == repeat.shape == (x.shape[0], 4 * window)
    assert (item[c] == item[:, None]).all()
    marked = 0
    for i, (row, rep) in enumerate(zip(c.tolist(), repeat.tolist())):
        kept = [v for v, r in zip(row, rep) if not r and v != i]
        assert sorted(kept) == sorted(set(row) - {i})
        marked += sum(rep)
    assert marked > 0                                      # small items and both orders repeat


@pytest.mark.parametrize("x", [np.uint8(1), np.array(1), 5])
def test_a_scalar_mask_is_named_as_one(x):
    from torch_isc.images import find_contours
    with pytest.raises(ImageError, match=r"expected a 2D \(H, W\) array, got shape \(\)"):      # said (1,)
        find_contours(x, "tree", "none")


def test_reconstruct_masks_flags_a_count_that_is_not_the_masks():
    # a 4-px checkerboard: cv2 finds 3 borders (8-connected diagonal blocks), the sampled
    # inside/outside function 5 curves; the results said nothing (the CLI's flag, not the API's)
    import cv2
    from torch_isc.images import reconstruct_masks
    checker = np.kron(np.indices((4, 4)).sum(0) % 2, np.ones((4, 4))).astype(np.uint8)
    box = np.zeros((30, 30), np.uint8)
    box[5:20, 6:25] = 1
    want = [len(cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)[0]) for m in (checker, box)]
    r_checker, r_box = reconstruct_masks([checker, box])
    assert (r_checker.boundaries, r_box.boundaries) == tuple(want) == (3, 1)
    assert r_checker.count_ok == (r_checker.num_closed == 3 and r_checker.num_open == 0)
    assert r_box.count_ok and r_box.num_closed == 1
