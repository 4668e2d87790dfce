"""The batch runner: many input files -> reconstructions -> output files, as library code.

:func:`run_inputs` takes point files, images and folders, a config and an output folder, and for
every input writes ``<out>/<stem>.<format>``. It

- expands folders (their point and image files, sorted by name) and gives every input a unique
  output stem (:func:`expand_inputs`, :func:`unique_stems`);
- skips an input only when its output set is complete and belongs to this input and config:
  ``<stem>.manifest.json``, written last, holds the sha256 of the input's bytes, of the
  config (and image options), the formats and every output file with its sha256; a missing,
  stale or mismatching manifest means the input is redone (:func:`manifest_matches`);
- reads inputs lazily, only when their batch fills, so memory stays bounded for a folder of
  any size, and solves each batch with :func:`torch_isc.reconstruct_batch`: point files with
  ``config``, images with the pixel config, masks with the mask as sign oracle and the count
  retry of :func:`torch_isc.images.solve_masks`;
- isolates failures: an input that cannot be listed, read, solved or written gets a failed
  record with a one-line error naming it (control characters in its name escaped), and the
  others go on (a batch that raises is solved again item by item to find the one at fault); an
  output set that fails while being written is removed again, so no partial set is left;
- checks inputs before anything large is allocated: a ``.npy`` header's declared size against
  the file, an image's pixel count from its header against ``ImageOptions.max_pixels``;
- calls ``progress(record)`` as soon as each input is final (skipped, failed or done) and
  returns the records in input order.

Example:
    >>> import tempfile, pathlib, numpy as np
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    >>> np.savetxt(d / "ring.xy", np.c_[np.cos(t), np.sin(t)])
    >>> _ = (d / "bad.xy").write_text("1 x\\n")
    >>> from torch_isc import load_config
    >>> report = run_inputs([d / "ring.xy", d / "bad.xy"], load_config(), d / "out", formats=["json"])
    >>> [(r.stem, r.status) for r in report.records]
    [('ring', 'done'), ('bad', 'failed')]
    >>> report.records[1].error.endswith("bad.xy: line 1: non-numeric value 'x'")
    True
"""
from __future__ import annotations

import hashlib
import json
import math
import operator
import os
import time
import traceback
import unicodedata
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple, Union

import torch

import torch_isc
from torch_isc import images
from torch_isc._helpers import is_regular_file, one_line, printable, read_file_bytes
from torch_isc.io import EXPORTERS, ExportContext, PointFileError, chosen_formats, export, formats_needing, loader_for
from torch_isc.io.registry import LOADERS
from torch_isc.io.files import atomic_write
from torch_isc.images.masks import MIN_SPACING, count_matches
from torch_isc.images.read import DEFAULT_MAX_PIXELS, decode_image
from torch_isc.pipeline.config import ReconstructConfig, config_hash
from torch_isc.pipeline.loop import PointSetError, _as_config
from torch_isc.core.points import item_label

__all__ = ["RunError", "ImageOptions", "DEFAULT_MAX_BOUNDARY", "boundary_length", "Record", "RunReport", "DEFAULT_FORMATS", "DEFAULT_IMAGE_FORMATS",
           "expand_inputs", "resolved_inputs", "inside_folder", "make_out_dir", "unique_stems", "overwritten_inputs", "run_arguments", "run_inputs", "shown", "file_sha256", "manifest_path", "manifest_matches",
           "MANIFEST_FORMAT"]

#: Version of the ``<stem>.manifest.json`` layout.
MANIFEST_FORMAT = 1

#: Outputs of a point file, and of an image (the drawings and the overlay on request).
DEFAULT_FORMATS = ("json", "npz", "svg", "png")
DEFAULT_IMAGE_FORMATS = ("json", "contours.npz")

PathLike = Union[str, os.PathLike]


#: The default :attr:`ImageOptions.max_boundary`: about 5 minutes and 3 GB of tracing on one
#: CPU core (a 400x400 checkerboard, 320,000 pixel edges, takes 26 s on a loaded machine).
DEFAULT_MAX_BOUNDARY = 4_000_000


def boundary_length(mask: torch.Tensor) -> int:
    """Pixel edges between foreground and background of a boolean ``(H, W)`` mask, the image
    frame counted where the foreground touches it: the length of its contours in pixels, which
    the tracing's work and memory follow."""
    m = mask.to(torch.int8)
    inner = (m[:, 1:] != m[:, :-1]).sum() + (m[1:, :] != m[:-1, :]).sum()
    frame = m[0, :].sum() + m[-1, :].sum() + m[:, 0].sum() + m[:, -1].sum()
    return int(inner + frame)


class RunError(ValueError):
    """Arguments a run cannot start with (nothing was read or written); one line."""


