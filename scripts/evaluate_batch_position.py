"""Count the point sets whose result depends on where they sit in a batch.

Run from the repository root:

    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_batch_position.py            # 24 sets, seed 0
    OMP_NUM_THREADS=1 .venv/bin/python scripts/evaluate_batch_position.py --sets 48 --seed 1

Sets: circles, three-lobed curves and pairs of circles of 30-200 points, half of them with
Gaussian noise, all rounded to integer coordinates (an integer lattice: many exactly equal
distances, the ties a neighbour search must break the same way wherever the set sits). Each set
is solved alone, in one batch of all the sets, and in the same batch reversed; a result counts as
the same when its mesh vertices and nodal values are equal bit for bit. An item's result must
not depend on its batch (:func:`torch_isc.reconstruct_batch`). A measuring tool: it prints the
counts and exits 0 whatever they are.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import torch_isc  # noqa: E402


def lattice_sets(n: int, seed: int) -> list:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        kind = rng.integers(3)
        m = int(rng.integers(30, 200))
        t = rng.uniform(0, 2 * np.pi, m)
        if kind == 0:
            p = np.c_[np.cos(t), np.sin(t)] * rng.uniform(5, 30)
        elif kind == 1:
            r = 1 + 0.3 * np.cos(3 * t)
            p = np.c_[np.cos(t) * r, np.sin(t) * r] * rng.uniform(5, 30)
        else:
            p = np.r_[np.c_[np.cos(t), np.sin(t)] * 10, np.c_[np.cos(t), np.sin(t)] * 4 + 2]
        noisy = rng.random() < 0.5
        out.append(np.rint(p + rng.normal(0, 0.5, p.shape) * noisy))
    return out


def same(a, b) -> bool:
    ca, cb = a.curve, b.curve
    return (ca.values.shape == cb.values.shape and torch.equal(ca.values, cb.values)
            and torch.equal(ca.mesh.verts, cb.mesh.verts))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    sets = lattice_sets(args.sets, args.seed)
    alone = [torch_isc.reconstruct(p) for p in sets]
    batch = torch_isc.reconstruct_batch(sets)
    reverse = torch_isc.reconstruct_batch(sets[::-1])[::-1]
    n_b = sum(same(a, b) for a, b in zip(alone, batch))
    n_r = sum(same(a, b) for a, b in zip(alone, reverse))
    print(f"{len(sets)} integer-lattice sets (seed {args.seed}): the same bits alone and in one batch: {n_b}; "
          f"alone and in the reversed batch: {n_r}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
