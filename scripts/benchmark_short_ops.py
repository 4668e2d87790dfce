"""Why the fit writes some ops out on a CPU: times of short reductions, broadcasts and gathers
against their written-out forms, and whether the bits agree (one thread).

    OMP_NUM_THREADS=1 python scripts/benchmark_short_ops.py [--rows 60000] [--repeats 50]
"""
import argparse
import time

import torch


def clock(fn, repeats):
    fn()
    t = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t) / repeats * 1e3


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=60000)
    ap.add_argument("--repeats", type=int, default=50)
    a = ap.parse_args()
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    n, f64 = a.rows, torch.float64
    x2 = torch.randn(n, 2, generator=g, dtype=f64)
    lab = torch.randint(0, n, (n, 2), generator=g)
    G = torch.randn(n, 3, 2, generator=g, dtype=f64)
    dg = torch.randn(1, n, 2, generator=g, dtype=f64)
    v = torch.randn(n, 2, generator=g, dtype=f64)
    idx = torch.randint(0, n, (n, 12), generator=g)
    rows = [
        ("x.sum(-1), x (N, 2) float64", lambda: x2.sum(-1), lambda: x2[:, 0] + x2[:, 1]),
        ("labels.amin(1), (N, 2) long", lambda: lab.amin(1), lambda: torch.minimum(lab[:, 0], lab[:, 1])),
        ("(G * g[..., None, :]).sum(-1), G (N, 3, 2)", lambda: (G * dg[..., None, :]).sum(-1),
         lambda: G[..., 0] * dg[..., None, 0] + G[..., 1] * dg[..., None, 1]),
        ("v[idx], idx (N, 12)", lambda: v[idx], lambda: v.index_select(0, idx.reshape(-1)).view(n, 12, 2)),
    ]
    print(f"{n:,} rows, one thread, milliseconds per call (mean of {a.repeats})\n")
    print("| op | torch form ms | written-out form ms | ratio | same bits |")
    print("|---|---:|---:|---:|:---:|")
    for name, ref, alt in rows:
        t0, t1 = clock(ref, a.repeats), clock(alt, a.repeats)
        print(f"| `{name}` | {t0:.3f} | {t1:.3f} | {t0 / t1:.1f}x | {'yes' if torch.equal(ref(), alt()) else 'no'} |")


if __name__ == "__main__":
    main()