@dataclass(frozen=True)
class ImageOptions:
    """How image inputs become points.

    Attributes:
        mode: ``"mask"`` (boundary points on the pixel cracks, vertex signs from the mask) or
            ``"edges"`` (kornia Canny edge points of the gray image, topology estimated).
        threshold: mask mode: foreground is gray > threshold (None: midway between the two
            levels of a two-level image, else 0.5; :func:`torch_isc.images.auto_threshold`).
        spacing: pixels between points along a contour.
        use_oracle: mask mode: read the vertex signs from the mask.
        canny: edges mode: ``(low, high)`` hysteresis thresholds on the gradient of the image in [0, 1].
        sigma: edges mode: Gaussian smoothing in pixels.
        max_pixels: the largest image read (width x height, from its header, before decoding);
            None: no limit.
        max_boundary: the longest boundary of one image: in mask mode its pixel edges between
            foreground and background (the image frame counted where the foreground meets it),
            in edges mode its edge points; counted before the curve is traced (a noise or
            checkerboard mask of a few megapixels has millions: hours of work and gigabytes);
            None or 0: no limit.
        connectivity: mask mode: 8 (OpenCV's) or 4, of the foreground.
        zoom, region: of ``overlay.png``: an integer zoom and the part of the image shown
            (``(x0, y0, x1, y1)`` pixels, None: all); see :func:`torch_isc.io.render_overlay`.
    """
    mode: str = "mask"
    threshold: Optional[float] = None
    spacing: float = 1.0
    use_oracle: bool = True
    canny: Tuple[float, float] = (0.1, 0.2)
    sigma: float = 1.0
    max_pixels: Optional[int] = DEFAULT_MAX_PIXELS
    max_boundary: Optional[int] = DEFAULT_MAX_BOUNDARY
    connectivity: int = 8
    zoom: int = 1
    region: Optional[Tuple[int, int, int, int]] = None

    def __post_init__(self):
        # checked at the boundary, with the option named (a spacing of inf crashed every image)
        def real(v):
            return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

        def integer(v):
            return isinstance(v, int) and not isinstance(v, bool)

        bad = None
        if self.mode not in ("mask", "edges"):
            bad = f"mode must be 'mask' or 'edges', got {self.mode!r}"
        elif self.threshold is not None and not (real(self.threshold) and 0 <= self.threshold < 1):
            bad = f"threshold must be None or in [0, 1), got {self.threshold!r}"
        elif not (real(self.spacing) and (self.spacing == 0 or MIN_SPACING <= self.spacing <= 1e6)):
            bad = f"spacing must be 0 (no resampling) or a number of pixels in [{MIN_SPACING}, 1e6], got {self.spacing!r}"
        elif not isinstance(self.use_oracle, bool):
            bad = f"use_oracle must be True or False, got {self.use_oracle!r}"
        elif not (isinstance(self.canny, (tuple, list)) and len(self.canny) == 2 and all(map(real, self.canny))
                  and 0 < self.canny[0] < self.canny[1]):
            bad = f"canny must be (low, high) with 0 < low < high, got {self.canny!r}"
        elif not (real(self.sigma) and 0 < self.sigma <= 1e3):
            bad = f"sigma must be in (0, 1000], got {self.sigma!r}"
        elif self.max_pixels is not None and not (integer(self.max_pixels) and self.max_pixels >= 0):
            bad = f"max_pixels must be None or an integer >= 0, got {self.max_pixels!r}"
        elif self.max_boundary is not None and not (integer(self.max_boundary) and self.max_boundary >= 0):
            bad = f"max_boundary must be None or an integer >= 0, got {self.max_boundary!r}"
        elif self.connectivity not in (4, 8) or isinstance(self.connectivity, bool):
            bad = f"connectivity must be 4 or 8, got {self.connectivity!r}"
        elif not (integer(self.zoom) and 1 <= self.zoom <= 64):
            bad = f"zoom must be an integer in [1, 64], got {self.zoom!r}"
        elif self.region is not None and not (isinstance(self.region, (tuple, list)) and len(self.region) == 4
                                              and all(map(integer, self.region))):
            bad = f"region must be None or (x0, y0, x1, y1) integers, got {self.region!r}"
        if bad is not None:
            raise RunError(f"image options: {bad[:300]}")


@dataclass
class Record:
    """What happened to one input.

    Attributes:
        source: the input as given. stem: its output name, unique within the run.
        status: ``"done"``, ``"skipped"`` (outputs exist) or ``"failed"``.
        error: for a failed input, one line naming it (``"<file>: <problem>"``).
        traceback: the traceback text of an unexpected (internal) error, else None.
        summary: for a done input: ``num_closed, num_open, levels, converged, limit,
            points_beyond_tolerance, seconds`` (inputs solved in one batch share its wall time).
        outputs: the files written, in the order of the formats.
    """
    source: str
    stem: str
    status: str = "pending"
    error: Optional[str] = None
    traceback: Optional[str] = None
    summary: Optional[Dict[str, Any]] = None
    outputs: List[Path] = field(default_factory=list)


@dataclass
class RunReport:
    """The records of a run, in input order, and how many batches were solved."""
    records: List[Record]
    batches: int = 0

    @property
    def failed(self) -> int:
        return sum(r.status == "failed" for r in self.records)


# ============================================================================ inputs
def _is_image(source: str) -> bool:
    return loader_for(source).kind == "image"


def shown(name: object) -> str:
    """``name`` as it is printed in a message: control characters (a newline in a file name)
    escaped, so a message stays one line.

    >>> shown("a\\nb.xy")
    'a\\\\nb.xy'
    """
    return printable(name)


def _message(source: str, e: BaseException) -> str:
    """A one-line error of ``e`` starting with the (escaped) name of ``source``."""
    text = str(e).strip()
    for prefix in (source, str(Path(source))):
        if prefix and text.startswith(prefix + ":"):
            rest = text[len(prefix):]
            return shown(source) + one_line(rest.replace("\r", "\n"), type(e).__name__)
    return one_line(shown(text) if "\n" not in text else text, type(e).__name__)


def _is_dir(p: Path) -> bool:
    try:
        return p.is_dir()
    except OSError:
        return False


def inside_folder(path: PathLike, folder: Optional[PathLike]) -> bool:
    """Whether ``path`` is ``folder`` or lies under it (real paths: links resolved)."""
    if folder is None:
        return False
    p, f = os.path.realpath(path), os.path.realpath(folder)
    return p == f or p.startswith(f.rstrip(os.sep) + os.sep)


def output_folder_input(src: PathLike, out_dir: Optional[PathLike]) -> RunError:
    """The error of a folder input that is the output folder (or lies in it)."""
    return RunError(f"{shown(src)}: is the output folder {shown(out_dir)} (or inside it): a rerun would read "
                    f"this run's outputs as inputs; give another output folder")


