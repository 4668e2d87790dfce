"""Generate ``nested.xy``, the built-in example of ``torch-isc reconstruct --example``.

A multiply connected point set in the spirit of Fig. 4 of Taubin & Ronfard (1996): an outer
rounded rectangle (a superellipse) containing two holes, a circle and an ellipse; the circular
hole contains a circular island. Four closed curves, nesting depth 3 (outer > hole > island).

Points are spaced uniformly in arc length along every curve (same spacing on all curves, a random
phase per curve), perturbed by tiny isotropic Gaussian noise, and shuffled so the set is
unorganized. The curves are at least ~8 sample spacings apart. Fixed seed: running this script
reproduces the shipped file byte for byte.

Usage: ``python make_example.py [OUTPUT]`` (default: ``nested.xy`` next to this script).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

SEED = 1996
NUM_POINTS = 600          # about; the spacing is total length / NUM_POINTS
NOISE = 0.1               # noise standard deviation, as a fraction of the sample spacing


def _superellipse(t: np.ndarray, a: float, b: float, n: float) -> np.ndarray:
    """``|x/a|^n + |y/b|^n = 1`` at angles ``t (K,)`` -> ``(K, 2)``."""
    c, s = np.cos(t), np.sin(t)
    return np.stack([a * np.sign(c) * np.abs(c) ** (2 / n), b * np.sign(s) * np.abs(s) ** (2 / n)], 1)


def curves() -> list:
    """The four true curves as dense closed polylines ``(K, 2)`` (first vertex not repeated)."""
    t = np.linspace(0.0, 2 * np.pi, 4000, endpoint=False)
    circle = np.stack([np.cos(t), np.sin(t)], 1)
    outer = _superellipse(t, 2.0, 1.3, 4.0)                       # rounded rectangle
    hole1 = circle * 0.75 + np.array([-0.9, 0.0])                # circular hole ...
    island = circle * 0.35 + np.array([-0.9, 0.0])               # ... with an island inside
    hole2 = circle * np.array([0.55, 0.8]) + np.array([1.0, 0.0])  # elliptic hole
    return [outer, hole1, island, hole2]


def _resample(poly: np.ndarray, spacing: float, phase: float) -> np.ndarray:
    """Points every ``spacing`` of arc length along a closed polyline ``(K, 2)``."""
    closed = np.vstack([poly, poly[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(3, int(round(s[-1] / spacing)))
    u = (phase + np.arange(n)) * (s[-1] / n)
    return np.stack([np.interp(u, s, closed[:, 0]), np.interp(u, s, closed[:, 1])], 1)


def make_points(seed: int = SEED, num_points: int = NUM_POINTS, noise: float = NOISE) -> np.ndarray:
    """``(N, 2)`` float64, N close to ``num_points``."""
    rng = np.random.default_rng(seed)
    cs = curves()
    length = sum(float(np.linalg.norm(np.diff(np.vstack([c, c[:1]]), axis=0), axis=1).sum()) for c in cs)
    spacing = length / num_points
    pts = np.vstack([_resample(c, spacing, rng.uniform()) for c in cs])
    pts = pts + rng.normal(scale=noise * spacing, size=pts.shape)
    return pts[rng.permutation(pts.shape[0])]


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else Path(__file__).with_name("nested.xy")
    pts = make_points()
    header = (f"# nested: {pts.shape[0]} points on 4 nested closed curves (outer, 2 holes, 1 island), "
              f"seed {SEED}, made by make_example.py")
    np.savetxt(out, pts, fmt="%.6f", header=header[2:], comments="# ")
    print(f"wrote {out} ({pts.shape[0]} points)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
