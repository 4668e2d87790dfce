"""Command line: ``torch-isc reconstruct INPUT... [options]`` (also ``python -m torch_isc``).

For each input point file it writes ``OUT/<stem>.json`` (polylines, component count, bbox,
per-level stats), ``.npz`` (the implicit curve, lossless), ``.svg`` (the curve) and ``.png``
(points, mesh, signs, curve), and prints one summary line on stdout::

    circle: 1 closed, 0 open, 4 levels, converged, 0.84 s

(the time is the reconstruction's wall time; inputs reconstructed in one batch share it evenly).

Image inputs (png, jpg, tif, bmp) are read as masks (``--mode mask``, default: boundary points
on the pixel cracks, vertex signs from the mask) or as grayscale images whose Canny edges are
the points (``--mode edges``, topology estimated); their coordinates are pixels (x right, y
down, pixel (0, 0) covering [0,1]x[0,1]), the settings are those of
:func:`torch_isc.images.image_config` unless the config sets them, and they also get
``<stem>.overlay.png`` (the curve over the image) and, by default, ``<stem>.contours.npz``
(OpenCV contours with their hierarchy). A folder INPUT stands for its point and image files,
sorted by name.

Inputs go through :func:`torch_isc.reconstruct_batch` in batches of ``--batch-size``, read only
when their batch fills (bounded memory, a folder of any size streams through); a batch that
raises is retried item by item so one bad input cannot sink the others.

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

from torch_isc.pipeline.config import ConfigError, load_config, parse_overrides
from torch_isc.images import IMAGE_SUFFIXES
from torch_isc.io import PointFileError, chosen_formats, export, read_points

#: Suffixes of point files picked up from a folder INPUT (any file given by name is tried).
POINT_SUFFIXES = (".xy", ".txt", ".csv", ".npy")
DEFAULT_IMAGE_FORMATS = "json,npz,svg,png,contours.npz"

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
    image: Optional[object] = None   # gray (H, W) float32 in [0, 1] for an image input, while in its batch
    mask: Optional[torch.Tensor] = None
    n_boundaries: Optional[int] = None

    @property
    def is_image(self) -> bool:
        return Path(self.source).suffix.lower() in IMAGE_SUFFIXES


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
        "reconstruct", help="reconstruct curves from point files or images",
        description="Reconstruct one curve set per input: a point file (text rows 'x y' or 'x,y', '#' comments, "
                    "an optional header line; or a .npy array of shape (N, 2)), an image (png, jpg, tif, bmp: a "
                    "mask, or a grayscale image with --mode edges), or a folder of such files. Image coordinates "
                    "are pixels: x right, y down, pixel (0, 0) covering [0,1]x[0,1].",
        epilog="exit status: 0 all done, 1 some inputs failed, 2 usage or configuration error")
    rec.add_argument("inputs", nargs="*", metavar="INPUT",
                     help="point files (.xy/.txt/.csv text, or .npy), images (.png/.jpg/.tif/.bmp), or folders of them")
    rec.add_argument("--config", metavar="FILE", help="YAML file of ReconstructConfig keys (see configs/default.yaml)")
    rec.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override one config key, e.g. --set max_level=6 (repeatable; applied after --config)")
    rec.add_argument("--out", default="out", metavar="DIR", help="output folder, created if needed (default: out)")
    rec.add_argument("--seed", type=int, metavar="N", help="random seed (sets config.seed)")
    rec.add_argument("--batch-size", type=int, default=64, metavar="N",
                     help="point sets reconstructed together (default: 64)")
    rec.add_argument("--formats", default=None, metavar="LIST",
                     help=f"comma-separated output formats among {', '.join(chosen_formats())} (default: {DEFAULT_FORMATS}; "
                          f"for images {DEFAULT_IMAGE_FORMATS}, and always overlay.png)")
    img = rec.add_argument_group("images")
    img.add_argument("--mode", choices=("mask", "edges"), default="mask",
                     help="mask: the image is a binary mask, its foreground boundary is the curve, and the mask "
                          "gives inside/outside (default); edges: kornia Canny edges of the grayscale image are the "
                          "points, topology estimated")
    img.add_argument("--threshold", type=float, default=None, metavar="T",
                     help="mask mode: foreground is gray > T, gray in [0, 1] (default: midway between the two levels "
                          "of a two-level image, else 0.5)")
    img.add_argument("--spacing", type=float, default=1.0, metavar="PX",
                     help="distance in pixels between boundary points along a contour (default: 1)")
    img.add_argument("--no-oracle", action="store_true",
                     help="mask mode: estimate the topology from the points instead of reading it from the mask")
    img.add_argument("--canny", default="0.1,0.2", metavar="LOW,HIGH",
                     help="edges mode: Canny hysteresis thresholds on the gradient of the image in [0, 1] "
                          "(default: 0.1,0.2)")
    img.add_argument("--sigma", type=float, default=1.0, help="edges mode: Gaussian smoothing in pixels (default: 1)")
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
    known = chosen_formats()
    unknown = [f for f in formats if f not in known]
    if unknown:
        raise UsageError(f"--formats: unknown format '{unknown[0]}' (known: {', '.join(known)})")
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


def _expand_inputs(sources: Sequence[str]) -> List[str]:
    """A folder stands for its point and image files (by suffix, sorted by name, not recursive);
    anything else is kept as given (a missing file is reported when it is read). An empty
    folder is a usage error."""
    out: List[str] = []
    for src in sources:
        p = Path(src)
        if p.is_dir():
            files = sorted(str(f) for f in p.iterdir()
                           if f.is_file() and f.suffix.lower() in POINT_SUFFIXES + IMAGE_SUFFIXES)
            if not files:
                raise UsageError(f"{src}: folder has no point or image file "
                                 f"({', '.join(POINT_SUFFIXES + IMAGE_SUFFIXES)})")
            out.extend(files)
        else:
            out.append(str(src))
    return out


def _config_keys(path: Optional[str]) -> List[str]:
    """The keys a config file sets (already validated by load_config)."""
    if path is None:
        return []
    import yaml

    try:
        d = yaml.safe_load(Path(path).read_text())
    except Exception:
        return []
    return list(d) if isinstance(d, dict) else []


def _bar(done: int, total: int, t0: float, width: int = 24) -> str:
    frac = done / total if total else 1.0
    fill = int(round(width * frac))
    rate = done / max(time.perf_counter() - t0, 1e-9)
    eta = (total - done) / rate if rate > 0 and done else float("nan")
    eta_s = "--:--" if eta != eta else f"{int(eta) // 60:02d}:{int(eta) % 60:02d}"
    return f"|{'#' * fill}{'.' * (width - fill)}| {100 * frac:3.0f}% {rate:.1f}/s ETA {eta_s}"


def _summary(job: _Job, result, seconds: float) -> str:
    levels = len(result.stats or [])
    state = "converged" if result.converged else f"not converged ({result.limit or 'tolerance not met'})"
    beyond = int((result.stats or [{}])[-1].get("points_beyond_tolerance", 0))
    if beyond:
        state += f", {beyond} point(s) beyond tolerance"
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
    formats = _parse_formats(args.formats if args.formats is not None else DEFAULT_FORMATS)
    image_formats = _parse_formats(args.formats if args.formats is not None else DEFAULT_IMAGE_FORMATS)
    overrides = parse_overrides(args.overrides)
    if args.seed is not None:
        overrides["seed"] = args.seed
    config = load_config(args.config, overrides)
    if args.threshold is not None and not (0.0 <= args.threshold < 1.0):
        raise UsageError(f"--threshold must be in [0, 1), got {args.threshold}")
    if not args.spacing >= 0 or args.spacing != args.spacing:
        raise UsageError(f"--spacing must be >= 0, got {args.spacing}")
    try:
        low, high = (float(v) for v in args.canny.split(","))
    except ValueError:
        raise UsageError(f"--canny expects LOW,HIGH (two numbers), got {args.canny!r}") from None
    if not 0 < low < high:
        raise UsageError(f"--canny: expected 0 < LOW < HIGH, got {args.canny!r}")
    if not args.sigma > 0:
        raise UsageError(f"--sigma must be > 0, got {args.sigma}")
    try:
        device = torch.device(args.device)
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError) as e:
        raise UsageError(f"--device {args.device}: {_one_line(e)}") from None
    sources = _expand_inputs([str(s) for s in args.inputs])
    if args.example:
        sources.append(str(EXAMPLE_PATH))
    if not sources:
        raise UsageError("no INPUT given (give point files, images, folders, or --example)")
    out_dir = Path(args.out)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"--out {out_dir}: cannot create the output folder ({e.strerror or e})") from None
    if not out_dir.is_dir():
        raise UsageError(f"--out {out_dir}: not a folder")

    jobs = [_Job(src, stem) for src, stem in zip(sources, _unique_stems(sources))]
    opts = _Options(args, formats, image_formats, config, low, high)

    # ---- skip finished inputs
    todo: List[_Job] = []
    for job in jobs:
        if not args.overwrite and all((out_dir / f"{job.stem}.{f}").exists() for f in opts.formats_of(job)):
            print(f"{job.stem}: skipped, outputs exist in {out_dir} (use --overwrite to redo)", flush=True)
        else:
            todo.append(job)

    # ---- read inputs as batches fill up (bounded memory), reconstruct, export at once
    state = {"failed": 0, "done": 0, "batches": 0, "t0": time.perf_counter()}
    batch: List[_Job] = []
    for i, job in enumerate(todo):
        try:
            _read(job, opts, device)
            batch.append(job)
        except _input_errors() as e:
            _err(_one_line(e))             # the message already starts with the file name
            state["failed"] += 1
            state["done"] += 1
        if len(batch) == args.batch_size or (i == len(todo) - 1 and batch):
            _process_batch(batch, opts, out_dir, len(todo), state, args.debug)
            batch = []
    failed = state["failed"]
    if state["batches"] > 1 or failed:
        _note(f"done: {len(jobs) - failed} of {len(jobs)} input(s) ok, {failed} failed")
    return 1 if failed else 0


class _Options:
    """What the command line asks for, resolved once."""

    def __init__(self, args, formats, image_formats, config, low, high):
        from torch_isc import images

        self.args = args
        self.formats = formats
        self.image_formats = image_formats
        self.config = config
        # pixel defaults for images, except where the user set a key
        keep = set(_config_keys(args.config)) | {k for k in parse_overrides(args.overrides)}
        self.image_config = images.image_config(config, keep=sorted(keep), mode=args.mode)
        self.canny = (low, high)

    def formats_of(self, job: _Job) -> List[str]:
        return self.image_formats + ["overlay.png"] if job.is_image else self.formats


def _input_errors() -> tuple:
    from torch_isc.images import ImageError

    return (PointFileError, ImageError)


def _read(job: _Job, opts: _Options, device) -> None:
    """Read one input into its job: points, and for an image the gray image (and the mask)."""
    if not job.is_image:
        job.points = torch.from_numpy(read_points(job.source)).to(device)
        return
    from torch_isc import images

    gray = images.read_image(job.source)
    job.image = gray
    if opts.args.mode == "mask":
        thr = opts.args.threshold if opts.args.threshold is not None else images.auto_threshold(gray)
        mask = torch.from_numpy(gray > thr).to(device)
        if not bool(mask.any()):
            raise images.ImageError(f"{job.source}: empty mask: no pixel above threshold {thr:.3g} (all black)")
        if bool(mask.all()):
            _note(f"note: {job.source}: the whole image is foreground (all white at threshold {thr:.3g}): "
                  f"its curve is the image frame")
        job.points, job.n_boundaries = images.mask_points(mask, opts.args.spacing, None, name=job.source)
        job.points = job.points.double()
        job.mask = mask
    else:
        pts = images.edge_points([torch.from_numpy(gray).to(device)], opts.canny[0], opts.canny[1],
                                 sigma=opts.args.sigma, spacing=opts.args.spacing)[0]
        if pts.shape[0] < 3:
            raise images.ImageError(f"{job.source}: no edges found ({pts.shape[0]} edge pixel(s) at Canny thresholds "
                                    f"{opts.canny[0]:g},{opts.canny[1]:g}; flat image?)")
        job.points = pts.double()


def _process_batch(batch: List[_Job], opts: _Options, out_dir: Path, total: int, state: dict,
                   debug: bool) -> None:
    state["batches"] += 1
    if total > 1:
        _note(f"[{state['done']}/{total}] batch {state['batches']}: reconstructing {len(batch)} input(s) "
              f"{_bar(state['done'], total, state['t0'])}")
    masks = [j for j in batch if j.is_image and j.mask is not None and not opts.args.no_oracle]
    others = [j for j in batch if j not in masks]
    solved = {}
    for group, kind in ((others, "plain"), (masks, "mask")):
        if group:
            solved.update(zip(map(id, group), _run_batch(group, opts, debug, kind)))
    for job in batch:
        res, seconds = solved[id(job)]
        state["done"] += 1
        image = job.image
        job.points = job.image = job.mask = None             # free the batch's inputs
        if res is None:
            state["failed"] += 1
            continue
        try:
            fmts = opts.formats_of(job)
            job.outputs = export(res, out_dir / job.stem, [f for f in fmts if f != "overlay.png"],
                                 y_down=job.is_image)
            if job.is_image:
                from torch_isc.io import write_overlay

                job.outputs.append(write_overlay(out_dir / f"{job.stem}.overlay.png", image, res))
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
    if total > 1 and state["done"] == total:
        _note(f"[{state['done']}/{total}] {_bar(state['done'], total, state['t0'])}")


def _solve(jobs: List[_Job], opts: _Options, kind: str) -> list:
    """One batched solve: point files with the user's config, images with the pixel config,
    masks with the mask as sign oracle (and the count check of :func:`images.solve_masks`)."""
    names = [j.stem for j in jobs]
    points = [j.points for j in jobs]
    if kind == "mask":
        from torch_isc.images import solve_masks

        return solve_masks(points, [j.mask for j in jobs], [j.n_boundaries for j in jobs], opts.image_config,
                           names)
    if all(not j.is_image for j in jobs):
        if len(jobs) == 1:
            return [torch_isc.reconstruct(points[0], opts.config, name=names[0])]
        return torch_isc.reconstruct_batch(points, opts.config, names=names)
    cfgs = [opts.image_config if j.is_image else opts.config for j in jobs]
    if any(c is not cfgs[0] for c in cfgs):         # images and point files: one solve per config
        out = [None] * len(jobs)
        for cfg in (opts.config, opts.image_config):
            idx = [i for i, c in enumerate(cfgs) if c is cfg]
            if idx:
                for i, r in zip(idx, torch_isc.reconstruct_batch([points[i] for i in idx], cfg,
                                                                 names=[names[i] for i in idx])):
                    out[i] = r
        return out
    return torch_isc.reconstruct_batch(points, cfgs[0], names=names)


def _run_batch(batch: List[_Job], opts: _Options, debug: bool, kind: str = "plain") -> list:
    """``(result, seconds)`` per item of one batch; ``(None, seconds)`` for an item that failed
    (its error printed). Items solved together share the batch's wall time evenly."""
    if len(batch) > 1:
        t0 = time.perf_counter()
        try:
            results = _solve(batch, opts, kind)
            if len(results) == len(batch):
                share = (time.perf_counter() - t0) / len(batch)
                return [(r, share) for r in results]
        except Exception:
            pass  # find the item(s) at fault by running them one by one
    bad_input = _point_set_errors() + _input_errors()
    out = []
    for job in batch:
        t0 = time.perf_counter()
        res = None
        try:
            res = _solve([job], opts, kind)[0]
        except bad_input as e:
            msg = _one_line(e)
            if msg.startswith(f"{job.stem}: "):     # a PointSetError names the item by its stem
                msg = msg[len(job.stem) + 2:]
            _err(f"{job.source}: {msg}")
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
