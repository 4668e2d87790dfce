"""Command line: ``torch-isc reconstruct INPUT... [options]`` (also ``python -m torch_isc``).

For each input point file it writes ``OUT/<stem>.json`` (polylines, component count, bbox,
per-level stats), ``.npz`` (the implicit curve, lossless), ``.svg`` (the curve) and ``.png``
(points, mesh, signs, curve), and prints one summary line on stdout::

    circle: 1 closed, 0 open, 4 levels, converged, 0.84 s

(the time is the reconstruction's wall time; inputs reconstructed in one batch share it evenly).

Image inputs (png, jpg, tif, bmp, gif, webp) are read as masks (``--mode mask``, default: boundary points
on the pixel cracks, vertex signs from the mask) or as grayscale images whose Canny edges are
the points (``--mode edges``, topology estimated); their coordinates are pixels (x right, y
down, pixel (0, 0) covering [0,1]x[0,1]), the settings are those of
:func:`torch_isc.images.image_config` unless the config sets them, and they also get
``<stem>.overlay.png`` (the curve over the image) and, by default, ``<stem>.contours.npz``
(OpenCV contours with their hierarchy). ``--zoom N`` and ``--region X0,Y0,X1,Y1`` draw the
overlay of that part of the image at that zoom (pixels as NxN blocks under the sub-pixel curve).
A folder INPUT stands for its point and image files, sorted by name.

Inputs go through :func:`torch_isc.reconstruct_batch` in batches of ``--batch-size``, read only
when their batch fills (bounded memory, a folder of any size streams through); a batch that
raises is retried item by item so one bad input cannot sink the others. The progress bar on
stderr advances once per input as soon as it is final (in place on a terminal).

Each input's outputs end with ``OUT/<stem>.manifest.json`` (written last: the sha256 of the input,
of the config and of every output file); a rerun skips an input only when its manifest matches,
and redoes it otherwise. Two inputs with the same stem are written as ``<stem>_<suffix>``
(``a.xy`` -> ``a_xy``), whatever their order; images larger than ``--max-pixels`` (from the
header, before decoding) are refused.

Datasets (:mod:`torch_isc.dataset`): an INPUT may also be a glob (``'scans/**/*.png'``, sorted) or a
``.parquet`` manifest, ``--manifest FILE`` adds the paths of a text/CSV/Parquet manifest,
``--table out.parquet`` writes the results table (a row per input), and ``--engine ray`` runs the
batches on a Ray cluster (``--address``; default a local one) in ``--actors`` solver actors, each
with ``--cpus-per-actor`` CPUs and ``--gpus-per-actor`` GPUs; the outputs are the same bytes. A
progress bar (tqdm, on stderr) shows on a terminal; elsewhere each batch is one log line.

Exit status: 0 every input done (or skipped because its complete outputs exist), 1 some inputs failed
(each with one ``torch-isc: error: <file>: <problem>`` line on stderr) or an internal error stopped the
run (one ``internal error`` line; ``--debug`` re-raises it), 2 usage or
configuration error (nothing was reconstructed), 130 interrupted (SIGINT), 143 terminated (SIGTERM);
a stopped run leaves only complete output sets (the one being written has no manifest and is redone). A user mistake never prints a traceback;
``--debug`` shows the traceback of an unexpected internal error.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import List, Optional, Sequence, TextIO

import torch

import torch_isc

from torch_isc._helpers import one_line
from torch_isc.io import chosen_formats
from torch_isc.pipeline.knobs import non_ascii_digit
from torch_isc.pipeline.config import ConfigError, flat_keys, load_config, parse_overrides, read_config_mapping
from torch_isc.images.read import DEFAULT_MAX_PIXELS
from torch_isc.runner import DEFAULT_MAX_BOUNDARY, MAX_BATCH_SIZE, ImageOptions, Record, RunError, run_inputs, shown, unique_stems

DEFAULT_IMAGE_FORMATS = "json,contours.npz"

__all__ = ["main", "build_parser", "EXAMPLE_PATH"]

PROG = "torch-isc"
#: The built-in example of ``--example`` (made by ``data/make_example.py``).
EXAMPLE_PATH = Path(__file__).resolve().parent / "data" / "nested.xy"
DEFAULT_FORMATS = "json,npz,svg,png"


class UsageError(Exception):
    """A mistake in the command line or the config: exit status 2."""


# ============================================================================ parser
def _number(kind: type):
    """An argparse type: ``int`` or ``float`` of ASCII text only (Python reads Arabic-Indic and
    full-width digits; the config, the point files and other tools refuse them)."""
    def parse(text: str):
        ch = non_ascii_digit(text)
        if ch is not None:
            raise argparse.ArgumentTypeError(f"non-ASCII digit {ch!r} (U+{ord(ch):04X}) in {text!r}; "
                                             f"write numbers with the digits 0-9")
        if "_" in text:                  # Python reads 4_0 as 40; the config and the point files refuse it
            raise argparse.ArgumentTypeError(f"invalid {kind.__name__} value: {text!r} (no _ in numbers)")
        try:
            return kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid {kind.__name__} value: {text!r}") from None
    parse.__name__ = kind.__name__
    return parse


_INT, _FLOAT = _number(int), _number(float)


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
        description="Reconstruct one curve set per input: a point file (text rows 'x y', 'x,y' or 'x;y', '#' comments, "
                    "an optional header line; or a .npy array of shape (N, 2)), an image (png, jpg, tif, bmp, gif, webp: a "
                    "mask, or a grayscale image with --mode edges), or a folder of such files. Image coordinates "
                    "are pixels: x right, y down, pixel (0, 0) covering [0,1]x[0,1].",
        epilog="exit status: 0 all done, 1 some inputs failed (or an internal error), 2 usage or configuration error, "
               "130 interrupted, 143 terminated (SIGTERM)")
    rec.add_argument("inputs", nargs="*", metavar="INPUT",
                     help="point files (.xy/.txt/.csv text, or .npy), images (.png/.jpg/.tif/.bmp/.gif/.webp), or folders of them")
    rec.add_argument("--config", metavar="FILE", help="YAML file of ReconstructConfig keys (see configs/default.yaml)")
    rec.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override one config key, e.g. --set max_level=6 (repeatable; applied after --config)")
    rec.add_argument("--out", default="out", metavar="DIR", help="output folder, created if needed (default: out)")
    rec.add_argument("--seed", type=_INT, metavar="N", help="random seed (sets config.seed)")
    rec.add_argument("--batch-size", type=_INT, default=64, metavar="N",
                     help="point sets reconstructed together (default: 64)")
    rec.add_argument("--formats", default=None, metavar="LIST",
                     help=f"comma-separated output formats among {', '.join(chosen_formats())} (default: {DEFAULT_FORMATS}; "
                          f"for images {DEFAULT_IMAGE_FORMATS}; overlay.png on request)")
    img = rec.add_argument_group("images")
    img.add_argument("--mode", choices=("mask", "edges"), default="mask",
                     help="mask: the image is a binary mask, its foreground boundary is the curve, and the mask "
                          "gives inside/outside (default); edges: kornia Canny edges of the grayscale image are the "
                          "points, topology estimated")
    img.add_argument("--threshold", type=_FLOAT, default=None, metavar="T",
                     help="mask mode: foreground is gray > T, gray in [0, 1] (default: midway between the two levels "
                          "of a two-level image, else 0.5)")
    img.add_argument("--spacing", type=_FLOAT, default=1.0, metavar="PX",
                     help="distance in pixels between boundary points along a contour, for --no-oracle and "
                          "--mode edges (mask mode traces the pixel grid itself; default: 1)")
    img.add_argument("--no-oracle", action="store_true",
                     help="mask mode: estimate the topology from the points instead of reading it from the mask")
    img.add_argument("--connectivity", type=_INT, choices=(8, 4), default=8,
                     help="mask mode: connectivity of the foreground (8, OpenCV's, default; or 4)")
    img.add_argument("--canny", default="0.1,0.2", metavar="LOW,HIGH",
                     help="edges mode: Canny hysteresis thresholds on the gradient of the image in [0, 1] "
                          "(default: 0.1,0.2)")
    img.add_argument("--sigma", type=_FLOAT, default=1.0, help="edges mode: Gaussian smoothing in pixels (default: 1)")
    img.add_argument("--max-pixels", type=_FLOAT, default=float(DEFAULT_MAX_PIXELS), metavar="N",
                     help=f"the largest image read, in pixels (width x height, from the header, before decoding; "
                          f"default: {DEFAULT_MAX_PIXELS:.0e}; 0: no limit)")
    img.add_argument("--max-boundary", type=_FLOAT, default=float(DEFAULT_MAX_BOUNDARY), metavar="N",
                     help=f"the longest boundary of an image: pixel edges between foreground and background in mask "
                          f"mode, edge points in edges mode; counted before tracing (default: {DEFAULT_MAX_BOUNDARY:.0e}; "
                          f"0: no limit)")
    img.add_argument("--zoom", type=_INT, default=1, metavar="N",
                     help="overlay.png: an integer zoom, each pixel drawn as an NxN block under the sub-pixel curve "
                          "(vertices marked from 8 on), to see sub-pixel defects; adds overlay.png to the image formats")
    img.add_argument("--region", default=None, metavar="X0,Y0,X1,Y1",
                     help="overlay.png: show only this part of the image (pixels, x right, y down, clipped to the "
                          "image; an image it misses is shown whole); adds overlay.png to the image formats")
    rec.add_argument("--device", default="cpu", help="torch device for the reconstruction (default: cpu)")
    rec.add_argument("--overwrite", action="store_true",
                     help="redo inputs whose output set is complete (by default they are skipped; a set is "
                          "complete when its <stem>.manifest.json matches the input, the config and the files)")
    rec.add_argument("--example", action="store_true",
                     help="also reconstruct the built-in example (4 nested closed curves); no INPUT needed")
    rec.add_argument("--debug", action="store_true", help="print the traceback of an unexpected internal error")
    ds = rec.add_argument_group("datasets (torch_isc.dataset)")
    ds.add_argument("--manifest", action="append", default=[], metavar="FILE",
                    help="more inputs: a text file of paths (one a line), or a CSV/Parquet file with a column of "
                         "paths (--manifest-column); relative paths are relative to the manifest (repeatable)")
    ds.add_argument("--manifest-column", default="path", metavar="NAME",
                    help="the column of paths in a CSV/Parquet manifest (default: path)")
    ds.add_argument("--table", metavar="FILE.parquet",
                    help="also write the results table: one Parquet row per input (status, error, counts, "
                         "convergence, levels, seconds, polylines)")
    ds.add_argument("--engine", choices=("local", "ray"), default="local",
                    help="local: this process (default); ray: Ray Data over the inputs, batches solved by a pool "
                         "of actors (pip install 'torch_isc[ray]')")
    ds.add_argument("--address", metavar="ADDR",
                    help="ray: the cluster to use (auto, HOST:6379, ray://HOST:10001); default: start a local one")
    ds.add_argument("--actors", type=_INT, default=2, metavar="N", help="ray: solver actors (default: 2)")
    ds.add_argument("--cpus-per-actor", type=_FLOAT, default=1.0, metavar="C",
                    help="ray: CPUs of each actor, also its torch threads (default: 1)")
    ds.add_argument("--gpus-per-actor", type=_FLOAT, default=0.0, metavar="G",
                    help="ray: GPUs of each actor; an actor given one solves on it (default: 0)")
    return parser


# ============================================================================ helpers
def _err(msg: str, stream: Optional[TextIO] = None) -> None:
    print(f"{PROG}: error: {msg}", file=stream or sys.stderr, flush=True)


def _note(msg: str) -> None:
    print(f"{PROG}: {msg}", file=sys.stderr, flush=True)


def _parse_formats(text: str) -> List[str]:
    formats = [f.strip().lower().lstrip(".") for f in text.split(",") if f.strip()]
    if not formats:
        raise UsageError("--formats: no format given")
    known = chosen_formats() + ["overlay.png"]
    unknown = [f for f in formats if f not in known]
    if unknown:
        raise UsageError(f"--formats: unknown format '{unknown[0]}' (known: {', '.join(known)})")
    return list(dict.fromkeys(formats))          # drop repeats, keep order


def _config_keys(path: Optional[str]) -> List[str]:
    """The keys a config file sets (already validated by load_config)."""
    if path is None:
        return []
    try:
        d = read_config_mapping(path)
    except ConfigError:
        return []
    return flat_keys(d)


class _Progress:
    """One tqdm bar per run on stderr, advanced per input; off when stderr is not a terminal
    (then the batch notes are the log). Lines printed while it shows go through ``tqdm.write``."""

    def __init__(self, total: int):
        self.bar = None
        try:
            from tqdm import tqdm
        except ImportError:  # pragma: no cover - tqdm is a dependency
            return
        bar = tqdm(total=total, unit="input", file=sys.stderr, disable=None, dynamic_ncols=True, leave=True)
        if not bar.disable:
            self.bar, self._write = bar, tqdm.write
        else:
            bar.close()

    @property
    def visible(self) -> bool:
        return self.bar is not None

    def print(self, line: str, file: TextIO) -> None:
        if self.bar is not None:
            self._write(line, file=file)
            file.flush()
        else:
            print(line, file=file, flush=True)

    def advance(self) -> None:
        if self.bar is not None:
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _summary(record: Record) -> str:
    """The stdout line of a done input."""
    r = record.summary
    state = "converged" if r["converged"] else f"not converged ({r['limit'] or 'tolerance not met'})"
    if r["points_beyond_tolerance"]:
        state += f", {r['points_beyond_tolerance']} point(s) beyond tolerance"
    if r.get("count_ok") is False:
        state += f", WARNING: the mask has {r['boundaries']} boundaries"
    return (f"{shown(record.stem)}: {r['num_closed']} closed, {r['num_open']} open, {r['levels']} levels, "
            f"{state}, {r['seconds']:.2f} s")


# ============================================================================ command
def _reconstruct_command(args: argparse.Namespace) -> int:
    # ---- everything that can be a usage error is checked before any work
    for opt, val in (("--out", args.out), ("--config", args.config), ("--table", args.table),
                     ("--manifest-column", args.manifest_column), ("--address", args.address),
                     ("--device", args.device), *(("--manifest", m) for m in args.manifest)):
        if val is not None and not val.strip():      # Path("") is ".": --out "" wrote into the working folder
            raise UsageError(f"{opt}: empty value")
    if not 1 <= args.batch_size <= MAX_BATCH_SIZE:
        raise UsageError(f"--batch-size must be in [1, {MAX_BATCH_SIZE}], got {args.batch_size}")
    formats = _parse_formats(args.formats if args.formats is not None else DEFAULT_FORMATS)
    image_formats = _parse_formats(args.formats if args.formats is not None else DEFAULT_IMAGE_FORMATS)
    overrides = parse_overrides(args.overrides)
    if args.seed is not None:
        overrides["seed"] = args.seed
    config = load_config(args.config, overrides, "--set" if args.overrides else "--seed")
    if args.threshold is not None and not (0.0 <= args.threshold < 1.0):
        raise UsageError(f"--threshold must be in [0, 1), got {args.threshold}")
    if not (args.spacing == 0 or 0.01 <= args.spacing <= 1e6):
        raise UsageError(f"--spacing must be 0 (no resampling) or in [0.01, 1e6] pixels, got {args.spacing}")
    try:
        if non_ascii_digit(args.canny):
            raise ValueError
        low, high = (float(v) for v in args.canny.split(","))
    except ValueError:
        raise UsageError(f"--canny expects LOW,HIGH (two numbers), got {args.canny!r}") from None
    if not 0 < low < high < float("inf"):
        raise UsageError(f"--canny: expected 0 < LOW < HIGH, got {args.canny!r}")
    if not 1e-3 <= args.sigma <= 1e3:
        raise UsageError(f"--sigma must be in [0.001, 1000] (pixels), got {args.sigma}")
    if not 1 <= args.zoom <= 64:
        raise UsageError(f"--zoom must be an integer in [1, 64], got {args.zoom}")
    region = None
    if args.region is not None:
        try:
            if non_ascii_digit(args.region):
                raise ValueError
            region = tuple(int(v) for v in args.region.split(","))
        except ValueError:
            region = ()
        if len(region) != 4 or not (region[0] < region[2] and region[1] < region[3]) or min(region[2:]) <= 0:
            raise UsageError(f"--region expects X0,Y0,X1,Y1 (integer pixels, X0 < X1, Y0 < Y1), got {args.region!r}")
    if args.table:
        real = os.path.realpath(args.table)
        if args.config and real == os.path.realpath(args.config):
            raise UsageError(f"--table {shown(args.table)}: is the --config file; writing it would overwrite the config")
        manifests = list(args.manifest or []) + [str(s) for s in args.inputs
                                                  if Path(str(s)).suffix.lower() in (".parquet", ".pq")]
        if real in {os.path.realpath(m) for m in manifests}:
            raise UsageError(f"--table {shown(args.table)}: is a manifest of the run; writing it would overwrite "
                             f"that manifest")
    if (args.zoom != 1 or region is not None) and "overlay.png" not in image_formats:
        image_formats.append("overlay.png")
    if not 0 <= args.max_pixels < 2 ** 62:
        raise UsageError(f"--max-pixels must be >= 0, got {args.max_pixels}")
    if not 0 <= args.max_boundary < 2 ** 62:
        raise UsageError(f"--max-boundary must be >= 0, got {args.max_boundary}")
    try:
        device = torch.device(args.device)
        torch.empty(0, device=device)
    except Exception as e:          # RuntimeError, or ModuleNotFoundError for a backend torch lacks (hpu)
        raise UsageError(f"--device {shown(args.device)}: {shown(one_line(e, type(e).__name__))[:200]}") from None
    if device.type == "meta":       # accepted by torch, but it holds no values: every input would fail
        raise UsageError(f"--device {shown(args.device)}: a meta device holds no values")
    if args.engine == "ray" and args.actors < 1:
        raise UsageError(f"--actors must be >= 1, got {args.actors}")
    if not 0 < args.cpus_per_actor < 1e6:
        raise UsageError(f"--cpus-per-actor must be > 0 and below 1e6, got {args.cpus_per_actor:g}")
    if not 0 <= args.gpus_per_actor < 1e6:
        raise UsageError(f"--gpus-per-actor must be >= 0 and below 1e6, got {args.gpus_per_actor:g}")
    from torch_isc.dataset import resolve_inputs

    try:
        sources = resolve_inputs([str(s) for s in args.inputs], args.manifest or None, args.manifest_column,
                                 errors={}, out_dir=args.out)    # unlistable folders: failed inputs
    except RunError as e:
        raise UsageError(str(e)) from None
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
    # pixel defaults for images, except where the user set a key
    from torch_isc import images

    keep = set(_config_keys(args.config)) | {k for k in parse_overrides(args.overrides)}
    image_config = images.image_config(config, keep=sorted(keep), mode=args.mode)
    try:
        image_options = ImageOptions(mode=args.mode, threshold=args.threshold, spacing=args.spacing,
                                     use_oracle=not args.no_oracle, canny=(low, high), sigma=args.sigma,
                                     max_pixels=int(args.max_pixels) or None,
                                     max_boundary=int(args.max_boundary) or None, connectivity=args.connectivity,
                                     zoom=args.zoom, region=region)
    except RunError as e:
        raise UsageError(str(e)) from None

    bar = _Progress(len(sources))

    def progress(record: Record) -> None:
        bar.advance()
        if record.status == "skipped":
            bar.print(f"{shown(record.stem)}: skipped, outputs exist in {shown(out_dir)} (use --overwrite to redo)",
                      sys.stdout)
        elif record.status == "failed":
            bar.print(f"{PROG}: error: {record.error}", sys.stderr)   # the message already starts with the file name
            if args.debug and record.traceback:
                bar.print(record.traceback.rstrip("\n"), sys.stderr)
        else:
            bar.print(_summary(record), sys.stdout)

    def on_batch(stage: str, batch: int, size: int, done: int, total: int) -> None:
        if total <= 1 or bar.visible:
            return
        if stage == "start":
            _note(f"[{done}/{total}] batch {batch}: reconstructing {size} input(s), {100 * done // total}% done")
        elif done == total:
            _note(f"[{done}/{total}] 100% done")

    try:
        if args.engine == "local" and args.table is None:
            # the inputs are resolved once, here: the same files with and without --table
            report = run_inputs(sources, config, out_dir, formats, image_formats, overwrite=args.overwrite,
                                batch_size=args.batch_size, image_options=image_options, image_config=image_config,
                                device=device, progress=progress, on_batch=on_batch, on_note=_note,
                                stems=unique_stems(sources, _note))
        else:
            from torch_isc.dataset import reconstruct_dataset

            try:
                report = reconstruct_dataset(
                    sources, out_dir, config, args.engine, formats=formats, image_formats=image_formats,
                    overwrite=args.overwrite, batch_size=args.batch_size, image_options=image_options,
                    image_config=image_config, device=None if args.device == "cpu" and args.gpus_per_actor
                    else args.device, table=args.table, address=args.address, actors=args.actors,
                    cpus_per_actor=args.cpus_per_actor, gpus_per_actor=args.gpus_per_actor,
                    progress=progress, on_note=_note, keep_records=False, resolved=True)
            except RunError as e:
                raise UsageError(str(e)) from None
    finally:
        bar.close()
    # the inputs the run had (a folder or a glob in a manifest lists many), not the arguments
    counts = getattr(report, "counts", None)
    n = sum(counts.values()) if counts else len(getattr(report, "records", None) or sources)
    failed = report.failed
    if getattr(report, "batches", 0) > 1 or failed:
        _note(f"done: {n - failed} of {n} input(s) ok, {failed} failed"
              + (f"; table: {args.table}" if args.table else ""))
    return 1 if failed else 0


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
        _err(one_line(e, type(e).__name__))
        return 2
    except KeyboardInterrupt as e:          # SIGINT, or SIGTERM under the torch-isc command (entry.Terminated)
        from torch_isc.entry import stop_status

        word, code = stop_status(e)
        _err(word)
        return code
    except Exception as e:        # a bug or an environment failure outside any one input: one line, not a traceback
        if getattr(args, "debug", False):
            raise
        _err(f"internal error ({type(e).__name__}: {shown(one_line(e, '(no message)'))[:300]}); "
             f"--debug shows the traceback")
        return 1
    return 2  # pragma: no cover


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
