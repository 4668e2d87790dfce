"""Reconstruct every real point set under ../shared/data (third-party files, no ground truth).

Run from the repository root:

    .venv/bin/python scripts/run_data.py --out out/data
    .venv/bin/python scripts/run_data.py --out out/data --filter fitconnect --set tolerance=0.006

Finds ``*.txt``, ``*.p2d`` and ``*.xy`` files recursively (default folder: ``../shared/data``
from the repository root), reads them with ``torch_isc.io.read_points`` (blank lines, ``#``
comments, one header line and repeated points are fine), reconstructs them all in ONE
``torch_isc.reconstruct_batch`` call (``--one-by-one``: one call per file), writes
``<out>/<folder>/<name>.png`` and ``.json`` and prints a markdown table: file, points, closed
and open curves, levels, converged, the mean distance from the points to the curve (% of the
points' bounding-box diagonal) and seconds. A problem with one file (unreadable, failed
reconstruction, failed write) is reported in one line and does not stop the others. Exits 0
unless the script itself crashed.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import torch_isc  # noqa: E402
from _common import add_run_args, json_text, resolve_dir, run_main, setup_run  # noqa: E402
from torch_isc.io import read_points  # noqa: E402
from torch_isc import metrics  # noqa: E402

DEFAULT_DATA = REPO / ".." / "shared" / "data"
SUFFIXES = {".txt", ".p2d", ".xy"}


def find_files(root: Path, filt: Optional[str]) -> List[Path]:
    files = [p for p in sorted(root.rglob("*")) if p.is_file() and p.suffix.lower() in SUFFIXES]
    if filt:
        files = [p for p in files if filt in str(p.relative_to(root))]
    return files


def one_line(e: BaseException) -> str:
    msg = str(e).strip().splitlines()
    return f"{type(e).__name__}: {msg[0] if msg else ''}"


def reconstruct(items: List[Dict[str, Any]], config, one_by_one: bool, device: str):
    """Fill ``item["result"]`` / ``item["seconds"]`` (or ``item["error"]``); returns the wall
    time and whether one batch call did it all."""
    t0 = time.perf_counter()
    todo = [it for it in items if "error" not in it]
    batch_ok = False
    if not one_by_one and todo:
        try:
            sets = [torch.as_tensor(it["points"], dtype=torch.float64, device=device) for it in todo]
            results = torch_isc.reconstruct_batch(sets, config, names=[it["name"] for it in todo])
            for it, res in zip(todo, results):
                it["result"] = res
                it["seconds"] = sum(lv.seconds for lv in res.stats)
            batch_ok = True
        except Exception as e:
            print(f"batch failed ({one_line(e)}); going on one file at a time", file=sys.stderr)
    if not batch_ok:
        for it in todo:
            t1 = time.perf_counter()
            try:
                pts = torch.as_tensor(it["points"], dtype=torch.float64, device=device)
                it["result"] = torch_isc.reconstruct_batch([pts], config, names=[it["name"]])[0]
                it["seconds"] = time.perf_counter() - t1
            except Exception as e:
                it["error"] = f"reconstruction failed: {one_line(e)}"
                print(f"{it['name']}: {it['error']}", file=sys.stderr)
    return time.perf_counter() - t0, batch_ok


def write_outputs(out: Path, items: List[Dict[str, Any]]) -> None:
    from torch_isc.io import write_png

    for it in items:
        if "result" not in it:
            continue
        stem = out / it["name"]
        try:
            stem.parent.mkdir(parents=True, exist_ok=True)
            d = {"file": it["name"], "mean_distance_pct": it.get("mean_pct"), **it["result"].to_json_dict()}
            Path(f"{stem}.json").write_text(json_text(d))
            write_png(Path(f"{stem}.png"), it["result"])
        except Exception as e:
            print(f"{it['name']}: could not write outputs: {one_line(e)}", file=sys.stderr)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="data folder (default: ../shared/data from the repo root)")
    ap.add_argument("--out", default="out/data", help="output folder (default: out/data)")
    add_run_args(ap, "file")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    config = setup_run(args)
    root = resolve_dir(args.data, DEFAULT_DATA)
    files = find_files(root, args.filter)
    if not files:
        print(f"no *.txt / *.p2d / *.xy file under {root}" + (f" matching {args.filter!r}" if args.filter else ""),
              file=sys.stderr)
        return 2
    items: List[Dict[str, Any]] = []
    for f in files:
        name = f.relative_to(root).with_suffix("").as_posix()
        it: Dict[str, Any] = {"name": name, "file": f.relative_to(root).as_posix()}
        try:
            it["points"] = read_points(f)
        except Exception as e:
            it["error"] = f"cannot read: {one_line(e)}"
            print(f"{it['file']}: {it['error']}", file=sys.stderr)
        items.append(it)
    print(f"{len(files)} file(s) from {root}; "
          f"{'one call per file' if args.one_by_one else 'one reconstruct_batch call'}; device {args.device}\n")
    total, batched = reconstruct(items, config, args.one_by_one, args.device)

    for it in items:
        if "result" not in it:
            continue
        try:
            pts = it["points"]
            diag = metrics.bbox_diagonal(pts) or 1.0
            dist = metrics.point_distances(pts, it["result"].polylines)
            it["mean_pct"] = 100.0 * float(dist.mean()) / diag
        except Exception as e:
            it["mean_pct"] = None
            print(f"{it['file']}: could not measure: {one_line(e)}", file=sys.stderr)

    out = Path(args.out).resolve()
    write_outputs(out, items)

    sec_note = ("sum of the times of the batch levels this file took part in" if batched
                else "wall time of its own call")
    print("| file | points | closed | open | levels | converged | mean distance % | seconds |")
    print("|---|---:|---:|---:|---:|:---:|---:|---:|")
    for it in items:
        if "result" not in it:
            npts = len(it["points"]) if "points" in it else "-"
            print(f"| {it['file']} | {npts} | - | - | - | - | error | - |")
            continue
        r = it["result"]
        m = it.get("mean_pct")
        mean = "inf" if m is None or not math.isfinite(m) else f"{m:.3f}"
        conv = "yes" if r.converged else f"no ({r.limit})" if r.limit else "no"
        print(f"| {it['file']} | {len(it['points'])} | {r.num_closed} | {r.num_open} | {len(r.stats)} | {conv} | "
              f"{mean} | {it['seconds']:.2f} |")
    n_ok = sum("result" in it for it in items)
    errors = [it for it in items if "result" not in it]
    if errors:
        print("\nerrors:")
        for it in errors:
            print(f"- {it['file']}: {it.get('error', 'no result')}")
    print(f"\n{n_ok} of {len(items)} file(s) reconstructed; total time {total:.2f} s "
          f"(seconds column: {sec_note}); outputs in {out}")
    return 0


if __name__ == "__main__":
    run_main(main)