def expand_inputs(sources: Iterable[PathLike], errors: Optional[Dict[str, str]] = None,
                  out_dir: Optional[PathLike] = None) -> List[str]:
    """A folder stands for its point and image files (by :data:`~torch_isc.io.LOADERS` suffix,
    sorted by name, not recursive; FIFOs, devices and dangling links of those suffixes too, so
    that they are reported when read); anything else is kept as given (a missing file is reported
    when it is read).

    ``out_dir``: the run's output folder. A folder input that is it, or lies in it, is refused:
    the outputs of one run (drawings, overlays) would be the next run's inputs.

    A folder that cannot be listed (no read permission) raises :class:`RunError`, unless
    ``errors`` is given: it is then kept in the list as one input and ``errors[folder]`` holds
    its one-line error (:func:`run_inputs` reports it as a failed input).

    Raises:
        RunError: a folder without any such file, or one that cannot be listed; an empty path.
    """
    out: List[str] = []
    for src in sources:
        if os.fspath(src) == "":        # Path("") is ".": an unset shell variable would run the whole working folder
            raise RunError("an empty path ('') given as an input")
        p = Path(src)
        try:
            is_dir = p.is_dir()
        except OSError:
            is_dir = False
        if is_dir:
            if inside_folder(p, out_dir):
                raise output_folder_input(src, out_dir)
            try:
                # every entry with a known suffix but folders: a FIFO or a dangling link among
                # them is an input that fails in one line, not one skipped silently
                files = sorted(str(f) for f in p.iterdir() if f.suffix.lower() in LOADERS and not _is_dir(f))
            except OSError as e:
                msg = f"{shown(src)}: cannot list the folder ({e.strerror or type(e).__name__})"
                if errors is None:
                    raise RunError(msg) from None
                errors[str(src)] = msg
                out.append(str(src))
                continue
            if not files:
                raise RunError(f"{shown(src)}: folder has no point or image file ({', '.join(LOADERS)})")
            out.extend(files)
        else:
            out.append(str(src))
    return out


def resolved_inputs(inputs: Iterable[PathLike], errors: Dict[str, str]) -> List[str]:
    """Inputs already resolved to files (one per output stem): kept as they are, a folder among
    them (a manifest's line) one failed input in ``errors``, never expanded here (the stems
    would no longer match, and the whole batch failed)."""
    out = [os.fspath(s) for s in inputs]
    for src in out:
        if src and _is_dir(Path(src)) and src not in errors:
            errs: Dict[str, str] = {}
            try:
                expand_inputs([src], errs)
                errors[src] = (f"{shown(src)}: is a folder, not a point or image file (a manifest lists "
                               f"files; give the folder itself as an input to reconstruct its files)")
            except RunError as e:
                errors[src] = str(e)
            errors.update(errs)
    return out


def make_out_dir(out_dir: PathLike) -> Path:
    """The output folder, created if needed; a :class:`RunError` naming it when it cannot be
    (a file of that name, no permission), not an ``OSError`` traceback."""
    if not isinstance(out_dir, (str, os.PathLike)) or os.fspath(out_dir) == "":
        raise RunError(f"out_dir: expected a folder path (a non-empty str or path object), got {out_dir!r:.60}")
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except (OSError, ValueError) as e:
        raise RunError(f"{shown(out_dir)}: cannot create the output folder "
                       f"({getattr(e, 'strerror', None) or one_line(e, type(e).__name__)})") from None
    return out


def unique_stems(sources: Sequence[str], note: Optional[Callable[[str], None]] = None) -> List[str]:
    """Output stems, by a rule that does not depend on the order of the inputs:

    Stems clash when they are equal up to case and Unicode normalization (:func:`_fold`).

    1. the file stem (``a.xy`` -> ``a``) when no other input has the same one;
    2. else the stem and the suffix (``a.xy`` -> ``a_xy``, ``a.npy`` -> ``a_npy``);
    3. where that still clashes (``d1/a.xy`` and ``d2/a.xy``, or another input's name), or where
       it is another stem followed by a dot and more (``a.manifest.xy`` beside ``a.xy``: its JSON
       would be ``a``'s manifest), also the first 8 hex digits of the sha256 of the input's
       absolute path (``a_xy_1f2e3d4c``, ``a.manifest_0c1d2e3f``);
    4. the same path given twice: ``_2``, ``_3``... on the repeats;
    5. a stem longer than :data:`MAX_STEM_BYTES` (200 bytes of UTF-8) is cut and ends with 8
       hex digits of the sha256 of the whole stem (a 250-character name overflowed the file
       system's 255 bytes with ``.manifest.json`` and lost the whole run).

    ``note`` is told about each renaming.

    >>> unique_stems(["a/x.xy", "b/x.png", "y.xy"])
    ['x_xy', 'x_png', 'y']
    >>> unique_stems(["b/x.png", "a/x.xy", "y.xy"])
    ['x_png', 'x_xy', 'y']
    """
    plain = [Path(s).stem or "input" for s in sources]
    n_plain = Counter(_fold(p) for p in plain)
    names = []
    for src, stem in zip(sources, plain):
        if n_plain[_fold(stem)] == 1:
            names.append(stem)
        else:
            names.append(f"{stem}_{Path(src).suffix.lower().lstrip('.') or 'noext'}")
    n_names = Counter(_fold(n) for n in names)
    # a stem that is another one's followed by a dot and more shares file names with it
    # (a.manifest.xy's JSON is a.xy's a.manifest.json, m.contours.xy's npz is m.png's contours)
    taken = {_fold(n) for n in names}
    dotted = [any(_fold(n[:k]) in taken for k in range(1, len(n)) if n[k] == ".") for n in names]
    for i, src in enumerate(sources):
        if n_names[_fold(names[i])] > 1 or dotted[i]:
            h = hashlib.sha256(os.path.abspath(src).encode("utf-8", "surrogateescape")).hexdigest()[:8]
            names[i] = f"{names[i]}_{h}"
    seen: Counter = Counter()
    for i in range(len(names)):
        seen[_fold(names[i])] += 1
        if seen[_fold(names[i])] > 1:
            names[i] = f"{names[i]}_{seen[_fold(names[i])]}"
    renamed = [name != stem for stem, name in zip(plain, names)]
    names = [_fit_stem(n) for n in names]
    if note is not None:
        for src, stem, name, clash, dot in zip(sources, plain, names, renamed, dotted):
            if dot and n_plain[stem] == 1:
                note(f"note: {shown(src)}: the outputs of '{shown(stem)}' would share file names with another "
                     f"input's (a stem followed by '.'), written as '{shown(name)}'")
            elif clash:
                note(f"note: another input is also named '{shown(stem)}': {shown(src)} is written as '{shown(name)}'")
            elif name != stem:
                note(f"note: {shown(src)}: name too long for an output file, written as '{shown(name)}'")
    return names


