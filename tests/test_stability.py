"""Issue 18, point 4 (stability): a perturbation far below the tolerance should move the result
by about as much. Perturbations: the 17-digit text round trip of ``x * 1e-6 + 1e7`` mapped back
(rounding of up to about 0.03% of the diagonal) and a repeat merged away (the same point set).

The noise estimate (the tolerance's floor) is tested here: it has no cliff left. The curve itself
is not yet within the issue's bound (``scripts/evaluate_stability.py --diagnose`` measures it and
names the first decision that differs; the xfail below holds the case).
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_isc import ReconstructConfig, reconstruct
from torch_isc.core.points import prepare_points
from torch_isc.metrics import bbox_diagonal, hausdorff
from torch_isc.pipeline.noise import NoiseConfig, noise_and_frames
from torch_isc.pipeline.noise import _noise_at_scale


def noisy_circle(n=400, noise=0.01, seed=0):
    """``n`` points uniform in angle on the unit circle, Gaussian noise of ``noise`` diagonals."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.cos(t), np.sin(t)], 1) + noise * 2 * np.sqrt(2) * rng.standard_normal((n, 2))


def noisy_flower(n=400, noise=0.01, seed=0):
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 2 * np.pi, n)
    r = 1 + 0.3 * np.cos(5 * t)
    return np.stack([r * np.cos(t), r * np.sin(t)], 1) + noise * 2.6 * np.sqrt(2) * rng.standard_normal((n, 2))


def round_trip(p):
    """What a file of ``p * 1e-6 + 1e7`` written with 17 digits gives back, mapped to ``p``'s frame."""
    q = np.array([float("%.17g" % v) for v in (p * 1e-6 + 1e7).ravel()]).reshape(p.shape)
    return (q - 1e7) / 1e-6


def noise_of(p, cfg=None):
    b = prepare_points([torch.as_tensor(p)])
    return float(noise_and_frames(b.points, b.point_item, 1, cfg, b.source).level[0])


@pytest.mark.parametrize("make,seed", [(noisy_circle, 0), (noisy_circle, 1), (noisy_flower, 1)])
def test_noise_estimate_moves_little_under_round_trip(make, seed):
    """The round trip moves points by ~1% of the noise and merges a few of them (exact
    repeats after rounding). The estimate moved by 10% (circle seed 0), 4% (seed 1) and 47%
    (flower seed 1) before: the subsets were redrawn when a merge shifted the indices, and the
    aspect tests switched scales. Now the kNN neighbourhoods alone move it (2% at most)."""
    p = make(noise=0.01, seed=seed)
    q = round_trip(p)
    assert prepare_points([torch.as_tensor(q)]).counts[0] < 400        # the case merges repeats
    a, b = noise_of(p), noise_of(q)
    assert abs(b / a - 1) < 0.03


@pytest.mark.parametrize("make,seed", [(noisy_circle, 3), (noisy_flower, 2), (noisy_flower, 3)])
def test_noise_estimate_moves_little_when_a_point_merges(make, seed):
    """What a rounding merge does: one point becomes a repeat of its neighbour (and is dropped).
    The others keep their subset draw (keyed by their index in the caller's set) and the scale
    blend moves with the subsets' aspect: the estimate moves by a few % (it moved by 10%, 37%
    and 0.2% before: all later points were redrawn and the aspect switched scales)."""
    p = make(noise=0.01, seed=seed)
    b = prepare_points([torch.as_tensor(p)])
    cfg = NoiseConfig()
    _, asp, _, _ = _noise_at_scale(b.points, b.point_item, 1, cfg.noise_neighbours, cfg.noise_window)
    assert float(asp[0]) < cfg.noise_blob_aspect                         # the subset path is taken
    q = p.copy()
    q[7] = q[6]
    assert abs(noise_of(q) / noise_of(p) - 1) < 0.1
    # a repeat that adds a row changes nothing at all (it is merged, the keys stay)
    assert noise_of(np.concatenate([p, p[5:6]])) == noise_of(p)
    res = [reconstruct(x, ReconstructConfig()) for x in (p, np.concatenate([p, p[7:9]]))]
    assert res[0].stats[0].noise == res[1].stats[0].noise


