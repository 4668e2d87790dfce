"""The CUDA graphs of the inner loops (``run.cuda_graphs``, pipeline/graphs.py) against eager
loops, in one process, runs alternated (a lent machine's speed drifts between runs).

Modes: ``off`` (eager), ``on`` (the annealer's sweeps and the fits' rounds replayed), ``anneal``
(everything but the fits' rounds), ``quarter`` (``on``, the fits' working set compacted when a quarter
of it is left running instead of a half: fewer recordings, more arithmetic), ``trials1`` (``on``
with one step length per line-search round, ``lbfgs_trials: 1``, instead of the GPU's 3: once a
round costs one launch, the two extra trials of a round that accepts its first are only
arithmetic). Per set and mode: the median wall time of a ``reconstruct_batch``
call, its stage seconds, and how many graphs were recorded and replayed, and the host seconds
spent recording them.

    python scripts/benchmark_graphs.py --device cuda --batches 512,4096 --hard 64 --repeats 3

On a CPU the graphs are emulated (``--device cpu``: the recorded step runs eagerly at each
replay); that checks the script, not the speed.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import statistics
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import benchmark as bm  # noqa: E402
import torch_isc  # noqa: E402
from torch_isc.pipeline import graphs, optim, values  # noqa: E402
from torch_isc.pipeline.config import ReconstructConfig  # noqa: E402

MODES = ("off", "on", "anneal", "quarter", "trials1")


class _Counts:
    def __init__(self):
        self.captures = self.replays = 0
        self.seconds = 0.0


def _install(counts: _Counts) -> None:
    """Count and time every recording, count every replay."""
    capture = graphs.capture

    def counted(step, device, kind):
        t0 = time.perf_counter()
        g = capture(step, device, kind)
        counts.seconds += time.perf_counter() - t0
        counts.captures += 1
        if g is None:
            return None
        replay = g.replay

        class Counted:
            def replay(self):
                counts.replays += 1
                replay()
        return Counted()
    graphs.capture = counted


class _NoFitGraphs:
    active = staticmethod(lambda device, kind: False)


def _mode(mode: str, device: str):
    emulate = graphs.use("emulate") if torch.device(device).type == "cpu" and mode != "off" else contextlib.nullcontext()
    cfg = ReconstructConfig().replace(cuda_graphs=mode != "off")
    if mode == "trials1":
        cfg = cfg.replace(lbfgs_trials=1)
    return cfg, emulate


def _run(tensors, mode: str, device: str, counts: _Counts):
    cfg, emulate = _mode(mode, device)
    saved, saved_fit = optim.graphs, values.batched_lbfgs
    if mode == "anneal":
        optim.graphs = _NoFitGraphs
    if mode == "quarter":
        values.batched_lbfgs = functools.partial(saved_fit, shrink=0.25)
    try:
        with emulate:
            t0 = bm.clock(device)
            res = torch_isc.reconstruct_batch(tensors, cfg)
            dt = bm.clock(device) - t0
    finally:
        optim.graphs, values.batched_lbfgs = saved, saved_fit
    return dt, res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--batches", default="512,4096", help="part b batch sizes, comma-separated")
    ap.add_argument("--hard", type=int, default=64, help="part d's hard mix, this many shapes (0: none)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--modes", default=",".join(MODES))
    a = ap.parse_args()
    torch.set_num_threads(1)
    modes = [m for m in a.modes.split(",") if m]
    bad = [m for m in modes if m not in MODES]
    if bad:
        sys.exit(f"benchmark_graphs: unknown mode {bad[0]!r} (one of {', '.join(MODES)})")
    batches = [int(b) for b in a.batches.split(",") if b]
    sets = []
    if batches:
        shapes = bm.make_shapes(max(batches), 500, 0)
        for B in batches:
            sets.append((f"b, B={B}", [bm.as_tensor(s["points"], a.device) for s in shapes[:B]]))
    if a.hard:
        hard = bm.make_hard_shapes(a.hard, 500, 0)
        sets.append((f"d, B={a.hard}", [bm.as_tensor(s["points"], a.device) for s in hard]))
    counts = _Counts()
    _install(counts)
    for m in modes:                                       # lazy initialization of every path
        _run(sets[0][1][:8], m, a.device, counts)
    print(f"# CUDA graphs against eager loops: torch {torch.__version__}, device {a.device}"
          + (f" ({torch.cuda.get_device_name(0)})" if a.device.startswith("cuda") else "")
          + f", median of {a.repeats}, modes alternated\n")
    print("| set | mode | wall s | shapes/s | noise | topology | geometry | relax | graphs recorded | replays | recording s |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, tensors in sets:
        rows = {m: dict(t=[], st=[], c=[]) for m in modes}
        for _ in range(a.repeats):
            for m in modes:
                c0 = (counts.captures, counts.replays, counts.seconds)
                dt, res = _run(tensors, m, a.device, counts)
                rows[m]["t"].append(dt)
                rows[m]["st"].append(bm.batch_stage_sums(res))
                rows[m]["c"] = (counts.captures - c0[0], counts.replays - c0[1], counts.seconds - c0[2])
        for m in modes:
            r = rows[m]
            t = statistics.median(r["t"])
            st = {k: statistics.median(s.get(k, 0.0) for s in r["st"]) for k in ("noise", "topology", "geometry", "relax")}
            cap, rep, cs = r["c"]
            print(f"| {name} | {m} | {t:.3f} | {len(tensors) / t:.1f} | {st['noise']:.3f} | {st['topology']:.3f} | {st['geometry']:.3f} "
                  f"| {st['relax']:.3f} | {cap} | {rep} | {cs:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
