"""Measure the reconstruction on the public evaluation cases (the 24 point sets with truth curves).

Run from the repository root:

    .venv/bin/python scripts/evaluate_cases.py
    .venv/bin/python scripts/evaluate_cases.py --out out/cases            # + <case>.png / <case>.json
    .venv/bin/python scripts/evaluate_cases.py --peers                    # + NN-crust and concave hull
    .venv/bin/python scripts/evaluate_cases.py --one-by-one --filter glyph --set tolerance=0.006

All cases go through ONE ``torch_isc.reconstruct_batch`` call (``--one-by-one``: one call per
case, to compare). Each case is scored with :func:`torch_isc.metrics.score_case` (the rule of
the cases' README: distances divided by the truth's bounding-box diagonal). The script prints a
markdown table, a summary per noise level and the bar (PASS / FAIL per line). It is a measuring
tool: it exits 0 whatever the scores, non-zero only when it could not run.

``--peers`` adds the same table for two classical methods, for scale (they need the benchmark
extras scipy and shapely): NN-crust on the Delaunay triangulation (each point keeps the edge to
its nearest neighbour, and the shortest edge to a point on the other side of the half-plane
through it, the nearest-neighbour edge pointing into the other side), and
``shapely.concave_hull(ratio=0.1)``, without and with ``allow_holes``, whose boundary rings are
taken as curves.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import torch_isc  # noqa: E402
from _common import add_run_args, json_text, resolve_dir, run_main, setup_run  # noqa: E402
from torch_isc.io import read_points  # noqa: E402
from torch_isc import metrics  # noqa: E402

DEFAULT_CASES = REPO / ".." / "shared" / "cases"

# the bar: (noise label, what, needed) -- topology counts are out of 6 cases per noise level
TOPOLOGY_BAR = {"n0": 6, "n0.5": 5, "n1": 5, "n2": 4}
HAUSDORFF_BAR = {"n0": 1.0, "n1": 3.0}  # median Hausdorff, % of the diagonal


# ----------------------------------------------------------------------------- inputs

def noise_label(name: str) -> str:
    m = re.search(r"_(n[0-9.]+)$", name)
    return m.group(1) if m else "n?"


def noise_value(label: str) -> float:
    try:
        return float(label[1:])
    except ValueError:
        return math.inf


def load_cases(cases_dir: Path, filt: Optional[str]) -> List[Dict[str, Any]]:
    cases = []
    for tj in sorted(cases_dir.glob("*.truth.json")):
        name = tj.name[: -len(".truth.json")]
        if filt and filt not in name:
            continue
        xy = cases_dir / f"{name}.xy"
        truth = json.loads(tj.read_text())
        cases.append(dict(name=name, truth=truth, points=read_points(xy), noise=noise_label(name)))
    shape = lambda n: re.sub(r"_n[0-9.]+$", "", n)  # noqa: E731
    cases.sort(key=lambda c: (shape(c["name"]), noise_value(c["noise"])))
    return cases


# ----------------------------------------------------------------------------- peers

def walk_edges(edges: Sequence[Tuple[int, int]], pts: np.ndarray) -> List[Dict[str, Any]]:
    """Turn an undirected edge set into polylines by walking through degree-2 vertices.

    A walk starts at every vertex whose degree is not 2 and follows each unused edge until it
    reaches another such vertex (an open chain), or its start (closed); edges left over after
    that form cycles of degree-2 vertices (closed curves)."""
    adj: Dict[int, List[int]] = {}
    for a, b in edges:
        if a == b:
            continue
        adj.setdefault(a, []).append(b)
        adj.setdefault(b, []).append(a)
    used = set()

    def key(a, b):
        return (a, b) if a < b else (b, a)

    def walk(start: int, nxt: int) -> List[int]:
        chain = [start]
        prev, cur = start, nxt
        used.add(key(prev, cur))
        while True:
            chain.append(cur)
            if cur == start or len(adj[cur]) != 2:
                return chain
            follow = [w for w in adj[cur] if key(cur, w) not in used]
            if not follow:
                return chain
            prev, cur = cur, follow[0]
            used.add(key(prev, cur))

    out: List[Dict[str, Any]] = []
    starts = [v for v in adj if len(adj[v]) != 2]
    # chains from their ends first, then what is left: cycles of degree-2 vertices
    for v in starts + list(adj):
        for w in adj[v]:
            if key(v, w) in used:
                continue
            chain = walk(v, w)
            closed = len(chain) > 2 and chain[-1] == chain[0]
            if closed:
                chain = chain[:-1]
            out.append(dict(closed=closed, points=torch.as_tensor(pts[chain])))
    return out


def nn_crust(points: np.ndarray) -> List[Dict[str, Any]]:
    """NN-crust (Dey & Kumar): from the Delaunay triangulation, each point p keeps the edge to its
    nearest neighbour q, and its shortest edge pr with (r - p).(q - p) < 0 (r on the other side
    of the line through p perpendicular to pq)."""
    from scipy.spatial import Delaunay

    pts = np.unique(np.asarray(points, dtype=np.float64), axis=0)
    if len(pts) < 3:
        return []
    try:
        tri = Delaunay(pts)
    except Exception:  # all points collinear (QhullError)
        return []
    indptr, nbrs = tri.vertex_neighbor_vertices
    edges = set()
    for p in range(len(pts)):
        nb = nbrs[indptr[p]:indptr[p + 1]]
        if len(nb) == 0:
            continue
        v = pts[nb] - pts[p]
        d = np.hypot(v[:, 0], v[:, 1])
        q = nb[np.argmin(d)]
        edges.add((min(p, q), max(p, q)))
        other = (v @ (pts[q] - pts[p])) < 0
        if other.any():
            r = nb[other][np.argmin(d[other])]
            edges.add((min(p, r), max(p, r)))
    return walk_edges(sorted(edges), pts)


def concave_hull(points: np.ndarray, ratio: float = 0.1, allow_holes: bool = False) -> List[Dict[str, Any]]:
    """Boundary rings of ``shapely.concave_hull(MultiPoint, ratio, allow_holes)`` as closed
    curves (a degenerate hull gives an open chain or nothing)."""
    import shapely

    geom = shapely.concave_hull(shapely.MultiPoint(np.asarray(points, dtype=np.float64)), ratio=ratio,
                                allow_holes=allow_holes)
    out: List[Dict[str, Any]] = []
    polys = list(geom.geoms) if hasattr(geom, "geoms") else [geom]
    for g in polys:
        if g.is_empty:
            continue
        if g.geom_type == "Polygon":
            for ring in [g.exterior, *g.interiors]:
                xy = np.asarray(ring.coords)[:-1]
                if len(xy) >= 3:
                    out.append(dict(closed=True, points=torch.as_tensor(xy)))
        elif g.geom_type == "LineString":
            out.append(dict(closed=False, points=torch.as_tensor(np.asarray(g.coords))))
    return out


PEERS: Dict[str, Callable[[np.ndarray], List[Dict[str, Any]]]] = {
    "NN-crust (Delaunay)": nn_crust,
    "shapely.concave_hull(ratio=0.1)": concave_hull,
    "shapely.concave_hull(ratio=0.1, allow_holes)": lambda p: concave_hull(p, 0.1, True),
}


# ----------------------------------------------------------------------------- running

def run_isc(cases, config, one_by_one: bool, device: str) -> Tuple[List[Dict[str, Any]], float]:
    """Reconstruct every case; returns per case ``{result, polylines, levels, seconds}`` and
    the total wall time."""
    sets = [torch.as_tensor(c["points"], dtype=torch.float64, device=device) for c in cases]
    names = [c["name"] for c in cases]
    rows: List[Dict[str, Any]] = []
    t0 = time.perf_counter()
    if one_by_one:
        for s, n in zip(sets, names):
            t1 = time.perf_counter()
            res = torch_isc.reconstruct_batch([s], config, names=[n])[0]
            rows.append(dict(result=res, seconds=time.perf_counter() - t1))
    else:
        results = torch_isc.reconstruct_batch(sets, config, names=names)
        for res in results:
            sec = sum(lv.seconds for lv in res.stats) if res.stats else None
            rows.append(dict(result=res, seconds=sec))
    total = time.perf_counter() - t0
    for r in rows:
        res = r["result"]
        r["polylines"] = res.polylines
        r["levels"] = len(res.stats)
    return rows, total


def run_peer(fn, cases) -> Tuple[List[Dict[str, Any]], float]:
    rows = []
    t0 = time.perf_counter()
    for c in cases:
        t1 = time.perf_counter()
        pl = fn(c["points"])
        rows.append(dict(result=None, polylines=pl, levels=None, seconds=time.perf_counter() - t1))
    return rows, time.perf_counter() - t0


def score_rows(cases, rows) -> None:
    for c, r in zip(cases, rows):
        r["score"] = metrics.score_case(r["polylines"], c["truth"])


# ----------------------------------------------------------------------------- printing

def fmt_pct(x: float) -> str:
    if x is None or not math.isfinite(x):
        return "inf"
    return f"{100 * x:.2f}"


def print_table(title: str, cases, rows, total: float, file=sys.stdout, note: str = "") -> Dict[str, Any]:
    p = lambda *a: print(*a, file=file)  # noqa: E731
    p(f"### {title}\n")
    p("| case | points | truth curves | closed | open | topology ok | Hausdorff % | Chamfer % | levels | seconds |")
    p("|---|---:|---:|---:|---:|:---:|---:|---:|---:|---:|")
    for c, r in zip(cases, rows):
        s = r["score"]
        lv = "-" if r["levels"] is None else str(r["levels"])
        sec = "-" if r["seconds"] is None else f"{r['seconds']:.2f}"
        p(f"| {c['name']} | {len(c['points'])} | {s['n_truth']} | {s['n_closed']} | {s['n_open']} | "
          f"{'yes' if s['topology_ok'] else 'NO'} | {fmt_pct(s['hausdorff'])} | {fmt_pct(s['chamfer'])} | {lv} | {sec} |")
    if note:
        p(f"\n{note}")
    # summary per noise level
    levels = sorted({c["noise"] for c in cases}, key=noise_value)
    summary: Dict[str, Any] = {"levels": {}, "total_seconds": total}
    p("")
    p("| noise | topology right | median Hausdorff % | median Chamfer % |")
    p("|---|---:|---:|---:|")
    for lvl in levels:
        idx = [i for i, c in enumerate(cases) if c["noise"] == lvl]
        ok = sum(rows[i]["score"]["topology_ok"] for i in idx)
        mh = float(np.median([rows[i]["score"]["hausdorff"] for i in idx]))
        mc = float(np.median([rows[i]["score"]["chamfer"] for i in idx]))
        summary["levels"][lvl] = dict(n=len(idx), topology_ok=ok, median_hausdorff=mh, median_chamfer=mc)
        p(f"| {lvl} | {ok} of {len(idx)} | {fmt_pct(mh)} | {fmt_pct(mc)} |")
    right = sum(r["score"]["topology_ok"] for r in rows)
    p(f"\ntopology right overall: {right} of {len(rows)}; total time: {total:.2f} s\n")
    # the bar
    p("bar:")
    n_pass = n_lines = 0
    for lvl, need in TOPOLOGY_BAR.items():
        st = summary["levels"].get(lvl)
        if st is None:
            p(f"- [n/a ] topology {lvl}: >= {need}/6 (no case at this level)")
            continue
        need_here = need if st["n"] == 6 else math.ceil(need / 6 * st["n"] - 1e-9)
        ok = st["topology_ok"] >= need_here
        note = "" if st["n"] == 6 else f" (only {st['n']} case(s): needs {need_here})"
        p(f"- [{'PASS' if ok else 'FAIL'}] topology {lvl}: {st['topology_ok']}/{st['n']} >= {need}/6{note}")
        n_pass += ok
        n_lines += 1
    for lvl, lim in HAUSDORFF_BAR.items():
        st = summary["levels"].get(lvl)
        if st is None:
            p(f"- [n/a ] median Hausdorff {lvl}: <= {lim:g}% (no case at this level)")
            continue
        ok = 100 * st["median_hausdorff"] <= lim
        p(f"- [{'PASS' if ok else 'FAIL'}] median Hausdorff {lvl}: {fmt_pct(st['median_hausdorff'])}% <= {lim:g}%")
        n_pass += ok
        n_lines += 1
    p(f"\nbar: {n_pass} of {n_lines} lines pass\n")
    summary["bar_pass"], summary["bar_lines"] = n_pass, n_lines
    return summary


def print_comparison(summaries: Dict[str, Dict[str, Any]], levels: List[str]) -> None:
    print("### Comparison\n")
    head = " | ".join(f"topo {l}" for l in levels) + " | " + " | ".join(f"med H% {l}" for l in levels)
    print(f"| method | {head} | bar | seconds |")
    print("|---|" + "---:|" * (2 * len(levels) + 2))
    for m, s in summaries.items():
        topo = " | ".join(f"{s['levels'][l]['topology_ok']}/{s['levels'][l]['n']}" if l in s["levels"] else "-"
                          for l in levels)
        med = " | ".join(fmt_pct(s["levels"][l]["median_hausdorff"]) if l in s["levels"] else "-" for l in levels)
        print(f"| {m} | {topo} | {med} | {s['bar_pass']}/{s['bar_lines']} | {s['total_seconds']:.2f} |")
    print("")


# ----------------------------------------------------------------------------- outputs

def write_outputs(out: Path, cases, rows) -> None:
    out.mkdir(parents=True, exist_ok=True)
    from torch_isc.io import write_png

    for c, r in zip(cases, rows):
        res = r["result"]
        try:
            d = {"case": c["name"], "score": r["score"], **res.to_json_dict()}
            (out / f"{c['name']}.json").write_text(json_text(d))
            write_png(out / f"{c['name']}.png", res)
        except Exception as e:  # an output problem must not stop the measurement
            print(f"{c['name']}: could not write outputs: {type(e).__name__}: {e}", file=sys.stderr)


# ----------------------------------------------------------------------------- main

def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=None, help="cases folder (default: ../shared/cases from the repo root)")
    ap.add_argument("--out", default=None, help="write <case>.png and <case>.json here")
    ap.add_argument("--peers", action="store_true", help="also score NN-crust and shapely.concave_hull")
    add_run_args(ap, "case")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    config = setup_run(args)
    cases_dir = resolve_dir(args.cases, DEFAULT_CASES)
    cases = load_cases(cases_dir, args.filter)
    if not cases:
        print(f"no case found in {cases_dir}" + (f" matching {args.filter!r}" if args.filter else ""), file=sys.stderr)
        return 2
    print(f"{len(cases)} case(s) from {cases_dir}; "
          f"{'one call per case' if args.one_by_one else 'one reconstruct_batch call'}; device {args.device}\n")

    summaries: Dict[str, Dict[str, Any]] = {}
    status = 0
    rows, total = run_isc(cases, config, args.one_by_one, args.device)
    score_rows(cases, rows)
    mode = "one by one" if args.one_by_one else "one batch"
    note = ("seconds: wall time of each call" if args.one_by_one else
            "seconds: sum of the times of the batch levels the case took part in (levels are shared)")
    summaries["torch_isc"] = print_table(f"torch_isc ({mode})", cases, rows, total, note=note)
    if args.out:
        write_outputs(Path(args.out).resolve(), cases, rows)
    if args.peers:
        for name, fn in PEERS.items():
            try:
                rows, total = run_peer(fn, cases)
            except ImportError as e:
                print(f"{name}: skipped ({e})\n")
                continue
            score_rows(cases, rows)
            summaries[name] = print_table(name, cases, rows, total, note="seconds: wall time per case")
    if len(summaries) > 1:
        print_comparison(summaries, sorted({c["noise"] for c in cases}, key=noise_value))
    return status


if __name__ == "__main__":
    run_main(main)