def _fold(name: str) -> str:
    """The key under which two stems clash: case-folded and NFC-normalized, as the file systems
    that ignore case or normalization (macOS, Windows) compare names (``Ring`` and ``ring``
    would write one set of files there)."""
    return unicodedata.normalize("NFC", name).casefold()


#: The longest output stem, in bytes (UTF-8): a file name holds 255 bytes, and the longest name
#: written is ``.<stem>.manifest.json.XXXXXXXX.tmp`` (the atomic write's temporary file).
MAX_STEM_BYTES = 200


def _fit_stem(stem: str) -> str:
    """``stem`` when it fits :data:`MAX_STEM_BYTES`; else its first bytes (whole characters)
    and 8 hex digits of the sha256 of all of it, so two long names never collide."""
    raw = stem.encode("utf-8", "surrogateescape")
    if len(raw) <= MAX_STEM_BYTES:
        return stem
    head = raw[:MAX_STEM_BYTES - 9].decode("utf-8", "ignore")      # a cut character is dropped
    return f"{head}_{hashlib.sha256(raw).hexdigest()[:8]}"


def overwritten_inputs(sources: Sequence[str], stems: Sequence[str], out_dir: PathLike,
                       formats_of: Callable[[str], Sequence[str]]) -> Dict[int, str]:
    """``{i: one-line error}`` for each input whose output set would overwrite an input file of
    the run (itself: ``m.png`` in the output folder with ``--formats png``; or another), by the
    real paths (links followed). Such an input is not reconstructed: writing would destroy an
    input, and a rerun would read the output as its input."""
    keys = {}
    for src in sources:
        try:
            keys.setdefault(os.path.realpath(src), src)
        except (OSError, ValueError):
            pass
    if not keys:
        return {}
    out_real = os.path.realpath(out_dir)
    if not any(os.path.dirname(k) == out_real for k in keys):      # no input in the output folder
        return {}
    bad: Dict[int, str] = {}
    for i, (src, stem) in enumerate(zip(sources, stems)):
        for name in [f"{stem}.{f}" for f in formats_of(src)] + [manifest_path("", stem).name]:
            victim = keys.get(os.path.join(out_real, name))
            if victim is not None:
                whose = "the input itself" if victim == src else f"the input {shown(victim)}"
                bad[i] = (f"{shown(src)}: its output {shown(Path(out_dir) / name)} would overwrite {whose}; "
                          f"choose another output folder or format")
                break
    return bad