def test_noise_estimate_is_continuous_in_the_aspect_threshold():
    """Sweeping ``noise_blob_aspect`` across the item's median aspect: far below it the estimate
    is the full-density one, far above it the subsets' one (each computed by its own route), and
    in between it passes from one to the other in small steps (it jumped by the whole gap)."""
    p = noisy_circle(noise=0.01, seed=2)
    b = prepare_points([torch.as_tensor(p)])
    k, w = NoiseConfig().noise_neighbours, NoiseConfig().noise_window
    v0, a0, _, _ = _noise_at_scale(b.points, b.point_item, 1, k, w)
    a0 = float(a0[0])
    full = float(v0[0]) ** 0.5
    # the subsets' estimate: with the line test passed at once, the first subset decides
    sub = noise_of(p, NoiseConfig(noise_blob_aspect=a0 * 1.5, noise_line_aspect=1e-3))
    assert abs(sub / full - 1) > 0.1                                      # a real gap to cross
    ests = [noise_of(p, NoiseConfig(noise_blob_aspect=a0 * f, noise_line_aspect=1e-3))
            for f in np.exp(np.linspace(-np.log(1.3), np.log(1.3), 41))]
    assert ests[0] == pytest.approx(full, rel=1e-6)
    assert ests[-1] == pytest.approx(sub, rel=1e-6)
    steps = np.abs(np.diff(ests))
    assert steps.max() < 0.15 * abs(sub - full)


@pytest.mark.xfail(strict=True, reason="issue 18 point 4 is open: the round trip moves points by 4.5% of the "
                   "tolerance and a level-0 max statistic sits within that of its threshold (seed 1: "
                   "1.025 -> 0.978 of the allowance), and the relaxation amplifies the perturbation 14-415x "
                   "(its step-length ladder, quality-floor stop and energy test are discrete), which moves "
                   "points across edges and flips later marks (seed 2); measured 0.04-0.5% of the diagonal "
                   "(scripts/evaluate_stability.py --diagnose)")
def test_round_trip_moves_the_curve_within_0_1_percent():
    """The issue's case: 400 noisy points on a circle, as they are and after the round trip."""
    worst = 0.0
    for seed in range(3):
        p = noisy_circle(noise=0.0025, seed=seed)
        a, b = reconstruct(p), reconstruct(round_trip(p))
        ca = [(x["points"].double(), x["closed"]) for x in a.polylines]
        cb = [(x["points"].double(), x["closed"]) for x in b.polylines]
        worst = max(worst, hausdorff(ca, cb) / bbox_diagonal(torch.as_tensor(p)))
    assert worst < 1e-3



@pytest.mark.slow
def test_round_trip_with_the_snap_moves_the_curve_within_0_1_percent():
    """The issue's case with ``band_snap`` (crossings on the data's moving-least-squares curve)
    on a band of ``band_levels`` 3: the curve follows the data, not the mesh, and the round trip
    moves it by 5.9e-4, 6.7e-4 and 8.7e-4 of the diagonal (seeds 0-2; by default 4.1e-4, 5.2e-3
    and 1.3e-3, the xfail above) although the refinement still differs for seeds 1 and 2."""
    cfg = ReconstructConfig().replace(band_levels=3, band_snap=True)
    worst = 0.0
    for seed in range(3):
        p = noisy_circle(noise=0.0025, seed=seed)
        a, b = reconstruct(p, cfg), reconstruct(round_trip(p), cfg)
        ca = [(x["points"].double(), x["closed"]) for x in a.polylines]
        cb = [(x["points"].double(), x["closed"]) for x in b.polylines]
        worst = max(worst, hausdorff(ca, cb) / bbox_diagonal(torch.as_tensor(p)))
    assert worst < 1e-3

def test_first_divergence_names_an_amplifying_relaxation(monkeypatch):
    """``evaluate_stability --diagnose``: the same input twice agrees everywhere ("none", no
    vertex moved); a relaxation that moves the mesh by 1e4 times the input's change (a stand-in
    for the real one's steep response) is named ``relax@1``, before any decision differs."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    import evaluate_stability as st
    import torch_isc.pipeline.loop as loop

    cfg = ReconstructConfig().replace(max_level=1)
    p = noisy_circle(n=120, noise=0.0025, seed=0)
    assert st.first_divergence(p, p.copy(), cfg).startswith("none noise+0.0e+00 move0x")
    real, ref = loop.relax_stage, []

    def steep(ws, rcfg):
        ws = real(ws, rcfg)
        if not ref:
            ref.append(ws.points.clone())
        d = float((ws.points - ref[0]).abs().max()) * 1e4       # 0 in the first run
        inner = ~ws.mesh.is_boundary_vert[:, None]
        return ws.replace(mesh=ws.mesh.with_verts(ws.mesh.verts + inner * torch.tensor([d, 0.0], dtype=ws.dtype)))
    monkeypatch.setattr(loop, "relax_stage", steep)
    q = p.copy()
    q[5, 0] += 1e-6 * bbox_diagonal(torch.as_tensor(p))
    out = st.first_divergence(p, q, cfg)
    assert out.startswith("relax@1"), out
    assert 5e3 < float(out.split("move")[1].rstrip("x")) < 2e4            # the move in units of the change
