"""gpu_floor's count of the code a GPU would run, on this CPU.

``../shared/tools/gpu_floor.py`` counts what the CPU runs; four choices of the solve depend on
the device type and give the same results either way, the last to rounding (tests/test_fit.py,
tests/test_budget.py and tests/test_graphs.py check them): the annealer's local fields by one ``embedding_bag`` (the CPU: a gather, a product
and a sum per part, faster there), its random numbers hashed in blocks of ``2**26`` (the CPU:
``2**20``, cache-sized), ``lbfgs_trials`` 3 step lengths per line-search round (the CPU: 1), and
the L-BFGS's fixed-shape rounds from the first (the CPU: lockstep rounds while its history fills).
This script forces the non-CPU choices, counts with gpu_floor's ``OpCounter`` on its shapes, and
extrapolates to B=4096 as gpu_floor does (linear in log B between the two batch sizes given).

With ``--graphs`` the loops replay their rounds as on CUDA with ``run.cuda_graphs``
(pipeline/graphs.py, emulated: the step runs eagerly): a graph's first replay is counted op by
op (recording it costs the host about what launching its kernels would), every later replay as
one launch.

    OMP_NUM_THREADS=1 python scripts/gpu_floor_device_path.py --B 64,256 [--graphs]
"""
from __future__ import annotations

import argparse
import contextlib
import math
import sys
from pathlib import Path

import torch
from torch.utils._python_dispatch import _disable_current_modes

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
for tools in (HERE.parent.parent / "shared" / "tools", HERE.parent / "shared" / "tools"):
    if (tools / "gpu_floor.py").exists():
        sys.path.insert(0, str(tools))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--B", default="64,256", help="two batch sizes, comma-separated")
    ap.add_argument("--points", type=int, default=500)
    ap.add_argument("--graphs", action="store_true", help="replay the loops' rounds as CUDA graphs would")
    a = ap.parse_args()
    try:
        from gpu_floor import LAUNCH_S, SYNC_S, OpCounter, make_shapes
    except ImportError:
        sys.exit("gpu_floor_device_path: ../shared/tools/gpu_floor.py not found")
    import torch_isc
    from torch_isc.pipeline import graphs, optim, signs
    from torch_isc.pipeline.config import ReconstructConfig
    torch.set_num_threads(1)
    signs._FIELDS_BY_BAG["cpu"] = True
    signs._RNG_NUMBERS["cpu"] = signs._RNG_NUMBERS_OTHER
    optim._LOCKSTEP_FILL["cpu"] = False
    cfg = ReconstructConfig().replace(lbfgs_trials=3)
    Bs = [int(b) for b in a.B.split(",")]
    shapes = make_shapes(max(Bs), a.points)
    counter = [None]

    class Counted(graphs._Emulated):
        first = True

        def replay(self):
            if self.first or counter[0] is None:
                self.first = False
                return super().replay()
            with _disable_current_modes():
                super().replay()
            counter[0].kinds["kernel"] += 1

    graphs._Emulated = Counted

    def mode():
        return graphs.use("emulate") if a.graphs else contextlib.nullcontext()

    with mode():
        torch_isc.reconstruct_batch(shapes[:2], cfg)
    rows = []
    print("| B | kernels | syncs | floor s | floor shapes/s |\n|---:|---:|---:|---:|---:|")
    for B in Bs:
        with OpCounter() as c, mode():
            counter[0] = c
            torch_isc.reconstruct_batch(shapes[:B], cfg)
        rows.append((B, c.kernels, c.syncs))
        f = c.floor_seconds()
        print(f"| {B} | {c.kernels:,} | {c.syncs:,} | {f:.2f} | {B / f:.0f} |")
    if len(rows) > 1:
        (b0, k0, s0), (b1, k1, s1) = rows[0], rows[-1]
        k4 = k1 + (k1 - k0) / math.log(b1 / b0) * math.log(4096 / b1)
        s4 = s1 + (s1 - s0) / math.log(b1 / b0) * math.log(4096 / b1)
        f4 = k4 * LAUNCH_S + s4 * SYNC_S
        print(f"| 4096 (extrapolated) | {k4:,.0f} | {s4:,.0f} | {f4:.2f} | {4096 / f4:.0f} |")


if __name__ == "__main__":
    main()
