"""Clean nested rings closer than a few sample spacings: how many loops come back.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_nested_rings.py [--random] [--set KEY=VALUE ...]

``k`` concentric circles (radii 1, 1 - g h, 1 - 2 g h, ..., ``h`` the outer ring's sample
spacing 2 pi / 300), each sampled evenly at the outer ring's spacing, no noise: the truth is
``k`` loops. Prints per set the loops found, the levels, the estimated noise (% of the diagonal)
and whether the loop hit a limit. One ``reconstruct_batch`` call.

``--random``: 36 harder sets instead, 4 seeds x 2, 3 or 4 rings x gaps of 3, 4 and 6 spacings:
concentric ellipses (one random eccentricity 0.6-1 per set), sampled with a jitter of +-0.3
spacings (even seeds) or uniformly at random (odd seeds: some spacings are several times the
mean), then rotated, scaled by 0.1-10 and shifted by up to 5 at random.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import add_run_args, setup_run  # noqa: E402
import torch_isc  # noqa: E402


def rings(k: int, gap: float, n: int = 300) -> np.ndarray:
    h = 2 * np.pi / n
    out = []
    for j in range(k):
        r = 1 - j * gap * h
        m = int(round(n * r))
        t = np.arange(m) * 2 * np.pi / m + 0.37 * j
        out.append(np.stack([r * np.cos(t), r * np.sin(t)], 1))
    return np.concatenate(out)


def ellipse_rings(rng: np.random.Generator, k: int, gap: float, uniform: bool = False, n: int = 300) -> np.ndarray:
    """``k`` concentric ellipses (axes r and e r, e drawn in [0.6, 1]; r = 1, 1 - g h, ... with
    ``h = 2 pi / n``), each sampled at ``n r`` angles jittered by up to 0.3 of their step (or, with
    ``uniform``, drawn uniformly at random), then turned, scaled by 0.1-10 and moved by up to 5
    at random: the gap is ``gap`` spacings along the major axis, ``e gap`` along the minor one."""
    h = 2 * np.pi / n
    ecc = rng.uniform(0.6, 1.0)
    out = []
    for j in range(k):
        r = 1 - j * gap * h
        m = int(round(n * r))
        if uniform:
            t = np.sort(rng.uniform(0, 2 * np.pi, m))
        else:
            t = (np.arange(m) + rng.uniform(-0.3, 0.3, m)) * 2 * np.pi / m
        out.append(np.stack([r * np.cos(t), ecc * r * np.sin(t)], 1))
    a = rng.uniform(0, np.pi)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return np.concatenate(out) @ rot.T * rng.uniform(0.1, 10) + rng.uniform(-5, 5, 2)


def random_ellipses(seed: int, k: int, gap: float) -> np.ndarray:
    """The ``--random`` set of ``seed``: jittered sampling on even seeds, uniform on odd ones."""
    return ellipse_rings(np.random.default_rng([100 + seed, k, int(gap * 10)]), k, gap, uniform=seed % 2 == 1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--random", action="store_true", help="the 36 jittered or randomly sampled ellipse sets")
    add_run_args(ap, "set")
    args = ap.parse_args(argv)
    config = setup_run(args)
    if args.random:
        keys = [(s, k, g) for s in range(4) for k in (2, 3, 4) for g in (3.0, 4.0, 6.0)]
        sets = [random_ellipses(s, k, g) for s, k, g in keys]
    else:
        keys = [(None, k, g) for k in (3, 5) for g in (2.0, 3.0, 4.0)]
        sets = [rings(k, g) for _, k, g in keys]
    res = torch_isc.reconstruct_batch([torch.tensor(p) for p in sets], config)
    print("| seed | rings | gap (spacings) | loops | levels | noise % of diagonal | limit |")
    print("|---:|---:|---:|---:|---:|---:|---|")
    for (s, k, g), p, r in zip(keys, sets, res):
        diag = float(np.hypot(*(p.max(0) - p.min(0))))
        print(f"| {'' if s is None else s} | {k} | {g:g} | {r.num_closed} | {len(r.stats)} | "
              f"{100 * r.stats[0].noise / diag:.3g} | {r.limit or ''} |")
    right = sum(r.num_closed == k for (_, k, _), r in zip(keys, res))
    print(f"\nright loop count: {right} of {len(keys)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
