"""pipeline/denoise.py: points moved onto weighted local parabolas at the noise scale.

Checked against known curves (a circle's radius, two parallel lines), a per-point numpy
reference of the same projection with exact neighbours, and the invariances."""
import math

import numpy as np
import pytest
import torch

from torch_isc.pipeline.config import ReconstructConfig
from torch_isc.pipeline.denoise import MIN_NEIGHBOURS, MIN_WEIGHT, ROUNDS, SPLIT_SPREAD, SPREAD_CLIP, SPREAD_FLOOR, denoise_points
from torch_isc.pipeline.noise import NoiseConfig, noise_and_frames

CFG = NoiseConfig(denoise_iterations=3, denoise_radius=8.0, denoise_band=1.5)


def _circle(n, sig, radius=0.35, seed=0):
    g = torch.Generator().manual_seed(seed)
    th = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    return torch.stack([th.cos(), th.sin()], 1) * radius + torch.randn(n, 2, generator=g, dtype=torch.float64) * sig


def _run(pts, cfg=CFG, noise=None):
    item = torch.zeros(pts.shape[0], dtype=torch.long)
    est = noise_and_frames(pts, item, 1)
    lvl = est.level if noise is None else torch.full((1,), noise, dtype=pts.dtype)
    return denoise_points(pts, item, lvl, est.frames, cfg)


def test_noisy_circle_moves_toward_its_radius_without_shrinking():
    sig, rad = 0.01, 0.35
    pts = _circle(400, sig, rad)
    out = _run(pts)
    r0, r1 = pts.norm(dim=1) - rad, out.norm(dim=1) - rad
    rms0, rms1 = r0.pow(2).mean().sqrt(), r1.pow(2).mean().sqrt()
    assert rms1 < 0.7 * rms0                           # the spread across the curve drops (measured 0.55)
    # the parabola keeps the curvature: a line fit over 6 noise widths would pull inward by
    # about R^2/6rho = 0.17 sigma per pass
    assert abs(r1.mean() - r0.mean()) < 0.05 * sig


def test_two_parallel_lines_six_noise_widths_apart_stay_apart():
    sig, gap, n = 0.01, 6.0, 200
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2 * n, generator=g, dtype=torch.float64) - 0.5
    y = torch.cat([torch.zeros(n), torch.full((n,), gap * sig)]).double() + torch.randn(2 * n, generator=g, dtype=torch.float64) * sig
    pts = torch.stack([x, y], 1)
    out = _run(pts, noise=sig)
    inner = x.abs() < 0.4
    m0 = out[:n][inner[:n], 1].mean() / sig
    m1 = out[n:][inner[n:], 1].mean() / sig
    # each line's points stay near their own line (a merge would put both means at 3)
    assert abs(m0) < 0.6 and abs(m1 - gap) < 0.6, (m0, m1)
    # ... and the gap between them does not fill: no more points within a noise width of the middle
    mid = gap * sig / 2
    assert int(((out[:, 1] - mid).abs() < sig).sum()) <= int(((pts[:, 1] - mid).abs() < sig).sum())


def test_noise_free_points_and_an_outlier_do_not_move():
    pts = _circle(200, 0.0)
    assert torch.equal(_run(pts, noise=0.0), pts)
    sig = 0.005
    pts = _circle(300, sig)
    pts[0] = torch.tensor([0.0, 0.0], dtype=pts.dtype)                # the centre: 70 noise widths off
    out = _run(pts, noise=sig)
    assert torch.equal(out[0], pts[0])
    # every move is within the cap
    assert float((out - pts).norm(dim=1).max()) <= CFG.denoise_max_move * sig * (1 + 1e-9)


def test_disabled_is_the_identity():
    pts = _circle(100, 0.01)
    assert _run(pts, NoiseConfig(denoise_iterations=0)) is pts


