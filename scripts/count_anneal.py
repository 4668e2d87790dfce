"""Kernels, syncs and seconds of the annealer alone (pipeline.signs.anneal) during
reconstruct_batch on gpu_floor.py's generated shapes, counted with gpu_floor's OpCounter.

    OMP_NUM_THREADS=1 PYTHONPATH=$PWD python scripts/count_anneal.py --B 64,1024 \
        --tools ../shared/tools
"""
from __future__ import annotations

import argparse
import sys
import time


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--B", default="64", help="batch sizes, comma-separated")
    ap.add_argument("--points", type=int, default=500)
    ap.add_argument("--tools", default="../shared/tools", help="folder of gpu_floor.py")
    a = ap.parse_args()
    sys.path.insert(0, a.tools)
    import torch
    from gpu_floor import OpCounter, make_shapes
    import torch_isc
    import torch_isc.pipeline.signs as signs
    torch.set_num_threads(1)
    plain = signs.anneal
    for B in [int(b) for b in a.B.split(",")]:
        tally = {"kernels": 0, "syncs": 0, "calls": 0, "seconds": 0.0}

        def counted(*args, **kwargs):
            # counted once for kernels/syncs, and timed once without the counter
            with OpCounter() as c:
                plain(*args, **kwargs)
            t0 = time.perf_counter()
            out = plain(*args, **kwargs)
            tally["seconds"] += time.perf_counter() - t0
            tally["kernels"] += c.kernels
            tally["syncs"] += c.syncs
            tally["calls"] += 1
            return out

        signs.anneal = counted
        try:
            torch_isc.reconstruct_batch(make_shapes(B, a.points))
        finally:
            signs.anneal = plain
        floor = tally["kernels"] * 8e-6 + tally["syncs"] * 30e-6
        print(f"B={B}: {tally['calls']} anneal calls, {tally['kernels']} kernels, {tally['syncs']} syncs, "
              f"floor {floor:.3f} s, CPU {tally['seconds']:.2f} s")


if __name__ == "__main__":
    main()
