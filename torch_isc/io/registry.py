"""The registries: :data:`LOADERS` (file suffix -> how the file is read) and :data:`EXPORTERS`
(format name -> how a result is encoded), in the manner of trimesh's exchange modules.

An exporter only *encodes*: it writes the bytes of one format into a binary file object.
:func:`export` is the one place that writes files, each through
:func:`~torch_isc.io.files.atomic_write`. What an exporter needs besides the result (the y
direction, the source image of an overlay) comes from an :class:`ExportContext`; an exporter
that needs a context field (``needs``) is written only where the context has it.

Example:
    >>> sorted(EXPORTERS)[:3], LOADERS[".npy"].kind, LOADERS[".png"].kind
    (['contours.npz', 'geojson', 'json'], 'points', 'image')
"""
from __future__ import annotations

import hashlib
import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Callable, Dict, Iterable, List, Optional, Tuple

import numpy as np

from torch_isc.images import IMAGE_SUFFIXES, ImageLike, read_image
from torch_isc.io import npy, points_text
from torch_isc.io.contours import encode_contours
from torch_isc.io.errors import PointFileError
from torch_isc.io.files import PathLike, atomic_write, read_file_bytes
from torch_isc.io.geojson import encode_geojson
from torch_isc.io.json import encode_json
from torch_isc.io.npz import encode_npz
from torch_isc.io.overlay import encode_overlay
from torch_isc.io.png import encode_png
from torch_isc.io.svg import encode_svg

__all__ = ["read_points", "Loader", "LOADERS", "loader_for", "ExportContext", "Exporter", "EXPORTERS",
           "chosen_formats", "formats_needing", "export"]


# =============================================================================== reading
def read_points(path: PathLike, data: Optional[bytes] = None) -> np.ndarray:
    """Read a point set.

    Args:
        path: a text file of ``x y`` rows (whitespace- or comma-separated; ``#`` starts a
            comment; blank lines are skipped; the first data line may be a header of
            non-numeric words such as ``x,y``; ``;`` separates too; :mod:`~torch_isc.io.points_text`), or a ``.npy``
            file holding a numeric ``(N, 2)`` array (:mod:`~torch_isc.io.npy`). A file that
            starts with the ``.npy`` magic is read as ``.npy`` whatever its extension; any other
            suffix is read as text.

    Returns:
        points: ``(N, 2)`` float64, C-contiguous. ``N`` may be 1 or 2: whether that is enough
        is for the reconstruction to decide.

    Raises:
        PointFileError: missing or unreadable file, no points, non-numeric text (with the line
            number), a row without exactly 2 columns (with the line number and the count), a
            ``.npy`` of the wrong shape or dtype or truncated, NaN/Inf coordinates (with the count).

    ``data``: the file's bytes when the caller has read them already (``path`` then only names
    the file and chooses the format), so what is decoded is what the caller hashed.
    """
    p = Path(path)
    raw = read_file_bytes(p, PointFileError, "a point file") if data is None else bytes(data)
    as_npy = npy.is_npy(raw) or p.suffix.lower() in npy.SUFFIXES
    suffix = p.suffix.lower()
    if not as_npy and suffix not in points_text.SUFFIXES and (
            raw.startswith(b"PK\x03\x04") or (b"\x00" in raw[:4096] and raw[:2] not in (b"\xff\xfe", b"\xfe\xff"))):
        # a binary file of another suffix (an .npz archive, a .gif): say what is read, not "byte 16 is not UTF-8"
        what = "a .npz archive" if raw.startswith(b"PK\x03\x04") else f"a binary {suffix or 'suffix-less'} file"
        if suffix in IMAGE_SUFFIXES:
            raise PointFileError(f"{p}: an image ({suffix}), not a point file: read it with read_image or the CLI")
        raise PointFileError(f"{p}: {what}, neither a point file (.xy/.txt/.csv text rows, a .npy array) nor an "
                             f"image read here ({'/'.join(IMAGE_SUFFIXES)})")
    pts, rows = (npy.decode_points if as_npy else points_text.decode_points)(p, raw)
    bad = ~np.isfinite(pts)
    if bad.any():
        nbad = int(bad.any(1).sum())
        first = int(np.flatnonzero(bad.any(1))[0])
        where = f"line {int(rows[first])}" if rows is not None else f"array row {first}"
        raise PointFileError(f"{p}: {nbad} point(s) have NaN or Inf coordinates (first at {where})")
    return np.ascontiguousarray(pts, dtype=np.float64)


@dataclass(frozen=True)
class Loader:
    """How files of one suffix are read.

    Attributes:
        kind: ``"points"`` (``load`` gives ``(N, 2)`` float64) or ``"image"`` (``load`` gives a
            gray ``(H, W)`` float32 image in ``[0, 1]``).
        load: ``load(path) -> array``; raises a one-line error naming the file.
        decode: ``decode(path, data) -> array`` from bytes already read (``path`` names the
            file), or None: a caller that hashes the input decodes the very bytes it hashed.
    """
    kind: str
    load: Callable[[PathLike], np.ndarray]
    decode: Optional[Callable[[PathLike, bytes], np.ndarray]] = None


_POINTS = Loader("points", read_points, lambda path, data: read_points(path, data=data))
_IMAGE = Loader("image", read_image)

#: Suffix (lower case, with the dot) -> :class:`Loader`, point formats first: the suffixes
#: picked up from a folder.
LOADERS: Dict[str, Loader] = {
    **{s: _POINTS for s in points_text.SUFFIXES + npy.SUFFIXES},
    **{s: _IMAGE for s in IMAGE_SUFFIXES},
}


