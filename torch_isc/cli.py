"""Command line: ``torch-isc reconstruct INPUT... [options]`` (also ``python -m torch_isc``).

For each input point file it writes ``OUT/<stem>.json`` (polylines, component count, bbox,
per-level stats), ``.npz`` (the implicit curve, lossless), ``.svg`` (the curve) and ``.png``
(points, mesh, signs, curve), and prints one summary line on stdout::

    circle: 1 closed, 0 open, 4 levels, converged, 0.84 s

(the time is the reconstruction's wall time; inputs reconstructed in one batch share it evenly).

Inputs go through :func:`torch_isc.reconstruct_batch` in batches of ``--batch-size``; a batch
that raises is retried item by item so one bad point set cannot sink the others.

Exit status: 0 every input done (or skipped because its outputs exist), 1 some inputs failed
(each with one ``torch-isc: error: <file>: <problem>`` line on stderr), 2 usage or
configuration error (nothing was reconstructed). A user mistake never prints a traceback;
``--debug`` shows the traceback of an unexpected internal error.
"""
from __future__ import annotations

import argparse
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence, TextIO

import torch

import torch_isc

from .config import ConfigError, load_config, parse_overrides
from .io import EXPORTERS, PointFileError, export, read_points

__all__ = ["main", "build_parser", "EXAMPLE_PATH"]

PROG = "torch-isc"
#: The built-in example of ``--example`` (made by ``data/make_example.py``).
EXAMPLE_PATH = Path(__file__).resolve().parent / "data" / "nested.xy"
DEFAULT_FORMATS = "json,npz,svg,png"


class UsageError(Exception):
    """A mistake in the command line or the config: exit status 2."""


@dataclass
class _Job:
    source: str                      # the input as given (for messages)
    stem: str                        # output name, unique within the run
    points: Optional[torch.Tensor] = None
    failed: bool = False
    outputs: List[Path] = field(default_factory=list)


# ============================================================================ parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Reconstruct 2D curves of unknown topology from unorganized points as implicit "
                    "simplicial curves (Taubin & Ronfard 1996).")
    parser.add_argument("--version", action="version", version=f"%(prog)s {torch_isc.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    rec = sub.add_parser(
        "reconstruct", help="reconstruct curves from point files",
        description="Reconstruct one curve set per input point file (text rows 'x y' or 'x,y', '#' comments, "
                    "an optional header line; or a .npy array of shape (N, 2)).",
        epilog="exit status: 0 all done, 1 some inputs failed, 2 usage or configuration error")
    rec.add_argument("inputs", nargs="*", metavar="INPUT", help="point files (.xy/.txt/.csv text, or .npy)")
    rec.add_argument("--config", metavar="FILE", help="YAML file of ReconstructConfig keys (see configs/default.yaml)")
    rec.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override one config key, e.g. --set max_level=6 (repeatable; applied after --config)")
    rec.add_argument("--out", default="out", metavar="DIR", help="output folder, created if needed (default: out)")
    rec.add_argument("--seed", type=int, metavar="N", help="random seed (sets config.seed)")
    rec.add_argument("--batch-size", type=int, default=64, metavar="N",
                     help="point sets reconstructed together (default: 64)")
    rec.add_argument("--formats", default=DEFAULT_FORMATS, metavar="LIST",
                     help=f"comma-separated output formats among {', '.join(EXPORTERS)} (default: {DEFAULT_FORMATS})")
    rec.add_argument("--device", default="cpu", help="torch device for the reconstruction (default: cpu)")
    rec.add_argument("--overwrite", action="store_true",
                     help="redo inputs whose outputs all exist (by default they are skipped)")
    rec.add_argument("--example", action="store_true",
                     help="also reconstruct the built-in example (4 nested closed curves); no INPUT needed")
    rec.add_argument("--debug", action="store_true", help="print the traceback of an unexpected internal error")
    return parser


# ============================================================================ helpers
def _err(msg: str, stream: Optional[TextIO] = None) -> None:
    print(f"{PROG}: error: {msg}", file=stream or sys.stderr, flush=True)


def _note(msg: str) -> None:
    print(f"{PROG}: {msg}", file=sys.stderr, flush=True)


def _one_line(e: BaseException) -> str:
    lines = str(e).strip().splitlines()
    return lines[0] if lines else type(e).__name__


def _parse_formats(text: str) -> List[str]:
    formats = [f.strip().lower().lstrip(".") for f in text.split(",") if f.strip()]
    if not formats:
        raise UsageError("--formats: no format given")
    unknown = [f for f in formats if f not in EXPORTERS]
    if unknown:
        raise UsageError(f"--formats: unknown format '{unknown[0]}' (known: {', '.join(EXPORTERS)})")
    return list(dict.fromkeys(formats))          # drop repeats, keep order


def _unique_stems(sources: Sequence[str]) -> List[str]:
    """Output stems: the file stem, with ``_2``, ``_3``... appended to a repeated one (also
    avoiding the plain stems of other inputs). Deterministic for the same input order, so a
    rerun finds the same outputs."""
    plain = [Path(s).stem or "input" for s in sources]
    taken = set(plain)
    used: set = set()
    out = []
    for src, stem in zip(sources, plain):
        name = stem
        if name in used:
            k = 2
            while f"{stem}_{k}" in used or f"{stem}_{k}" in taken:
                k += 1
            name = f"{stem}_{k}"
            _note(f"note: another input is also named '{stem}': {src} is written as '{name}'")
        used.add(name)
        out.append(name)
    return out


