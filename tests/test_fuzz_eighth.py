"""Fuzzing, eighth round (issue 12/18, the session-18 report on the OpenCV drop-in): one fast
regression test per failure found.

=====================================================  ==========================================
case (what happened before)                            tests
=====================================================  ==========================================
float contours and mask curves outside the image frame  test_float_contours_stay_in_the_frame,
on 86% of random masks (a 2x2 white mask: -0.553 in     test_mask_curves_stay_in_the_frame
cv2's coordinates; up to 0.48 px)
a ``(1, W, 1)`` array read as a ``W x 1`` column; an    test_one_channel_arrays_read_as_cv2
``(H, W, 1)`` array refused (cv2 reads both)
``find_contours`` of a ``(0, W)`` mask: an error where  test_empty_mask_has_no_contour
cv2 returns no contour
=====================================================  ==========================================
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

cv2 = pytest.importorskip("cv2")

from torch_isc.images import find_contours, grid_results  # noqa: E402

#: the report's worst case: 0.43 px outside at (10.93, 1.93) with W = 11
WORST = np.array([[0, 1, 0, 0, 0, 0, 0, 0, 1, 1, 0], [1, 0, 1, 1, 0, 0, 0, 0, 0, 0, 1],
                  [1, 0, 0, 0, 1, 0, 0, 0, 0, 1, 1], [1, 0, 0, 0, 1, 1, 1, 1, 1, 0, 0]], np.uint8)


def _masks():
    rng = np.random.default_rng(5)
    out = [np.ones((2, 2), np.uint8), np.ones((1, 1), np.uint8), WORST]
    for _ in range(60):
        h, w = rng.integers(1, 24, 2)
        out.append((rng.random((h, w)) < rng.uniform(0.2, 0.9)).astype(np.uint8))
    return out


def test_float_contours_stay_in_the_frame():
    """Every float32 point within OpenCV's frame ``[-0.5, W-0.5] x [-0.5, H-0.5]``, the same
    contours as cv2 (count and hierarchy), each point within a pixel of cv2's chain (it is the
    crossing between a pixel centre of each class)."""
    for m in _masks():
        H, W = m.shape
        c, h = find_contours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
        c2, h2 = cv2.findContours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
        assert len(c) == len(c2) and np.array_equal(h, h2)
        for x in c:
            x = x.reshape(-1, 2).astype(np.float64)
            assert x.min() >= -0.5 and x[:, 0].max() <= W - 0.5 and x[:, 1].max() <= H - 0.5, (m.shape, x.min(0), x.max(0))
    c, _ = find_contours(np.ones((2, 2), np.uint8), cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
    x = c[0].reshape(-1, 2)
    # a white image's border is the frame: its corners are reached, not passed
    assert np.allclose(x.min(0), [-0.5, -0.5]) and np.allclose(x.max(0), [1.5, 1.5])


def test_mask_curves_stay_in_the_frame():
    """The curves of ``grid_results`` (pixel ``(i, j)`` covers ``[j, j+1] x [i, i+1]``) within
    ``[0, W] x [0, H]``, and still on the zero set of their mesh function at the border."""
    masks = _masks()[:20]
    for m, r in zip(masks, grid_results([torch.as_tensor(m.astype(bool)) for m in masks])):
        H, W = m.shape
        for pl in r.polylines:
            p = pl["points"].double()
            assert float(p.min()) >= 0 and float(p[:, 0].max()) <= W and float(p[:, 1].max()) <= H
        if r.curve is not None and len(r.polylines):
            f = r.curve(torch.cat([pl["points"] for pl in r.polylines]).to(r.curve.values.dtype))
            assert float(f.abs().max()) < 1e-3 * float(r.curve.values.abs().max())


def test_one_channel_arrays_read_as_cv2():
    """``(H, W, 1)`` arrays as cv2 reads them; a ``(1, W, 1)`` array is a row (cv2), not a
    column; a ``(1, H, W)`` tensor keeps torch's channel-first reading."""
    x = np.array([[0, 1, 1, 0, 1, 0, 0]], np.uint8)[:, :, None]
    for m in (x, (np.random.default_rng(1).random((9, 7)) < 0.5).astype(np.uint8)[:, :, None]):
        a, ha = find_contours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE, dtype=np.int32)
        b, hb = cv2.findContours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE)
        assert len(a) == len(b) and all(np.array_equal(p, q) for p, q in zip(a, b)) and np.array_equal(ha, hb)
    col, _ = find_contours(torch.as_tensor(x[:, :, 0])[None], cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE, dtype=np.int32)
    row, _ = cv2.findContours(x[:, :, 0], cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    assert len(col) == len(row) and all(np.array_equal(p, q) for p, q in zip(col, row))


def test_empty_mask_has_no_contour():
    """``(0, 5)``, ``(5, 0)`` and ``(0, 5, 1)``: no contour and no hierarchy, as cv2; a bad
    argument is still refused."""
    from torch_isc.images import ImageError
    for shape in ((0, 5), (5, 0), (0, 5, 1)):
        m = np.zeros(shape, np.uint8)
        assert find_contours(m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE) == cv2.findContours(
            m, cv2.RETR_TREE, cv2.CHAIN_APPROX_NONE) == ((), None)
    with pytest.raises(ImageError):
        find_contours(np.zeros((0, 5), np.uint8), 99, cv2.CHAIN_APPROX_NONE)
