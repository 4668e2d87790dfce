"""Record, or compare against a recording, the outputs of every evaluation: the guard of a
refactoring that must not change results.

Run from the repository root:

    .venv/bin/python scripts/record_outputs.py --record out/baseline     # before a change
    .venv/bin/python scripts/record_outputs.py --compare out/baseline    # after it

Suites (each solved in one batch, as the evaluation scripts do): the 24 public cases
(``../shared/cases``), a generated sample (``evaluate_synthetic``: ``--count`` sets and the public
cases turned by ``--rotations`` angles), the rendered masks of ``evaluate_masks`` and the real point
sets of ``../shared/data``. Per item it keeps the result's JSON without timings; ``--compare``
reports, per suite, how many items are byte-identical and, for the others, whether the curves
have the same structure and the largest coordinate difference. Exit status 1 when any item
differs by more than ``--atol`` (default 1e-12, in the item's units) or changes structure.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = Path(__file__).resolve().parent
for _p in (str(REPO), str(SCRIPTS)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

import torch_isc  # noqa: E402
from torch_isc import images  # noqa: E402

SHARED = REPO.parent / "shared"


def _item_json(res) -> Dict[str, Any]:
    d = res.to_json_dict()
    for lev in d["stats"]["levels"]:
        lev.pop("seconds", None)
        lev.pop("stage_seconds", None)
    return d


def suite_cases() -> Dict[str, Any]:
    import evaluate_cases as ev
    cases = ev.load_cases(SHARED / "cases", None)
    res = torch_isc.reconstruct_batch([torch.as_tensor(c["points"]) for c in cases], names=[c["name"] for c in cases])
    return {c["name"]: _item_json(r) for c, r in zip(cases, res)}


def suite_synthetic(count: int, rotations: int) -> Dict[str, Any]:
    import evaluate_synthetic as es
    rng = np.random.default_rng(0)
    cases = [es.make_case(i, es.KINDS, rng) for i in range(count)]
    cases += es.rotated_public(SHARED / "cases", rotations)
    res = torch_isc.reconstruct_batch([torch.as_tensor(c["points"]) for c in cases])
    return {c["name"]: _item_json(r) for c, r in zip(cases, res)}


def suite_masks() -> Dict[str, Any]:
    import evaluate_masks as em
    shapes = em.load_truths(SHARED / "cases")
    masks = []
    for s in shapes:
        px = em.to_pixels([np.asarray(c, np.float64) for c in s["truth"]["curves"]], 256)
        masks.append(em.render(px, 256, 16, False))
    res = images.reconstruct_masks(masks, images.image_config(), names=[s["name"] for s in shapes])
    return {s["name"]: _item_json(r) for s, r in zip(shapes, res)}


def suite_data() -> Dict[str, Any]:
    import run_data as rd
    root = SHARED / "data"
    files = rd.find_files(root, None)
    names, sets = [], []
    for f in files:
        names.append(f.relative_to(root).with_suffix("").as_posix())
        sets.append(torch.as_tensor(torch_isc.io.read_points(f)))
    res = torch_isc.reconstruct_batch(sets, names=names)
    return {n: _item_json(r) for n, r in zip(names, res)}


def _max_diff(a: Any, b: Any) -> float:
    """Largest absolute difference of two JSON trees of the same structure; inf otherwise."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return float("inf")
        return max([_max_diff(a[k], b[k]) for k in a] + [0.0])
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return float("inf")
        return max([_max_diff(x, y) for x, y in zip(a, b)] + [0.0])
    if isinstance(a, bool) or isinstance(b, bool) or a is None or b is None or isinstance(a, str):
        return 0.0 if a == b else float("inf")
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        if a == b:
            return 0.0
        return abs(float(a) - float(b))
    return 0.0 if a == b else float("inf")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--record", metavar="DIR")
    g.add_argument("--compare", metavar="DIR")
    ap.add_argument("--suites", default="cases,synthetic,masks,data")
    ap.add_argument("--count", type=int, default=440, help="generated sets (default 440)")
    ap.add_argument("--rotations", type=int, default=2, help="angles for the public cases (default 2)")
    ap.add_argument("--atol", type=float, default=1e-12)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    runs = {"cases": suite_cases, "synthetic": lambda: suite_synthetic(args.count, args.rotations),
            "masks": suite_masks, "data": suite_data}
    bad = 0
    for name in args.suites.split(","):
        t0 = time.perf_counter()
        got = runs[name]()
        secs = time.perf_counter() - t0
        if args.record:
            d = Path(args.record)
            d.mkdir(parents=True, exist_ok=True)
            (d / f"{name}.json").write_text(json.dumps(got, sort_keys=True))
            print(f"{name}: {len(got)} item(s) recorded ({secs:.1f} s)")
            continue
        ref = json.loads((Path(args.compare) / f"{name}.json").read_text())
        got = json.loads(json.dumps(got, sort_keys=True))
        same = sum(1 for k in ref if k in got and json.dumps(ref[k]) == json.dumps(got[k]))
        worst, wname = 0.0, None
        for k in ref:
            d = _max_diff(ref[k], got.get(k))
            if d > worst:
                worst, wname = d, k
        ok = set(ref) == set(got) and worst <= args.atol
        bad += not ok
        print(f"{name}: {same}/{len(ref)} identical; largest difference {worst:.3g}"
              + (f" ({wname})" if wname else "") + ("" if ok else "  <-- DIFFERS") + f" ({secs:.1f} s)")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
