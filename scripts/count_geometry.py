"""gpu_floor counts (kernels, syncs) of the geometry fit alone and of the whole run, on
gpu_floor's generated shapes (about 500 points), default config but for ``--trials``.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/count_geometry.py --B 64,256 [--trials 3]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO.parent / "shared" / "tools"))

import torch_isc  # noqa: E402
from torch_isc.pipeline import values  # noqa: E402
from torch_isc.pipeline.config import ReconstructConfig  # noqa: E402
from gpu_floor import OpCounter, make_shapes  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--B", default="64,256")
    ap.add_argument("--trials", type=int, default=0, help="geometry.lbfgs_trials (0: the default)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    fits = []
    fit = values.fit_geometry

    def counted(*args, **kw):
        with OpCounter() as c:
            out = fit(*args, **kw)
        fits.append(c)
        return out

    values.fit_geometry = counted
    cfg = ReconstructConfig()
    cfg.geometry.lbfgs_trials = a.trials
    for B in (int(b) for b in a.B.split(",")):
        fits.clear()
        with OpCounter() as c:
            torch_isc.reconstruct_batch(make_shapes(B), cfg)
        fk, fs = sum(f.kernels for f in fits), sum(f.syncs for f in fits)
        print(f"B={B}: whole run {c.kernels} kernels, {c.syncs} syncs, floor {c.floor_seconds():.2f} s "
              f"({B / c.floor_seconds():.0f} shapes/s); fit_geometry ({len(fits)} levels) {fk} kernels, "
              f"{fs} syncs, floor {fk * 8e-6 + fs * 30e-6:.2f} s")


if __name__ == "__main__":
    main()
