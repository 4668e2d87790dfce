"""Where a batched solve's time goes on a device: torch.profiler around one ``reconstruct_batch``.

    python scripts/profile_device.py --device cuda --B 4096 [--top 15]

The benchmark's mix (``scripts/benchmark.py`` part b) of ``--B`` shapes, solved once to warm up
and once under the profiler. Prints: the wall time without and with the profiler; the device's
busy time (the sum of its kernels' times) against the wall time, which says whether the solve is
bound by the host's launches and syncs or by the device's work; kernel launches, host syncs
(stream / device synchronizations and device-to-host copies) and their host time; the ops with
the most device time and the most calls. On the CPU (``--device cpu``) only the op table.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

import torch_isc  # noqa: E402


def _sync(dev: str) -> None:
    if torch.device(dev).type == "cuda":
        torch.cuda.synchronize()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--B", type=int, default=4096)
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    import benchmark as bm
    from torch.profiler import ProfilerActivity, profile

    dev = args.device
    cuda = torch.device(dev).type == "cuda"
    shapes = bm.make_shapes(args.B, 500, args.seed)
    pts = [torch.as_tensor(s["points"], dtype=torch.float64, device=dev) for s in shapes]
    torch_isc.reconstruct_batch(pts[: min(64, len(pts))])
    _sync(dev)
    t = time.perf_counter()
    torch_isc.reconstruct_batch(pts)
    _sync(dev)
    wall = time.perf_counter() - t
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=acts) as prof:
        t = time.perf_counter()
        torch_isc.reconstruct_batch(pts)
        _sync(dev)
        wall_prof = time.perf_counter() - t
    ev = prof.key_averages()
    print(f"# {dev}, B = {args.B}, torch {torch.__version__}\n")
    print(f"wall {wall:.3f} s ({args.B / wall:.0f} shapes/s); under the profiler {wall_prof:.3f} s\n")
    if cuda:
        busy = sum(e.self_device_time_total for e in ev if e.device_type == torch.autograd.DeviceType.CUDA) / 1e6
        by_name = {e.key: e for e in ev}

        def count(*names):
            return sum(by_name[n].count for n in names if n in by_name)

        def host_s(*names):
            return sum(by_name[n].self_cpu_time_total for n in names if n in by_name) / 1e6

        launches = count("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx")
        syncs = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaMemcpyAsync", "cudaMemcpy")
        print("| measure | value |\n|---|---:|")
        print(f"| device busy (sum of kernel times) | {busy:.3f} s ({100 * busy / wall_prof:.0f}% of the profiled wall) |")
        print(f"| kernel launches | {launches:,} (host {host_s('cudaLaunchKernel', 'cudaLaunchKernelExC'):.3f} s) |")
        for n in syncs:
            if n in by_name:
                print(f"| {n} | {by_name[n].count:,} calls, host {by_name[n].self_cpu_time_total / 1e6:.3f} s |")
        print()
        try:
            print(ev.table(sort_by="self_device_time_total", row_limit=args.top, max_name_column_width=48))
        except Exception:                               # older torch: the CUDA-named key
            print(ev.table(sort_by="self_cuda_time_total", row_limit=args.top, max_name_column_width=48))
    print(ev.table(sort_by="count", row_limit=args.top, max_name_column_width=48))
    return 0


if __name__ == "__main__":
    sys.exit(main())
