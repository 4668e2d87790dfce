"""Hand-computed checks of torch_isc.metrics (distances and the cases' topology rule)."""
import math

import numpy as np
import pytest
import torch

from torch_isc import metrics as M


def circle(r, n=2000, cx=0.0, cy=0.0):
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    return torch.stack([cx + r * torch.cos(t), cy + r * torch.sin(t)], 1)


def square(x0=0.0, y0=0.0, s=1.0):
    return torch.tensor([[x0, y0], [x0 + s, y0], [x0 + s, y0 + s], [x0, y0 + s]], dtype=torch.float64)


# ------------------------------------------------------------------ resampling

def test_resample_closed_square_uniform():
    pts = M.resample_polyline(square(), True, 0.1)
    assert isinstance(pts, torch.Tensor) and pts.shape == (40, 2)
    step = torch.linalg.vector_norm(torch.roll(pts, -1, 0) - pts, dim=1)
    assert torch.allclose(step, torch.full_like(step, 0.1), atol=1e-12)
    # every sample lies on the square's boundary
    on_edge = ((pts[:, 0].abs() < 1e-12) | ((pts[:, 0] - 1).abs() < 1e-12)
               | (pts[:, 1].abs() < 1e-12) | ((pts[:, 1] - 1).abs() < 1e-12))
    assert bool(on_edge.all())


def test_resample_open_keeps_ends_and_numpy_in_numpy_out():
    line = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.5]])
    pts = M.resample_polyline(line, False, 0.2)
    assert isinstance(pts, np.ndarray)
    assert pts.shape == (int(math.ceil(1.5 / 0.2)) + 1, 2)
    np.testing.assert_allclose(pts[0], [0, 0])
    np.testing.assert_allclose(pts[-1], [1, 0.5])
    assert np.linalg.norm(np.diff(pts, axis=0), axis=1).max() <= 0.2 + 1e-12


def test_resample_degenerate():
    one = M.resample_polyline(torch.tensor([[1.0, 2.0]]), True, 0.1)
    assert one.shape == (1, 2)
    with pytest.raises(ValueError):
        M.resample_polyline(square(), True, 0.0)


# ------------------------------------------------------------------ distances

def test_concentric_circles():
    a = [(circle(1.0), True)]
    b = [(circle(1.1), True)]
    d = M.distance_summary(a, b, 1e-3)
    assert d["hausdorff"] == pytest.approx(0.1, abs=1e-4)
    assert d["chamfer"] == pytest.approx(0.1, abs=1e-4)
    assert d["a_to_b_mean"] == pytest.approx(0.1, abs=1e-4) and d["b_to_a_max"] == pytest.approx(0.1, abs=1e-4)
    assert M.hausdorff(b, a, 1e-2) == pytest.approx(0.1, abs=1e-4)


def test_square_shifted():
    a = [(square(), True)]
    b = [(square(0.05, 0.0), True)]
    assert M.hausdorff(a, b, 1e-3) == pytest.approx(0.05, abs=1e-6)
    # chamfer by hand, A -> B along A's perimeter 4: left edge at 0.05 (integral 0.05); right
    # edge at min(0.05, y, 1 - y) (integral 0.05 - 0.05**2); bottom and top edges: 0 except the
    # 0.05 overhang where d = 0.05 - x (integral 0.05**2 / 2 each) -> total 0.1, mean 0.025;
    # B -> A is the mirror image.
    assert M.chamfer(a, b, 1e-4) == pytest.approx(0.025, abs=1e-6)
    assert M.hausdorff(a, a, 1e-3) == 0.0


def test_distance_sets_and_dict_form():
    two = [{"closed": True, "points": circle(1.0)}, {"closed": True, "points": circle(1.0, cx=5.0)}]
    one = [(circle(1.0), True)]
    d = M.distance_summary(one, two, 1e-3)
    assert d["a_to_b_max"] == pytest.approx(0.0, abs=1e-5)
    assert d["b_to_a_max"] == pytest.approx(5.0, abs=1e-3)  # (6, 0) on the second circle
    assert d["hausdorff"] == pytest.approx(5.0, abs=1e-3)
    assert math.isinf(M.hausdorff([], one))
    assert M.hausdorff([], []) == 0.0


def test_point_distances_exact():
    pl = [(square(), True)]
    q = torch.tensor([[0.5, 0.5], [2.0, 0.5], [2.0, 2.0], [0.5, 0.0]], dtype=torch.float64)
    d = M.point_distances(q, pl)
    assert torch.allclose(d, torch.tensor([0.5, 1.0, math.sqrt(2), 0.0], dtype=torch.float64), atol=1e-12)


def test_chunking_matches_unchunked(monkeypatch):
    a = [(circle(1.0, 300), True)]
    b = [(circle(1.2, 300, cx=0.1), True), (torch.tensor([[3.0, 0.0], [4.0, 1.0]], dtype=torch.float64), False)]
    ref = M.distance_summary(a, b, 0.01)
    monkeypatch.setattr(M, "_CHUNK_ELEMS", 1000)
    monkeypatch.setattr(M, "_BLOCK", 7)
    assert M.distance_summary(a, b, 0.01) == pytest.approx(ref, abs=1e-12)


