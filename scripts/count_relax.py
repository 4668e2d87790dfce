"""Kernel launches and host syncs of the relaxation stage alone (gpu_floor's model), per batch size.

Run from the repository root:

    OMP_NUM_THREADS=1 .venv/bin/python scripts/count_relax.py --B 64,1024

Solves gpu_floor's generated shapes (about 500 points each) with ``reconstruct_batch``, keeps the
inputs of every relaxation call, then counts the relaxation calls alone under gpu_floor's
``OpCounter``: kernels, syncs, the time floor they imply and the top sync sites.
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
import torch_isc.pipeline.loop as loop  # noqa: E402
from torch_isc.pipeline.relax import relax_mesh  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--B", default="64,1024")
    ap.add_argument("--points", type=int, default=500)
    ap.add_argument("--top", type=int, default=5)
    a = ap.parse_args()
    from gpu_floor import OpCounter, make_shapes
    torch.set_num_threads(1)
    Bs = [int(b) for b in a.B.split(",")]
    shapes = make_shapes(max(Bs), a.points)
    orig = loop.relax_stage
    for B in Bs:
        calls = []

        def keep(ws, cfg):
            calls.append((ws.mesh, ws.points, ws.point_item, ws.face, cfg))
            return orig(ws, cfg)

        loop.relax_stage = keep
        try:
            torch_isc.reconstruct_batch(shapes[:B])
        finally:
            loop.relax_stage = orig
        with OpCounter() as c:
            for mesh, pts, item, face, cfg in calls:
                relax_mesh(mesh, pts, item, face, cfg)
        print(f"B={B}: {len(calls)} relaxation calls; {c.kernels} kernels, {c.syncs} syncs; "
              f"floor {c.floor_seconds():.3f} s")
        for s, n in c.top_sites(a.top, "sync"):
            print(f"    sync   {n:7d}  {s}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