def _summary(job: _Job, result, seconds: float) -> str:
    levels = len(result.stats or [])
    state = "converged" if result.converged else f"not converged ({result.limit or 'tolerance not met'})"
    return (f"{job.stem}: {result.num_closed} closed, {result.num_open} open, {levels} levels, "
            f"{state}, {seconds:.2f} s")


def _point_set_errors() -> tuple:
    pse = getattr(torch_isc, "PointSetError", None)
    return (pse, ValueError) if isinstance(pse, type) else (ValueError,)


# ============================================================================ command
def _reconstruct_command(args: argparse.Namespace) -> int:
    # ---- everything that can be a usage error is checked before any work
    if args.batch_size < 1:
        raise UsageError(f"--batch-size must be >= 1, got {args.batch_size}")
    formats = _parse_formats(args.formats)
    overrides = parse_overrides(args.overrides)
    if args.seed is not None:
        overrides["seed"] = args.seed
    config = load_config(args.config, overrides)
    try:
        device = torch.device(args.device)
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError) as e:
        raise UsageError(f"--device {args.device}: {_one_line(e)}") from None
    sources = [str(s) for s in args.inputs]
    if args.example:
        sources.append(str(EXAMPLE_PATH))
    if not sources:
        raise UsageError("no INPUT given (give point files, or --example)")
    out_dir = Path(args.out)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"--out {out_dir}: cannot create the output folder ({e.strerror or e})") from None
    if not out_dir.is_dir():
        raise UsageError(f"--out {out_dir}: not a folder")

    jobs = [_Job(src, stem) for src, stem in zip(sources, _unique_stems(sources))]
    failed = 0

    # ---- skip finished inputs
    todo: List[_Job] = []
    for job in jobs:
        if not args.overwrite and all((out_dir / f"{job.stem}.{f}").exists() for f in formats):
            print(f"{job.stem}: skipped, outputs exist in {out_dir} (use --overwrite to redo)", flush=True)
        else:
            todo.append(job)

    # ---- read inputs as batches fill up (bounded memory), reconstruct, export at once
    state = {"failed": 0, "done": 0, "batches": 0}
    batch: List[_Job] = []
    for i, job in enumerate(todo):
        try:
            job.points = torch.from_numpy(read_points(job.source)).to(device)
            batch.append(job)
        except PointFileError as e:
            _err(_one_line(e))             # the message already starts with the file name
            state["failed"] += 1
            state["done"] += 1
        if len(batch) == args.batch_size or (i == len(todo) - 1 and batch):
            _process_batch(batch, config, out_dir, formats, len(todo), state, args.debug)
            batch = []
    failed = state["failed"]
    if state["batches"] > 1 or failed:
        _note(f"done: {len(jobs) - failed} of {len(jobs)} input(s) ok, {failed} failed")
    return 1 if failed else 0


def _process_batch(batch: List[_Job], config, out_dir: Path, formats: List[str], total: int, state: dict,
                   debug: bool) -> None:
    state["batches"] += 1
    if total > 1:
        _note(f"[{state['done']}/{total}] batch {state['batches']}: reconstructing {len(batch)} input(s)")
    for job, (res, seconds) in zip(batch, _run_batch(batch, config, debug)):
        state["done"] += 1
        job.points = None                  # free the batch's points
        if res is None:
            state["failed"] += 1
            continue
        try:
            job.outputs = export(res, out_dir / job.stem, formats)
        except OSError as e:
            _err(f"{job.source}: cannot write outputs in {out_dir} ({e.strerror or _one_line(e)})")
            state["failed"] += 1
            continue
        except Exception as e:  # an exporter bug: report it as one line, keep going
            _err(f"{job.source}: writing outputs failed ({type(e).__name__}: {_one_line(e)})")
            if debug:
                traceback.print_exc()
            state["failed"] += 1
            continue
        print(_summary(job, res, seconds), flush=True)


def _run_batch(batch: List[_Job], config, debug: bool) -> list:
    """``(result, seconds)`` per item of one batch; ``(None, seconds)`` for an item that failed
    (its error printed). Items solved together share the batch's wall time evenly."""
    names = [j.stem for j in batch]
    points = [j.points for j in batch]
    if len(batch) > 1:
        t0 = time.perf_counter()
        try:
            results = torch_isc.reconstruct_batch(points, config, names=names)
            if len(results) == len(batch):
                share = (time.perf_counter() - t0) / len(batch)
                return [(r, share) for r in results]
        except Exception:
            pass  # find the item(s) at fault by running them one by one
    bad_input = _point_set_errors()
    out = []
    for job in batch:
        t0 = time.perf_counter()
        res = None
        try:
            res = torch_isc.reconstruct(job.points, config, name=job.stem)
        except bad_input as e:
            _err(f"{job.source}: {_one_line(e)}")
        except Exception as e:
            _err(f"{job.source}: reconstruction failed ({type(e).__name__}: {_one_line(e)})")
            if debug:
                traceback.print_exc()
        out.append((res, time.perf_counter() - t0))
    return out


# ============================================================================ entry point
def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the command line; returns the exit status (0 ok, 1 some inputs failed, 2 usage)."""
    parser = build_parser()
    try:
        args = parser.parse_args(list(argv) if argv is not None else None)
    except SystemExit as e:              # argparse: --help / --version (0) or a usage error (2)
        return int(e.code) if isinstance(e.code, int) else (0 if e.code is None else 2)
    try:
        if args.command == "reconstruct":
            return _reconstruct_command(args)
        parser.error(f"unknown command {args.command!r}")  # pragma: no cover
    except (UsageError, ConfigError) as e:
        _err(_one_line(e))
        return 2
    except KeyboardInterrupt:
        _err("interrupted")
        return 130
    return 2  # pragma: no cover


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