def _reference(pts, sigma, cfg):
    """Per point, in numpy: exact k nearest neighbours, the weighted tangent, then the passes of
    reweighted parabola fits (the module's formulas, one point at a time)."""
    x0 = pts.numpy().astype(np.float64)
    P = len(x0)
    k = min(cfg.denoise_neighbours, P - 1)
    d = np.linalg.norm(x0[:, None] - x0[None], axis=2)
    np.fill_diagonal(d, np.inf)
    nbr = np.argsort(d, axis=1, kind="stable")[:, :k]
    R = np.array([max(cfg.denoise_radius * sigma, d[i, nbr[i, MIN_NEIGHBOURS - 1]]) * (1 + 1e-3) for i in range(P)])
    t = np.zeros((P, 2))
    for i in range(P):
        q = x0[nbr[i]] - x0[i]
        w = np.clip(1 - (q ** 2).sum(1) / R[i] ** 2, 0, None) ** 2
        m = (w[:, None] * q).sum(0) / (1 + w.sum())
        qd = q - m
        C = (w[:, None, None] * qd[:, :, None] * qd[:, None, :]).sum(0) + np.outer(m, m)
        ev, V = np.linalg.eigh(C)
        t[i] = V[:, 1]
    x = x0.copy()
    band = np.full(P, cfg.denoise_band * sigma)

    def fit_point(i, x, t, b):
        n = np.array([-t[i, 1], t[i, 0]])
        q = np.vstack([np.zeros(2), x[nbr[i]] - x[i]])
        u, s = q @ t[i] / R[i], q @ n
        wsp = np.clip(1 - u ** 2 - (s / R[i]) ** 2, 0, None) ** 2
        B = np.stack([np.ones_like(u), u, u * u], 1)
        fit = np.zeros_like(s)
        for _ in range(ROUNDS):
            w = wsp * np.exp(-0.5 * ((s - fit) / b) ** 2)
            A = B.T @ (w[:, None] * B) + np.diag([0, 1e-3, 1e-3]) * wsp.sum()
            c = np.linalg.solve(A, B.T @ (w * s))
            fit = B @ c
        r = s - fit
        near = np.abs(r) <= SPREAD_CLIP * b
        var = (wsp[near] * r[near] ** 2).sum() / wsp[near].sum()
        if w.sum() < MIN_WEIGHT:
            return x[i], t[i], 0.0
        mv = np.clip(c[0], -cfg.denoise_max_move * sigma, cfg.denoise_max_move * sigma)
        tt = t[i] + c[1] / R[i] * n
        return x[i] + mv * n, tt / np.linalg.norm(tt), var

    for it in range(cfg.denoise_iterations):
        xn, tn = x.copy(), t.copy()
        var = np.zeros(P)
        for i in range(P):
            xn[i], tn[i], var[i] = fit_point(i, x, t, band[i])
        if it == 0 and cfg.denoise_split_band > 0:
            med = np.sort(var)[(P - 1) // 2]                    # the lower median
            two = var > SPLIT_SPREAD * max(med, SPREAD_FLOOR * sigma ** 2)
            band = np.where(two, cfg.denoise_split_band * sigma, band)
            for i in np.nonzero(two)[0]:
                xn[i], tn[i], _ = fit_point(i, x, t, band[i])
        x, t = xn, tn
    dd = x - x0
    nrm = np.linalg.norm(dd, axis=1)
    cap = cfg.denoise_max_move * sigma
    return x0 + dd * np.minimum(1, cap / np.maximum(nrm, 1e-300))[:, None]


def test_matches_a_per_point_reference_on_a_tiny_set():
    # 13 points: the Morton windows (12 a side) hold every point, so the
    # approximate neighbours are the exact ones
    sig = 0.02
    pts = _circle(13, sig, seed=3)
    out = _run(pts, noise=sig)
    ref = _reference(pts, sig, CFG)
    # the tangent's sign is arbitrary: compare positions only
    assert np.allclose(out.numpy(), ref, atol=1e-9 * 1 + 1e-10)
    assert float((out - pts).norm(dim=1).max()) > 0.2 * sig              # it did move


def test_split_band_matches_the_reference_on_two_close_strands():
    # 13 points along a line (tiny: exact neighbours), the left six alternating between two
    # strands 4 noise widths apart: those see a spread across well above twice the noise's
    # variance and take the narrow band, the right ones (one strand) do not
    sig = 0.02
    g = torch.Generator().manual_seed(7)
    x = torch.linspace(-0.3, 0.3, 13, dtype=torch.float64)
    two = (torch.arange(13) < 6) & (torch.arange(13) % 2 == 1)
    y = torch.where(two, 4.0 * sig, 0.0) + torch.randn(13, generator=g, dtype=torch.float64) * 0.2 * sig
    pts = torch.stack([x, y.double()], 1)
    cfg = NoiseConfig(denoise_iterations=3, denoise_radius=8.0, denoise_band=1.5, denoise_split_band=1.0)
    out = _run(pts, cfg, noise=sig)
    ref = _reference(pts, sig, cfg)
    assert np.allclose(out.numpy(), ref, atol=1e-9)
    assert not np.allclose(ref, _reference(pts, sig, CFG), atol=1e-6)       # the split changed something


def test_split_band_keeps_two_strands_three_noise_widths_apart():
    """Two noisy lines 3 noise widths apart: the default band (1.5) pulls them together (their
    means move toward the middle); with denoise_split_band 1.0 their points see twice the
    median spread and each keeps nearer to its own line."""
    sig, gap, n = 0.01, 3.0, 300
    g = torch.Generator().manual_seed(2)
    x = torch.rand(5 * n, generator=g, dtype=torch.float64) - 0.5
    # a single noisy line far away, with most of the points, sets the item's median spread (one wall)
    y = torch.cat([torch.zeros(n), torch.full((n,), gap * sig), torch.full((3 * n,), 0.3)]).double()
    y = y + torch.randn(5 * n, generator=g, dtype=torch.float64) * sig
    pts = torch.stack([x, y], 1)
    inner = (x.abs() < 0.4)[:2 * n]

    def sep(cfg):
        out = _run(pts, cfg, noise=sig)
        return float(out[n:2 * n][inner[n:], 1].mean() - out[:n][inner[:n], 1].mean()) / sig

    wide = sep(CFG)
    split = sep(NoiseConfig(denoise_iterations=3, denoise_radius=8.0, denoise_band=1.5, denoise_split_band=1.0))
    assert split > wide + 0.3, (wide, split)


def test_translation_scale_batch_and_dtype():
    sig = 0.01
    a = _circle(150, sig, seed=4)
    b = _circle(90, 0.02, radius=0.2, seed=5)
    item = torch.cat([torch.zeros(150), torch.ones(90)]).long()
    both = torch.cat([a, b])
    est = noise_and_frames(both, item, 2)
    out = denoise_points(both, item, est.level, est.frames, CFG)
    alone = denoise_points(a, item[:150], est.level[:1], est.frames[:150], CFG)
    assert torch.allclose(out[:150], alone, atol=1e-12)                  # independent of the batch
    f = denoise_points(a.float(), item[:150], est.level[:1].float(), est.frames[:150].float(), CFG)
    assert f.dtype == torch.float32 and torch.allclose(f.double(), alone, atol=1e-4)


def test_reconstruction_with_denoising_is_invariant_to_translation_and_scale():
    from torch_isc.pipeline.loop import reconstruct
    cfg = ReconstructConfig().replace(denoise_iterations=2, max_level=4)
    pts = _circle(200, 0.01, seed=6)
    s, t = 37.0, torch.tensor([500.0, -20.0], dtype=torch.float64)
    r0 = reconstruct(pts, cfg)
    r1 = reconstruct(pts * s + t, cfg)
    assert r0.num_closed == r1.num_closed == 1
    c0 = r0.polylines[0]["points"].double()
    c1 = (r1.polylines[0]["points"].double() - t) / s
    assert c0.shape == c1.shape and torch.allclose(c0, c1, atol=1e-4)


def test_config_keys_reach_the_noise_section():
    cfg = ReconstructConfig().replace(denoise_iterations=2, denoise_radius=5.0)
    assert cfg.noise.denoise_iterations == 2 and cfg.noise.denoise_radius == 5.0
    with pytest.raises(ValueError):
        ReconstructConfig().replace(denoise_iterations=-1)


def test_the_loop_assumes_the_scaled_noise_after_denoising():
    from torch_isc.pipeline.loop import reconstruct
    pts = _circle(200, 0.01, seed=7)
    base = ReconstructConfig().replace(max_level=2)
    n_raw = reconstruct(pts, base).stats[0].noise
    n_on = reconstruct(pts, base.replace(denoise_iterations=1)).stats[0].noise
    n_half = reconstruct(pts, base.replace(denoise_iterations=1, denoise_noise_scale=0.5)).stats[0].noise
    assert n_on == pytest.approx(n_raw, rel=1e-6)          # the estimate is of the raw points
    assert n_half == pytest.approx(0.5 * n_raw, rel=1e-6)


def test_block_size_does_not_change_the_results(monkeypatch):
    """The neighbour searches, the noise estimate and the denoising run in blocks of points
    (``noise.knn_budget``: small on the CPU, a share of memory on an accelerator): blocks of a
    few points and one block for all give the same bits as the CPU's default."""
    from torch_isc.pipeline import noise as nz
    g = torch.Generator().manual_seed(7)
    pts = torch.cat([_circle(400, 0.01, seed=8), _circle(300, 0.02, radius=0.2, seed=9) + 0.1])
    item = torch.cat([torch.zeros(400), torch.ones(300)]).long()
    pts = pts + 1e-3 * torch.randn(pts.shape, generator=g, dtype=torch.float64)
    cfg = NoiseConfig()

    def run():
        est = noise_and_frames(pts, item, 2, cfg)
        out = denoise_points(pts, item, est.level, est.frames, cfg, return_tangents=True)
        return est.level, est.frames, *out

    want = run()
    for budget in (1 << 11, 1 << 26):
        monkeypatch.setitem(nz._KNN_BUDGETS, "cpu", budget)
        # 11: many blocks (the denoising's holds 10 points); 26: one block each
        for a, b in zip(run(), want):
            assert torch.equal(a, b)
    assert (want[2] - pts).norm(dim=1).max() > 0                       # the denoising moved points


def test_squared_distances_are_the_naive_sums_bit_for_bit():
    """noise.squared_distances (by coordinate columns) against Python's own arithmetic per pair,
    and against the (R, C, 2) expression it replaces in float32; ``take`` is plain indexing."""
    from torch_isc.pipeline.noise import squared_distances, take
    g = torch.Generator().manual_seed(7)
    p = torch.randn(500, 2, dtype=torch.float64, generator=g) * 3.0
    p[:100] = (p[:100] * 4).round() / 4                       # a grid: many equal distances
    idx = torch.arange(40, 70)
    c = torch.randint(0, 500, (30, 17), generator=g)
    got = squared_distances(p, idx, c)
    P = p.tolist()
    for r in range(30):
        xi, yi = P[40 + r]
        for j in range(17):
            xc, yc = P[c[r, j]]
            dx, dy = xc - xi, yc - yi
            assert got[r, j].item() == dx * dx + dy * dy
    p32 = p.float()
    assert torch.equal(squared_distances(p32, idx, c), ((p32[c] - p32[idx][:, None, :]) ** 2).sum(-1))
    assert torch.equal(take(p, c), p[c]) and torch.equal(take(c, idx - 40), c[idx - 40])