# ------------------------------------------------------------------ topology

TRUTH = [(circle(1.0, 500), True), (circle(1.0, 500, cx=4.0), True)]
DIAG = M.bbox_diagonal(TRUTH)  # sqrt(6^2 + 2^2)


def test_topology_right():
    rec = [(circle(1.02, 80, cx=4.0), True), (circle(0.98, 80), True)]  # order swapped is fine
    r = M.match_topology(rec, TRUTH, DIAG)
    assert r["ok"] and r["n_closed"] == 2 and r["n_open"] == 0 and r["n_truth"] == 2
    assert r["matches"] == [1, 0]
    assert r["matched_distances"][0] == pytest.approx(0.02 / DIAG, abs=2e-4)


def test_topology_wrong_count():
    r = M.match_topology([(circle(1.0, 80), True)], TRUTH, DIAG)
    assert not r["ok"] and r["n_closed"] == 1 and r["matches"][0] == 0 and r["matches"][1] is None
    rec3 = [(circle(1.0, 80), True), (circle(1.0, 80, cx=4.0), True), (circle(0.2, 40, cx=2.0), True)]
    assert not M.match_topology(rec3, TRUTH, DIAG)["ok"]


def test_topology_open_chain():
    arc = circle(1.0, 80)[:70]
    rec = [(arc, False), (circle(1.0, 80, cx=4.0), True)]
    r = M.match_topology(rec, TRUTH, DIAG)
    assert not r["ok"] and r["n_open"] == 1
    # right curves but an extra open chain is still wrong
    rec = [(circle(1.0, 80), True), (circle(1.0, 80, cx=4.0), True), (arc, False)]
    r = M.match_topology(rec, TRUTH, DIAG)
    assert not r["ok"] and r["matches"] == [0, 1]


def test_topology_far_curve():
    # one curve matches, the other is 0.7 away (> 10% of the diagonal 6.32)
    rec = [(circle(1.0, 80), True), (circle(1.0, 80, cx=4.0, cy=0.7), True)]
    r = M.match_topology(rec, TRUTH, DIAG)
    assert not r["ok"] and r["matches"] == [0, None]
    assert r["distances"][1] == pytest.approx(0.7 / DIAG, abs=1e-3)
    # the same offset passes with a looser threshold
    assert M.match_topology(rec, TRUTH, DIAG, max_dist=0.2)["ok"]


def test_topology_not_mutually_nearest():
    # both reconstructed curves sit on the first truth circle: truth 1 has no mutual partner
    rec = [(circle(1.0, 80), True), (circle(1.05, 80, cx=0.3), True)]
    r = M.match_topology(rec, TRUTH, DIAG, max_dist=10.0)
    assert not r["ok"] and r["matches"][1] is None


def test_score_case():
    truth = {"name": "x", "n_components": 2, "noise": 0.0,
             "curves": [circle(1.0, 500).tolist(), circle(1.0, 500, cx=4.0).tolist()]}
    rec = [{"closed": True, "points": circle(1.06, 200)}, {"closed": True, "points": circle(1.0, 200, cx=4.0)}]
    s = M.score_case(rec, truth)
    assert s["topology_ok"] and s["n_closed"] == 2 and s["n_open"] == 0
    assert s["hausdorff"] == pytest.approx(0.06 / DIAG, abs=1e-3 / DIAG)
    assert 0 < s["chamfer"] < s["hausdorff"]
    empty = M.score_case([], truth)
    assert not empty["topology_ok"] and math.isinf(empty["hausdorff"])


def test_point_segment_against_direct_formula():
    g = torch.Generator().manual_seed(0)
    q = torch.rand(200, 2, generator=g, dtype=torch.float64) * 10 + 100  # away from the origin
    a = torch.rand(50, 2, generator=g, dtype=torch.float64) * 10 + 100
    b = a + torch.randn(50, 2, generator=g, dtype=torch.float64)
    b[3] = a[3]  # a degenerate segment
    d = b - a
    t = (((q[:, None] - a[None]) * d[None]).sum(-1) / (d * d).sum(1).clamp_min(1e-300)).clamp(0, 1)
    ref = torch.linalg.vector_norm(q[:, None] - a[None] - t[..., None] * d[None], dim=-1)
    got = M._point_segment_min(q, a, b, [0, 20, 20, 50])  # an empty middle group
    assert torch.allclose(got[:, 0], ref[:, :20].min(1).values, atol=1e-12)
    assert bool(torch.isinf(got[:, 1]).all())
    assert torch.allclose(got[:, 2], ref[:, 20:].min(1).values, atol=1e-12)
    assert torch.allclose(M._point_segment_min(q, a, b), ref.min(1).values, atol=1e-12)
