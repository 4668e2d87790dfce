"""Does a small closed curve beside a large one survive? A unit circle of 300 points and one
small circle (radius 0.03-0.12, 12-40 points) 1.6 away, noise 0 and 0.5% of the diagonal, with
the speck rule as configured, without its surrounded guard, and off, and with the enclosure rule
on (enclose_chord 1.8); prints a table of curve
counts (2 is right).

    OMP_NUM_THREADS=1 python scripts/evaluate_small_components.py [--seed 0]
"""
from __future__ import annotations

import argparse

import numpy as np

from torch_isc import reconstruct

VARIANTS = (("default", {}), ("no surrounded guard", {"open_keep_surrounded": False}),
            ("speck rule off", {"open_tolerances": 0.0}), ("enclosure rule on", {"enclose_chord": 1.8}))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)

    def circle(n, r, cx=0.0):
        t = rng.uniform(0, 2 * np.pi, n)
        return np.stack([cx + r * np.cos(t), r * np.sin(t)], 1)

    rows, right = [], [0] * len(VARIANTS)
    for r in (0.03, 0.05, 0.08, 0.12):
        for n in (12, 20, 40):
            for noise in (0.0, 0.005):
                p = np.concatenate([circle(300, 1.0), circle(n, r, 1.6)])
                diag = float(np.hypot(*(p.max(0) - p.min(0))))
                p = p + noise * diag * rng.standard_normal(p.shape)
                counts = [len(reconstruct(p, config=cfg or None).polylines) for _, cfg in VARIANTS]
                right = [a + (c == 2) for a, c in zip(right, counts)]
                rows.append(f"| {100 * r / diag:.1f} | {n} | {100 * noise:.1f} | " + " | ".join(map(str, counts)) + " |")
    print("| radius % of diagonal | points | noise % | " + " | ".join(v for v, _ in VARIANTS) + " |")
    print("|---:|---:|---:|" + "---:|" * len(VARIANTS))
    print("\n".join(rows))
    print(f"| **two curves** | | | " + " | ".join(f"**{a}/{len(rows)}**" for a in right) + " |")


if __name__ == "__main__":
    main()