def file_sha256(path: PathLike) -> str:
    """sha256 (hex) of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def manifest_path(out_dir: PathLike, stem: str) -> Path:
    """``<out_dir>/<stem>.manifest.json``."""
    return Path(out_dir) / f"{stem}.manifest.json"


#: a manifest larger than this is foreign (ours list a few files in a few hundred bytes): it is
#: not read, so a huge file under that name cannot exhaust memory
MANIFEST_MAX_BYTES = 1 << 20

_MANIFEST_ERRORS = (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError, MemoryError)


def _read_manifest(mp: Path) -> Optional[dict]:
    """The JSON object of the manifest ``mp``, or None: no regular file there (a FIFO under that
    name would block the run), larger than :data:`MANIFEST_MAX_BYTES` (ours are a few hundred
    bytes: a foreign file), or not a JSON object (deeply nested JSON raises RecursionError)."""
    try:
        if not is_regular_file(mp) or mp.stat().st_size > MANIFEST_MAX_BYTES:
            return None
        m = json.loads(mp.read_text(encoding="utf-8"))
    except _MANIFEST_ERRORS:
        return None
    return m if isinstance(m, dict) else None


def manifest_matches(out_dir: PathLike, stem: str, input_sha256: str, config_sha256: str,
                     formats: Sequence[str]) -> bool:
    """Whether ``<stem>.manifest.json`` says the outputs of ``stem`` are complete and were made
    from this input and config in these formats, and every file it lists still has its hash."""
    m = _read_manifest(manifest_path(out_dir, stem))
    if m is None:
        return False
    try:
        if (m.get("manifest_format") != MANIFEST_FORMAT or m["input"]["sha256"] != input_sha256
                or m["config_sha256"] != config_sha256 or list(m["formats"]) != list(formats)):
            return False
        files = m["files"]
        if [f["name"] for f in files] != [f"{stem}.{fmt}" for fmt in formats]:
            return False
        return all(is_regular_file(Path(out_dir) / f["name"]) and file_sha256(Path(out_dir) / f["name"]) == f["sha256"]
                   for f in files)
    except _MANIFEST_ERRORS:
        return False


def _listed_outputs(man: Path, stem: str) -> set:
    """The output files an existing manifest lists, restricted to ``<stem>.<format>`` names of
    known formats that are regular files (a manifest is never trusted to name other files)."""
    m = _read_manifest(man)
    try:
        names = {f["name"] for f in m["files"] if isinstance(f, dict) and isinstance(f.get("name"), str)}
    except _MANIFEST_ERRORS:                    # None (no manifest) included: TypeError
        return set()
    known = {f"{stem}.{f}" for f in EXPORTERS}
    return {n for n in names & known if is_regular_file(man.parent / n)}


# ============================================================================ the run
@dataclass
class _Job:
    record: Record
    is_image: bool
    points: Optional[torch.Tensor] = None
    image: Optional[object] = None   # gray (H, W) float32 in [0, 1] for an image input, while in its batch
    mask: Optional[torch.Tensor] = None
    n_boundaries: Optional[int] = None
    input_sha256: Optional[str] = None

    @property
    def source(self) -> str:
        return self.record.source

    @property
    def stem(self) -> str:
        return self.record.stem


class _Run:
    """One call of :func:`run_inputs`: the resolved options and the callbacks."""

    def __init__(self, config, image_config, out_dir, formats, image_formats, batch_size, image_opts, device,
                 progress, on_batch, on_note, on_result=None):
        self.config = config
        self.image_config = image_config
        self.out_dir = out_dir
        self.formats = formats
        # an image gets the formats asked for (the overlay too: it needs the image, which it has)
        self.image_formats = list(image_formats)
        self.formats = [f for f in formats if f not in formats_needing({"image"})]
        # said once, at the first point-set input: an overlay asked for has no image to draw on
        self.image_only = [f for f in formats if f not in self.formats]
        self.batch_size = batch_size
        self.opts = image_opts
        self.device = device
        self.progress = progress or (lambda record: None)
        self.on_batch = on_batch or (lambda *a: None)
        self.note = on_note or (lambda msg: None)
        self.on_result = on_result or (lambda record, result: None)
        self.done = 0
        self.total = 0
        self.batches = 0
        # what an output set must have been made with (the manifest's config hash)
        opts = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(image_opts).items() if k not in ("max_pixels", "max_boundary")}
        for k, default in (("zoom", 1), ("region", None)):      # the overlay's view: hashed when set
            if opts.get(k) == default:
                opts.pop(k, None)
        self.config_sha = {False: config_hash(config, {"kind": "points"}),
                           True: config_hash(image_config, {"kind": "image", **opts})}

    def formats_of(self, job: _Job) -> List[str]:
        if not job.is_image and self.image_only:
            left = ", ".join(self.formats) if self.formats else "only the manifest"
            self.note(f"{', '.join(self.image_only)} needs an image: point-set inputs get {left}")
            self.image_only = []
        return self.image_formats if job.is_image else self.formats

    def finish(self, job: _Job, status: str, error: Optional[str] = None, tb: Optional[str] = None) -> None:
        job.record.status, job.record.error, job.record.traceback = status, error, tb
        self.progress(job.record)

    # ---------------------------------------------------------------- reading
    def read(self, job: _Job) -> None:
        """Read one input into its job: points, and for an image the gray image (and the mask)."""
        if not job.is_image:
            loader = loader_for(job.source)
            if loader.decode is None:
                job.points = torch.from_numpy(loader.load(job.source)).to(self.device)
                return
            # the bytes decoded are the bytes hashed: a file rewritten during the run cannot leave a
            # manifest whose hash is of other content than its outputs
            data = read_file_bytes(Path(job.source), PointFileError, "a point file")
            job.input_sha256 = hashlib.sha256(data).hexdigest()
            job.points = torch.from_numpy(loader.decode(job.source, data)).to(self.device)
            return
        o = self.opts
        # the file is read once: its bytes are decoded and hashed (the manifest's input sha256)
        data = read_file_bytes(Path(job.source), images.ImageError, "an image")
        job.input_sha256 = hashlib.sha256(data).hexdigest()
        gray = decode_image(data, Path(job.source), max_pixels=o.max_pixels)
        job.image = gray
        if o.mode == "mask":
            thr = o.threshold if o.threshold is not None else images.auto_threshold(gray)
            mask = torch.from_numpy(gray > thr).to(self.device)
            if not bool(mask.any()):
                # a valid mask with no border (cv2.findContours: no contour): an output set without
                # curves, so a rerun skips it and the run does not fail
                self.note(f"note: {shown(job.source)}: empty mask (no pixel above threshold {thr:.10g}, all "
                          f"black): no curve")
                job.points, job.n_boundaries, job.mask = None, 0, mask
                return
            if o.max_boundary:
                n = boundary_length(mask)
                if n > o.max_boundary:
                    raise images.ImageError(
                        f"{job.source}: mask boundary too long: {n} pixel edges, more than the limit of "
                        f"{o.max_boundary} (max_boundary, --max-boundary; a noise-like mask?)")
            if bool(mask.all()):
                self.note(f"note: {shown(job.source)}: the whole image is foreground (all white at threshold "
                          f"{thr:.3g}): its curve is the image frame")
            if o.use_oracle:        # the grid path needs no boundary points
                job.points, job.n_boundaries = None, None
            else:
                job.points, job.n_boundaries = images.mask_points(mask, o.spacing, None, name=job.source)
                job.points = job.points.double()
            job.mask = mask
        else:
            low, high = o.canny
            need = max(2, int(math.ceil(2 * o.sigma)) + 1)       # kornia's reflect padding of the Gaussian
            if min(gray.shape) < need:
                raise images.ImageError(f"{job.source}: image too small for edges mode ({gray.shape[1]}x{gray.shape[0]} "
                                        f"px; Canny with sigma {o.sigma:g} needs at least {need}x{need})")
            pts = images.edge_points([torch.from_numpy(gray).to(self.device)], low, high, sigma=o.sigma,
                                     spacing=o.spacing)[0]
            if pts.shape[0] < 3:
                # with a coarse spacing the edges may be there but resampled to fewer than 3 points
                why = (f"{pts.shape[0]} point(s) at Canny thresholds {low:g},{high:g} and --spacing {o.spacing:g}: "
                       f"a flat image, or a spacing too coarse for its edges" if o.spacing > 1 else
                       f"{pts.shape[0]} edge pixel(s) at Canny thresholds {low:g},{high:g}; flat image?")
                raise images.ImageError(f"{job.source}: no edges found ({why})")
            if o.max_boundary and pts.shape[0] > o.max_boundary:
                raise images.ImageError(f"{job.source}: too many edge points: {pts.shape[0]}, more than the limit of "
                                        f"{o.max_boundary} (max_boundary, --max-boundary)")
            job.points = pts.double()

    def read_isolated(self, job: _Job) -> bool:
        """:meth:`read`, any failure made the job's failed record (one line naming it)."""
        try:
            self.read(job)
            if job.input_sha256 is None:
                job.input_sha256 = file_sha256(job.source)
            return True
        except (PointFileError, images.ImageError, PointSetError) as e:
            self.fail_read(job, _message(job.source, e))
        except FileNotFoundError:
            self.fail_read(job, f"{shown(job.source)}: no such file")
        except IsADirectoryError:
            self.fail_read(job, f"{shown(job.source)}: is a directory, not a point file or an image")
        except OSError as e:
            self.fail_read(job, f"{shown(job.source)}: cannot read ({e.strerror or type(e).__name__})")
        except MemoryError:
            self.fail_read(job, f"{shown(job.source)}: out of memory while reading it")
        except Exception as e:
            self.fail_read(job, f"{shown(job.source)}: reading failed ({type(e).__name__}: "
                                f"{one_line(shown(str(e)), type(e).__name__)})", traceback.format_exc())
        job.points = job.image = job.mask = None
        return False

    def fail_read(self, job: _Job, msg: str, tb: Optional[str] = None) -> None:
        self.done += 1
        self.finish(job, "failed", msg, tb)

    # ---------------------------------------------------------------- solving
    def solve(self, jobs: List[_Job], kind: str) -> list:
        """One batched solve: point files with the user's config, images with the pixel config,
        masks with the mask as sign oracle (and the count check of :func:`images.solve_masks`)."""
        # the solvers are looked up on the package at call time, so a caller can substitute them
        reconstruct, reconstruct_batch = torch_isc.reconstruct, torch_isc.reconstruct_batch
        names = [j.stem for j in jobs]
        points = [j.points for j in jobs]
        if kind == "mask":
            return images.grid_results([j.mask for j in jobs], names, connectivity=self.opts.connectivity,
                                       config=self.image_config)
        if all(not j.is_image for j in jobs):
            if len(jobs) == 1:
                return [reconstruct(points[0], self.config, name=names[0])]
            return reconstruct_batch(points, self.config, names=names)
        cfgs = [self.image_config if j.is_image else self.config for j in jobs]
        if any(c is not cfgs[0] for c in cfgs):         # images and point files: one solve per config
            out = [None] * len(jobs)
            for cfg in (self.config, self.image_config):
                idx = [i for i, c in enumerate(cfgs) if c is cfg]
                if idx:
                    for i, r in zip(idx, reconstruct_batch([points[i] for i in idx], cfg,
                                                           names=[names[i] for i in idx])):
                        out[i] = r
            return out
        return reconstruct_batch(points, cfgs[0], names=names)

    def solve_isolated(self, batch: List[_Job], kind: str) -> list:
        """``(result, seconds)`` per item of one batch; ``(None, seconds)`` for an item that
        failed (its record final). Items solved together share the batch's wall time evenly."""
        if len(batch) > 1:
            t0 = time.perf_counter()
            try:
                results = self.solve(batch, kind)
                if len(results) == len(batch):
                    share = (time.perf_counter() - t0) / len(batch)
                    return [(r, share) for r in results]
            except Exception:
                pass  # find the item(s) at fault by running them one by one
        bad_input = (PointSetError, ValueError, PointFileError, images.ImageError)
        out = []
        for job in batch:
            t0 = time.perf_counter()
            res = None
            try:
                res = self.solve([job], kind)[0]
            except bad_input as e:
                msg = str(e).strip()
                label = item_label(job.stem)
                if msg.startswith(f"{label}: "):        # a PointSetError names the item by its stem
                    msg = msg[len(label) + 2:]
                self.finish(job, "failed", f"{shown(job.source)}: {one_line(shown(msg), type(e).__name__)}")
            except MemoryError:
                self.finish(job, "failed", f"{shown(job.source)}: out of memory while reconstructing it")
            except Exception as e:
                self.finish(job, "failed", f"{shown(job.source)}: reconstruction failed ({type(e).__name__}: "
                                           f"{one_line(e, type(e).__name__)})", traceback.format_exc())
            out.append((res, time.perf_counter() - t0))
        return out

    def write(self, job: _Job, res, image) -> List[Path]:
        """Write the job's output set, one format after the other, then its manifest (last). The
        old manifest goes first, so an interrupted or failed write never leaves a set that looks
        complete; on an error the files written by this call are removed again."""
        formats = self.formats_of(job)
        man = manifest_path(self.out_dir, job.stem)
        stale = _listed_outputs(man, job.stem)
        try:
            man.unlink()
        except FileNotFoundError:
            pass
        # the previous set's files of formats not written now (a rerun with fewer formats or
        # another config) would sit beside the new set as if they belonged to it
        for name in stale - {f"{job.stem}.{f}" for f in formats}:
            try:
                (self.out_dir / name).unlink()
            except OSError:
                pass
        ctx = ExportContext(y_down=job.is_image, image=image, zoom=self.opts.zoom, region=self.opts.region)
        written: List[Path] = []
        try:
            digests: List[Tuple[str, int]] = []
            for f in formats:
                # no fsync: the manifest hashes every file, so a set torn by a power loss is redone;
                # the hashes are of the bytes written, taken in memory (no read back)
                written += export(res, self.out_dir / job.stem, [f], context=ctx, fsync=False, digests=digests)
            files = [{"name": p.name, "sha256": sha, "bytes": size} for p, (sha, size) in zip(written, digests)]
            doc = {"manifest_format": MANIFEST_FORMAT, "torch_isc": torch_isc.__version__,
                   "input": {"path": os.fspath(job.source), "sha256": job.input_sha256},
                   "config_sha256": self.config_sha[job.is_image], "formats": list(formats), "files": files}
            atomic_write(man, json.dumps(doc, indent=1) + "\n", fsync=False)
        except Exception:
            for p in written:
                try:
                    p.unlink()
                except OSError:
                    pass
            raise
        return written

    def complete(self, job: _Job) -> bool:
        """Whether the job's outputs are a complete set made from this input and config."""
        try:
            if not manifest_path(self.out_dir, job.stem).exists():
                return False
        except (OSError, ValueError):           # a name the file system refuses: redo (its write reports it)
            return False
        if not is_regular_file(job.source):     # hashing a FIFO or a device would block or never end
            return False
        try:
            sha = file_sha256(job.source)
        except OSError:
            return False
        return manifest_matches(self.out_dir, job.stem, sha, self.config_sha[job.is_image], self.formats_of(job))

    def owner(self, job: _Job) -> Optional[str]:
        """The input another run made ``job``'s output set from, when that is another file that
        still exists (two inputs of one stem from different folders, run one after the other):
        replacing its set silently would lose finished work. None otherwise (no set, ours, or
        an input since moved or deleted: redone as before)."""
        m = _read_manifest(manifest_path(self.out_dir, job.stem))
        try:
            path = m["input"]["path"]
            if (not isinstance(path, str) or path == os.fspath(job.source) or not is_regular_file(path)
                    or os.path.realpath(path) == os.path.realpath(job.source)):
                return None
            return path
        except _MANIFEST_ERRORS:                # None (no manifest) included: TypeError
            return None

    def process(self, batch: List[_Job]) -> None:
        self.batches += 1
        self.on_batch("start", self.batches, len(batch), self.done, self.total)
        # empty masks take the grid path whatever the oracle setting: they have no boundary points
        masks = [j for j in batch if j.is_image and j.mask is not None
                 and (self.opts.use_oracle or j.n_boundaries == 0)]
        others = [j for j in batch if j not in masks]
        solved = {}
        for group, kind in ((others, "plain"), (masks, "mask")):
            if group:
                solved.update(zip(map(id, group), self.solve_isolated(group, kind)))
        for job in batch:
            res, seconds = solved[id(job)]
            self.done += 1
            image = job.image
            job.points = job.image = job.mask = None             # free the batch's inputs
            if res is None:
                continue
            try:
                job.record.outputs = self.write(job, res, image)
            except OSError as e:
                # os.replace(tmp, dst) names dst second: the output the user sees
                name = getattr(e, "filename2", None) or getattr(e, "filename", None)
                where = shown(name) if name else shown(self.out_dir)
                self.finish(job, "failed", f"{shown(job.source)}: cannot write outputs in {where} "
                                           f"({e.strerror or one_line(e, type(e).__name__)})")
                continue
            except Exception as e:  # an exporter bug: report it as one line, keep going
                self.finish(job, "failed", f"{shown(job.source)}: writing outputs failed ({type(e).__name__}: "
                                           f"{one_line(e, type(e).__name__)})", traceback.format_exc())
                continue
            stats = res.stats or []
            job.record.summary = {
                "num_closed": res.num_closed, "num_open": res.num_open, "levels": len(stats),
                "converged": bool(res.converged), "limit": res.limit,
                "points_beyond_tolerance": (stats[-1].points_beyond_tolerance if stats else 0),
                "seconds": seconds,
            }
            if job.is_image and self.opts.mode == "mask":
                # the mask's own count of borders, and whether the curve has as many
                nb = getattr(res, "boundaries", job.n_boundaries)
                job.record.summary["boundaries"] = nb
                job.record.summary["count_ok"] = count_matches(res, nb)
            self.on_result(job.record, res)
            self.finish(job, "done")
        self.on_batch("end", self.batches, len(batch), self.done, self.total)


