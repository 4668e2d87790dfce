"""Clean nested rings closer than a few sample spacings: how many loops come back.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_nested_rings.py [--set KEY=VALUE ...]

``k`` concentric circles (radii 1, 1 - g h, 1 - 2 g h, ..., ``h`` the outer ring's sample
spacing 2 pi / 300), each sampled evenly at the outer ring's spacing, no noise: the truth is
``k`` loops. Prints per set the loops found, the levels, the estimated noise (% of the radius)
and whether the loop hit a limit. One ``reconstruct_batch`` call.
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_run_args(ap, "set")
    args = ap.parse_args(argv)
    config = setup_run(args)
    keys = [(k, g) for k in (3, 5) for g in (2.0, 3.0, 4.0)]
    res = torch_isc.reconstruct_batch([torch.tensor(rings(k, g)) for k, g in keys], config)
    print("| rings | gap (spacings) | loops | levels | noise % of radius | limit |")
    print("|---:|---:|---:|---:|---:|---|")
    for (k, g), r in zip(keys, res):
        print(f"| {k} | {g:g} | {r.num_closed} | {len(r.stats)} | {100 * r.stats[0].noise:.3g} | {r.limit or ''} |")
    right = sum(r.num_closed == k for (k, _), r in zip(keys, res))
    print(f"\nright loop count: {right} of {len(keys)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