def loader_for(path: PathLike) -> Loader:
    """The loader of ``path``'s suffix; a file of another suffix is read as a point file."""
    return LOADERS.get(Path(path).suffix.lower(), _POINTS)


# =============================================================================== writing
@dataclass(frozen=True)
class ExportContext:
    """What exporters may need besides the result.

    Attributes:
        y_down: the coordinates are image pixels (y pointing down): drawings are not flipped.
        image: the source image (gray ``(H, W)`` or BGR ``(H, W, 3)``) of an image input.
        zoom, region: of ``overlay.png``: an integer zoom, and the part of the image shown
            (``(x0, y0, x1, y1)`` pixels, None: all; :func:`~torch_isc.io.render_overlay`).
    """
    y_down: bool = False
    image: Optional[ImageLike] = None
    zoom: int = 1
    region: Optional[Tuple[int, int, int, int]] = None


@dataclass(frozen=True)
class Exporter:
    """One output format.

    Attributes:
        encode: ``encode(result, fh, context)`` writes the format's bytes into the binary file
            object ``fh``.
        needs: the :class:`ExportContext` fields the format cannot do without (e.g.
            ``("image",)``); formats that need nothing can be asked for any result.
    """
    encode: Callable[[Any, BinaryIO, ExportContext], None]
    needs: Tuple[str, ...] = ()

    def missing(self, context: ExportContext) -> List[str]:
        """The needed context fields that ``context`` leaves unset."""
        return [n for n in self.needs if getattr(context, n) is None]


def _json(result, fh: BinaryIO, context: ExportContext) -> None:
    encode_json(result, fh)


def _npz(result, fh: BinaryIO, context: ExportContext) -> None:
    encode_npz(result, fh)


def _svg(result, fh: BinaryIO, context: ExportContext) -> None:
    encode_svg(result, fh, y_down=context.y_down)


def _png(result, fh: BinaryIO, context: ExportContext) -> None:
    encode_png(result, fh, y_down=context.y_down)


def _geojson(result, fh: BinaryIO, context: ExportContext) -> None:
    encode_geojson(result, fh)


def _contours(result, fh: BinaryIO, context: ExportContext) -> None:
    encode_contours(result, fh)


def _overlay(result, fh: BinaryIO, context: ExportContext) -> None:
    encode_overlay(result, fh, context.image, scale=context.zoom, region=context.region)


#: Format name -> :class:`Exporter`; :func:`export` writes ``<stem>.<format>``.
EXPORTERS: Dict[str, Exporter] = {
    "json": Exporter(_json),
    "npz": Exporter(_npz),
    "svg": Exporter(_svg),
    "png": Exporter(_png),
    "contours.npz": Exporter(_contours),
    "geojson": Exporter(_geojson),
    "overlay.png": Exporter(_overlay, needs=("image",)),
}


def chosen_formats() -> List[str]:
    """The formats a user chooses among: those that need nothing beyond the result."""
    return [f for f, e in EXPORTERS.items() if not e.needs]


def formats_needing(available: Iterable[str]) -> List[str]:
    """The formats that need context, all of it among ``available`` (e.g. ``{"image"}``): the
    outputs an input that brings this context gets in addition to the chosen ones."""
    have = set(available)
    return [f for f, e in EXPORTERS.items() if e.needs and set(e.needs) <= have]


def export(result, path_stem: PathLike, formats: Iterable[str] = ("json", "npz", "svg", "png"),
           y_down: bool = False, image: Optional[ImageLike] = None,
           context: Optional[ExportContext] = None, fsync: bool = True,
           digests: Optional[List[Tuple[str, int]]] = None) -> List[Path]:
    """Write ``result`` as ``<path_stem>.<fmt>`` for every format, each write atomic.

    Args:
        y_down: the coordinates are image pixels (y pointing down): SVG and PNG are drawn
            without flipping y, so they look like the image.
        image: the source image, for ``overlay.png``.
        context: an :class:`ExportContext` instead of ``y_down`` and ``image``.
        fsync: sync each file to disk before its move (see :func:`~torch_isc.io.files.atomic_write`).
        digests: a list to which ``(sha256 hex, size in bytes)`` of each written file is
            appended, in the order of ``formats``: each file is then encoded in memory and
            hashed from there, not read back (the batch runner's manifests).

    Returns:
        the written paths, in the order of ``formats``.

    Raises:
        ValueError: an unknown format, or one whose context is missing (before anything is
            written). OSError from the writes.
    """
    formats = list(formats)
    ctx = context if context is not None else ExportContext(y_down=y_down, image=image)
    unknown = [f for f in formats if f not in EXPORTERS]
    if unknown:
        raise ValueError(f"unknown output format '{unknown[0]}' (known: {', '.join(EXPORTERS)})")
    for f in formats:
        missing = EXPORTERS[f].missing(ctx)
        if missing:
            raise ValueError(f"output format '{f}' needs the {missing[0]} (not given)")
    stem = os.fspath(path_stem)
    out = []
    for f in formats:
        enc = EXPORTERS[f].encode
        if digests is None:
            out.append(atomic_write(Path(f"{stem}.{f}"), lambda fh, enc=enc: enc(result, fh, ctx), fsync))
            continue
        buf = io.BytesIO()
        enc(result, buf, ctx)
        data = buf.getvalue()
        out.append(atomic_write(Path(f"{stem}.{f}"), data, fsync))
        digests.append((hashlib.sha256(data).hexdigest(), len(data)))
    return out