#: the registry's order of the output formats (unknown names last, as given: refused later)
_FORMAT_ORDER = {f: i for i, f in enumerate(("json", "npz", "svg", "png", "contours.npz", "geojson", "overlay.png"))}


#: the largest batch size taken (2^31: beyond any batch that fits a machine; 2^63 overflowed
#: Arrow's slices with a raw OverflowError)
MAX_BATCH_SIZE = 2 ** 31


def run_arguments(inputs, formats, image_formats, batch_size, image_options=None):
    """The arguments shared by :func:`run_inputs` and :func:`torch_isc.dataset.reconstruct_dataset`,
    checked and normalized: one path (a str or path object) is one input, not a sequence of
    characters; a str of formats is a comma-separated list; the batch size an integer >= 1.

    Returns:
        ``(inputs, formats, image_formats)`` as lists."""
    if isinstance(inputs, (str, bytes, os.PathLike)):
        inputs = [inputs]
    elif not hasattr(inputs, "__iter__"):
        raise RunError(f"inputs: expected paths, got {type(inputs).__name__}")
    inputs = [os.fsdecode(s) if isinstance(s, bytes) else s for s in inputs]
    for s in inputs:
        if not isinstance(s, (str, os.PathLike)):
            raise RunError(f"inputs: expected paths (str or path objects), got {type(s).__name__}")
    lists = []
    for name, f in (("formats", formats), ("image_formats", image_formats)):
        if isinstance(f, str):
            f = [x.strip() for x in f.split(",") if x.strip()]
        if not hasattr(f, "__iter__") or not all(isinstance(x, str) for x in f):
            raise RunError(f"{name}: expected format names, got {f!r:.100}")
        f = list(dict.fromkeys(f))
        if not f:
            raise RunError(f"{name}: no output format (an input would be written as a manifest alone)")
        # one order for one set of formats: "svg,json" and "json,svg" are the same outputs (the
        # manifest compares the lists, and a rerun redid every input)
        f.sort(key=lambda x: _FORMAT_ORDER.get(x, len(_FORMAT_ORDER)))
        lists.append(f)
    try:
        size = operator.index(batch_size)           # int, numpy integers
    except TypeError:
        size = None
    if size is None or isinstance(batch_size, bool) or not 1 <= size <= MAX_BATCH_SIZE:
        raise RunError(f"batch size must be an integer in [1, {MAX_BATCH_SIZE}], got {batch_size!r:.50}")
    if image_options is not None and not isinstance(image_options, ImageOptions):
        raise RunError(f"image_options: expected an ImageOptions, got {type(image_options).__name__}")
    return inputs, lists[0], lists[1]


