"""Kernel launches and host syncs of single pipeline stages (gpu_floor's model), per batch size.

Run from the repository root:

    OMP_NUM_THREADS=1 PYTHONPATH=$PWD .venv/bin/python scripts/count_stages.py \
        --stage relax,anneal,geometry --B 64,1024 [--points 500] [--top 5] [--trials 0] \
        [--tools ../shared/tools]

Runs ``reconstruct_batch`` on gpu_floor's generated shapes under gpu_floor's ``OpCounter`` (the
whole run) with each chosen stage's function wrapped in an ``OpCounter`` of its own, and prints
per stage its calls, kernels, syncs, the time floor they imply, its top sync sites and its CPU
seconds (from a second run, not counted). ``--trials`` sets ``geometry.lbfgs_trials`` (0: default).
``--gpu-layout`` counts the layout the code takes off the CPU (same results, other launches):
``lbfgs_trials`` 3, the annealer's fields as one embedding bag and its random numbers in the
large blocks (``pipeline/signs.py``: ``_FIELDS_BY_BAG``, ``_RNG_NUMBERS``), the neighbour
searches in the blocks of an 80 GB device (``pipeline/noise.py``: ``knn_budget``).
"""
from __future__ import annotations

import argparse
import importlib
import sys
import time

# stage -> (module, function wrapped there: the name the pipeline calls it by; fit_geometry's calls
# from band.py, which imports it by name, are not counted)
STAGES = {"relax": ("torch_isc.pipeline.loop", "relax_stage"),
          "anneal": ("torch_isc.pipeline.signs", "anneal"),
          "geometry": ("torch_isc.pipeline.values", "fit_geometry")}


def run_wrapped(run, stages, wrap):
    """``run()`` with each stage's function replaced by ``wrap(stage, function)``."""
    targets = [(s, importlib.import_module(STAGES[s][0]), STAGES[s][1]) for s in stages]
    plain = [getattr(m, name) for _, m, name in targets]
    for (s, m, name), fn in zip(targets, plain):
        setattr(m, name, wrap(s, fn))
    try:
        return run()
    finally:
        for (_, m, name), fn in zip(targets, plain):
            setattr(m, name, fn)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stage", default=",".join(STAGES), help="stages, comma-separated: " + ", ".join(STAGES))
    ap.add_argument("--B", default="64,1024", help="batch sizes, comma-separated")
    ap.add_argument("--points", type=int, default=500)
    ap.add_argument("--top", type=int, default=5, help="sync sites shown per stage")
    ap.add_argument("--trials", type=int, default=0, help="geometry.lbfgs_trials (0: the default)")
    ap.add_argument("--tools", default="../shared/tools", help="folder of gpu_floor.py")
    ap.add_argument("--gpu-layout", action="store_true",
                    help="count the layout taken off the CPU (lbfgs_trials 3, bag fields, large RNG and neighbour blocks)")
    a = ap.parse_args()
    stages = a.stage.split(",")
    if unknown := set(stages) - set(STAGES):
        ap.error(f"unknown stage(s): {', '.join(sorted(unknown))}")
    sys.path.insert(0, a.tools)
    import torch
    from gpu_floor import OpCounter, make_shapes
    import _common  # noqa: F401  (puts the repository on sys.path)
    import torch_isc
    from torch_isc.pipeline.config import ReconstructConfig
    torch.set_num_threads(1)
    cfg = ReconstructConfig()
    cfg.geometry.lbfgs_trials = a.trials
    if a.gpu_layout:
        from torch_isc.pipeline import signs
        signs._FIELDS_BY_BAG["cpu"] = True
        signs._RNG_NUMBERS["cpu"] = signs._RNG_NUMBERS_OTHER
        from torch_isc.pipeline import noise
        # the neighbour searches' blocks of an 80 GB device (noise.knn_budget)
        noise._KNN_BUDGETS["cpu"] = (80 << 30) // noise._KNN_BYTES_PER_PAIR
        cfg.geometry.lbfgs_trials = a.trials or 3
    Bs = [int(b) for b in a.B.split(",")]
    shapes = make_shapes(max(Bs), a.points)
    for B in Bs:
        tally = {s: OpCounter() for s in stages}   # the stage's calls' counts, summed
        calls = dict.fromkeys(stages, 0)
        seconds = dict.fromkeys(stages, 0.0)

        def counted(stage, fn):
            def f(*args, **kwargs):
                with OpCounter() as c:
                    out = fn(*args, **kwargs)
                tally[stage].kinds.update(c.kinds)
                tally[stage].sites.update(c.sites)
                calls[stage] += 1
                return out
            return f

        def timed(stage, fn):
            def f(*args, **kwargs):
                t0 = time.perf_counter()
                out = fn(*args, **kwargs)
                seconds[stage] += time.perf_counter() - t0
                return out
            return f

        with OpCounter() as whole:
            run_wrapped(lambda: torch_isc.reconstruct_batch(shapes[:B], cfg), stages, counted)
        t0 = time.perf_counter()
        run_wrapped(lambda: torch_isc.reconstruct_batch(shapes[:B], cfg), stages, timed)
        wall = time.perf_counter() - t0
        print(f"B={B}: whole run {whole.kernels} kernels, {whole.syncs} syncs, floor "
              f"{whole.floor_seconds():.3f} s ({B / whole.floor_seconds():.0f} shapes/s), CPU {wall:.2f} s")
        for s in stages:
            t = tally[s]
            print(f"  {s}: {calls[s]} calls, {t.kernels} kernels, {t.syncs} syncs, "
                  f"floor {t.floor_seconds():.3f} s, CPU {seconds[s]:.2f} s")
            for site, n in t.top_sites(a.top, "sync"):
                print(f"    sync   {n:7d}  {site}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