def run_inputs(inputs: Iterable[PathLike], config: ReconstructConfig, out_dir: PathLike,
               formats: Sequence[str] = DEFAULT_FORMATS, image_formats: Sequence[str] = DEFAULT_IMAGE_FORMATS,
               overwrite: bool = False, batch_size: int = 64, image_options: ImageOptions = ImageOptions(),
               image_config: Optional[ReconstructConfig] = None, device: Union[str, torch.device] = "cpu",
               progress: Optional[Callable[[Record], None]] = None,
               on_batch: Optional[Callable[[str, int, int, int, int], None]] = None,
               on_note: Optional[Callable[[str], None]] = None,
               stems: Optional[Sequence[str]] = None,
               on_result: Optional[Callable[[Record, Any], None]] = None) -> RunReport:
    """Reconstruct every input and write its outputs (see the module docstring).

    Args:
        inputs: point files, images, folders of them.
        config: the config of point files.
        out_dir: output folder, created if needed.
        formats, image_formats: outputs of point files and of images, among
            :func:`torch_isc.io.chosen_formats`; images also get the formats that need the
            image (``overlay.png``).
        overwrite: redo inputs whose output set is complete (by default they are skipped: a
            complete set is one whose ``<stem>.manifest.json`` matches the input's bytes, the
            config and the formats, and whose files still have the hashes it lists).
        batch_size: inputs read and solved together.
        image_options: how images become points (:class:`ImageOptions`).
        image_config: the config of images (default
            ``images.image_config(config, mode=image_options.mode)``).
        device: torch device of the reconstructions.
        progress: ``progress(record)``, called once per input as soon as it is final.
        on_batch: ``on_batch(stage, batch, size, done, total)`` with ``stage`` ``"start"``
            before and ``"end"`` after each batch (``done`` of ``total`` inputs not skipped).
        on_note: ``on_note(message)`` for remarks that are not errors (renamed outputs, an
            all-foreground mask).
        stems: the output stem of each input (already expanded: one per file), instead of
            :func:`unique_stems` of this call's inputs; a caller that splits one run into
            several calls (:mod:`torch_isc.dataset`) passes the stems of the whole run.
        on_result: ``on_result(record, result)`` for each input done, after its outputs are
            written and before ``progress``: the :class:`~torch_isc.ReconstructionResult`
            itself (the results table of :mod:`torch_isc.dataset` reads its polylines).

    A folder that cannot be listed is one failed input (its record says why).

    Returns:
        a :class:`RunReport`: one :class:`Record` per input, in input order.

    Raises:
        RunError: bad arguments (an empty folder, a batch size below 1, an unknown format):
            nothing was written.
    """
    inputs, formats, image_formats = run_arguments(inputs, formats, image_formats, batch_size, image_options)
    config = _as_config(config)
    if image_config is not None:
        image_config = _as_config(image_config)
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError) as e:
        raise RunError(f"device {shown(device)}: {shown(one_line(e, type(e).__name__))[:200]}") from None
    if dev.type == "meta":
        raise RunError(f"device {shown(device)}: a meta device holds no values")
    known = chosen_formats() + formats_needing({"image"})
    for f in list(formats) + list(image_formats):
        if f not in known:
            raise RunError(f"unknown output format '{f}' (known: {', '.join(known)})")
    if image_options.mode not in ("mask", "edges"):
        raise RunError(f"image mode must be 'mask' or 'edges', got {image_options.mode!r}")
    listing: Dict[str, str] = {}
    sources = expand_inputs(inputs, listing, out_dir) if stems is None else resolved_inputs(inputs, listing)
    out = make_out_dir(out_dir)
    if image_config is None:
        image_config = images.image_config(config, mode=image_options.mode)
    run = _Run(config, image_config, out, list(formats), list(image_formats), batch_size, image_options,
               torch.device(device), progress, on_batch, on_note, on_result)
    if stems is None:
        stems = unique_stems(sources, run.note)
    elif len(stems) != len(sources):
        raise RunError(f"{len(stems)} stem(s) given for {len(sources)} input(s)")
    else:
        # a stem names files inside out_dir: "../x" or "a/b" would write elsewhere, two equal
        # stems would overwrite each other's outputs
        for st in stems:
            if (not isinstance(st, str) or st in ("", ".", "..") or "/" in st or "\0" in st
                    or (os.altsep is not None and os.altsep in st) or os.sep in st):
                raise RunError(f"stems: {shown(st)!r} is not a file name inside the output folder")
        dup = [st for st, n in Counter(stems).items() if n > 1]
        if dup:
            raise RunError(f"stems: {shown(dup[0])!r} is given to more than one input")
    jobs = [_Job(Record(src, stem), _is_image(src)) for src, stem in zip(sources, stems)]
    clobber = overwritten_inputs(sources, stems, out, lambda src: run.image_formats if _is_image(src) else run.formats)

    # ---- folders that cannot be listed; finished inputs (a manifest that matches) are skipped
    todo: List[_Job] = []
    for i, job in enumerate(jobs):
        if job.source in listing:
            run.finish(job, "failed", listing[job.source])
        elif i in clobber:
            run.finish(job, "failed", clobber[i])
        elif not overwrite and run.complete(job):
            run.finish(job, "skipped")
        elif not overwrite and (owner := run.owner(job)) is not None:
            run.finish(job, "failed", f"{shown(job.source)}: its output set '{job.stem}' in {shown(out)} was made from "
                                      f"another input, {shown(owner)}; give --overwrite (overwrite=True) to replace it, "
                                      f"or another output folder")
        else:
            todo.append(job)

    # ---- read inputs as batches fill up (bounded memory), solve, export at once
    run.total = len(todo)
    batch: List[_Job] = []
    for i, job in enumerate(todo):
        if run.read_isolated(job):
            batch.append(job)
        if len(batch) == batch_size or (i == len(todo) - 1 and batch):
            run.process(batch)
            batch = []
    return RunReport([j.record for j in jobs], run.batches)
