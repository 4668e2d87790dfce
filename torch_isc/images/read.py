"""Image files decoded as grayscale arrays.

Before anything is decoded, the header is read (PNG, JPEG, BMP, TIFF: :func:`image_header`):
an image of more than ``max_pixels`` pixels (default :data:`DEFAULT_MAX_PIXELS`, 100
megapixels) is rejected without allocating it (a 168 KB 1-bit PNG can declare 32000x32000
pixels), a TIFF of several pages is rejected (only single images are read), and the EXIF
orientation (JPEG APP1, PNG ``eXIf``; OpenCV applies a TIFF's itself) is applied after
decoding, as a viewer shows the image. Other formats OpenCV decodes have their size checked after decoding (OpenCV itself refuses
more than 2**30 pixels).
"""
from __future__ import annotations

import operator
import os
import struct
import sys
import tempfile
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterator, Optional, Union

import numpy as np

from torch_isc._helpers import import_cv2, read_file_bytes
from torch_isc.images.arrays import ImageError

__all__ = ["IMAGE_SUFFIXES", "DEFAULT_MAX_PIXELS", "ImageHeader", "image_header", "read_image", "decode_image"]

#: File suffixes read as images (lower case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".gif", ".webp")
#: The largest image read, in pixels (width x height), unless the caller sets another limit.
DEFAULT_MAX_PIXELS = 100_000_000


@dataclass(frozen=True)
class ImageHeader:
    """What an image file's header says: ``width``, ``height``, ``pages`` (TIFF pages, animated
    PNG frames), the EXIF
    ``orientation`` (1-8, 1 when absent) and the ``format`` name."""
    format: str
    width: int
    height: int
    pages: int = 1
    orientation: int = 1


def _exif_orientation(tiff: bytes) -> int:
    """The orientation tag (274) of the first IFD of a TIFF/EXIF byte block; 1 when absent."""
    try:
        end = {b"II": "<", b"MM": ">"}[tiff[:2]]
        off = struct.unpack(end + "I", tiff[4:8])[0]
        n = struct.unpack(end + "H", tiff[off:off + 2])[0]
        for i in range(min(n, 4096)):
            e = off + 2 + 12 * i
            tag, typ = struct.unpack(end + "HH", tiff[e:e + 4])
            if tag == 274:
                v = struct.unpack(end + "H", tiff[e + 8:e + 10])[0] if typ == 3 else \
                    struct.unpack(end + "I", tiff[e + 8:e + 12])[0]
                return v if 1 <= v <= 8 else 1
    except (KeyError, struct.error, IndexError):
        pass
    return 1


def _tiff_header(b: bytes) -> Optional[ImageHeader]:
    end = {b"II": "<", b"MM": ">"}[b[:2]]
    if struct.unpack(end + "H", b[2:4])[0] != 42:
        return None                                   # BigTIFF (43) and others: not parsed
    off = struct.unpack(end + "I", b[4:8])[0]
    pages, seen, first = 0, set(), None
    while off and off not in seen and pages < 100_000:
        seen.add(off)
        n = struct.unpack(end + "H", b[off:off + 2])[0]
        w = h = None
        for i in range(n):
            e = off + 2 + 12 * i
            tag, typ = struct.unpack(end + "HH", b[e:e + 4])
            if tag in (256, 257):
                v = struct.unpack(end + "H", b[e + 8:e + 10])[0] if typ == 3 else struct.unpack(end + "I", b[e + 8:e + 12])[0]
                w, h = (v, h) if tag == 256 else (w, v)
        if first is None:
            first = (w, h)
        pages += 1
        off = struct.unpack(end + "I", b[off + 2 + 12 * n:off + 6 + 12 * n])[0]
    if first is None or first[0] is None or first[1] is None:
        return None
    return ImageHeader("tiff", first[0], first[1], pages, _exif_orientation(b))


def _png_header(b: bytes) -> Optional[ImageHeader]:
    if b[12:16] != b"IHDR":
        return None
    w, h = struct.unpack(">II", b[16:24])
    orient, frames, pos = 1, 1, 8
    while pos + 8 <= len(b):                          # eXIf and acTL chunks come before the image data
        ln, typ = struct.unpack(">I4s", b[pos:pos + 8])
        if typ == b"eXIf":
            orient = _exif_orientation(b[pos + 8:pos + 8 + ln])
        elif typ == b"acTL":                          # an animated PNG: its number of frames
            frames = max(1, struct.unpack(">I", b[pos + 8:pos + 12])[0])
        elif typ in (b"IDAT", b"IEND"):
            break
        pos += 12 + ln
    return ImageHeader("png", w, h, frames, orient)


def _jpeg_header(b: bytes) -> Optional[ImageHeader]:
    pos, orient = 2, 1
    while pos + 4 <= len(b):
        if b[pos] != 0xFF:
            return None
        marker = b[pos + 1]
        if marker == 0xFF:                            # fill byte
            pos += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            pos += 2
            continue
        ln = struct.unpack(">H", b[pos + 2:pos + 4])[0]
        if marker == 0xE1 and b[pos + 4:pos + 10] == b"Exif\x00\x00":
            orient = _exif_orientation(b[pos + 10:pos + 2 + ln])
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            h, w = struct.unpack(">HH", b[pos + 5:pos + 9])
            return ImageHeader("jpeg", w, h, 1, orient)
        if marker == 0xDA:                            # start of scan before any frame header
            return None
        pos += 2 + ln
    return None


def _bmp_header(b: bytes) -> Optional[ImageHeader]:
    size = struct.unpack("<I", b[14:18])[0]
    if size == 12:
        w, h = struct.unpack("<HH", b[18:22])
    else:
        w, h = struct.unpack("<ii", b[18:26])
    return ImageHeader("bmp", abs(w), abs(h))


def _gif_header(b: bytes) -> Optional[ImageHeader]:
    """The logical screen's size and the number of frames (image descriptors; the walk stops at
    the second: an animation is refused whatever its length)."""
    w, h = struct.unpack("<HH", b[6:10])
    pos = 13 + (3 << ((b[10] & 7) + 1) if b[10] & 0x80 else 0)      # the global colour table
    frames = 0
    while pos < len(b) and frames < 2:
        tag = b[pos]
        if tag == 0x3B:                               # trailer
            break
        if tag == 0x21:                               # extension: label, then data sub-blocks
            pos += 2
        elif tag == 0x2C:                             # image descriptor (+ local colour table, LZW size)
            frames += 1
            flags = b[pos + 9]
            pos += 10 + (3 << ((flags & 7) + 1) if flags & 0x80 else 0) + 1
        else:
            return None
        while pos < len(b) and b[pos]:                # sub-blocks up to the empty one
            pos += 1 + b[pos]
        pos += 1
    return ImageHeader("gif", w, h, max(frames, 1))


def _webp_header(b: bytes) -> Optional[ImageHeader]:
    """A WebP's canvas size (``VP8 `` lossy, ``VP8L`` lossless, ``VP8X`` extended) and, for an
    animation, its number of ``ANMF`` frames."""
    kind = b[12:16]
    if kind == b"VP8 " and b[23:26] == b"\x9d\x01\x2a":
        w, h = struct.unpack("<HH", b[26:30])
        return ImageHeader("webp", w & 0x3FFF, h & 0x3FFF)
    if kind == b"VP8L" and b[20] == 0x2F:
        v = struct.unpack("<I", b[21:25])[0]
        return ImageHeader("webp", (v & 0x3FFF) + 1, ((v >> 14) & 0x3FFF) + 1)
    if kind == b"VP8X":
        w = int.from_bytes(b[24:27], "little") + 1
        h = int.from_bytes(b[27:30], "little") + 1
        frames, pos = 1, 12
        if b[20] & 0x02:                              # the animation flag: count the frames
            frames = 0
            while pos + 8 <= len(b):
                ln = struct.unpack("<I", b[pos + 4:pos + 8])[0]
                frames += b[pos:pos + 4] == b"ANMF"
                pos += 8 + ln + (ln & 1)
        return ImageHeader("webp", w, h, max(frames, 1))
    return None


def image_header(data: bytes) -> Optional[ImageHeader]:
    """The :class:`ImageHeader` of a PNG, JPEG, BMP, TIFF, GIF or WebP file's bytes, read without decoding;
    None for other formats or a header that cannot be parsed.

    >>> import cv2
    >>> image_header(cv2.imencode(".png", np.zeros((2, 3), np.uint8))[1].tobytes())
    ImageHeader(format='png', width=3, height=2, pages=1, orientation=1)
    """
    b = bytes(data[:1 << 20]) if len(data) > (1 << 20) else bytes(data)
    try:
        if b.startswith(b"\x89PNG\r\n\x1a\n"):
            return _png_header(b)
        if b.startswith(b"\xff\xd8"):
            return _jpeg_header(b)
        if b.startswith(b"BM") and len(b) >= 26:
            return _bmp_header(b)
        if b[:2] in (b"II", b"MM"):
            return _tiff_header(bytes(data))          # page offsets may lie anywhere in the file
        if b[:6] in (b"GIF87a", b"GIF89a") and len(b) >= 13:
            return _gif_header(bytes(data))           # frames may follow a large first one
        if b[:4] == b"RIFF" and b[8:12] == b"WEBP":
            return _webp_header(bytes(data))
    except (struct.error, IndexError, KeyError):
        return None
    return None


def _orient(img: np.ndarray, orientation: int) -> np.ndarray:
    """Apply an EXIF orientation (1-8) to a decoded ``(H, W[, C])`` image."""
    ops = {2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
           5: lambda a: np.swapaxes(a, 0, 1), 6: lambda a: np.rot90(a, -1),
           7: lambda a: np.rot90(a, 1)[:, ::-1], 8: lambda a: np.rot90(a, 1)}
    return np.ascontiguousarray(ops[orientation](img)) if orientation in ops else img


_STDERR_LOCK = threading.Lock()
#: what libjpeg says (on the process's stderr, past OpenCV) when it decodes a damaged file anyway:
#: the missing part grey, or garbage after flipped bits ("N extraneous bytes before marker")
_JPEG_DAMAGE = ("Corrupt JPEG data", "Premature end of JPEG file")


@contextmanager
def _native_stderr() -> Iterator[Dict[str, str]]:
    """Capture what native code (libjpeg, libpng) writes to file descriptor 2 meanwhile:
    ``box["text"]`` after the block. libjpeg only *warns* there when it decodes a damaged
    file (the rest filled in grey), and libpng's errors would add lines to our one-line
    messages. Nothing is captured when descriptor 2 cannot be duplicated."""
    box = {"text": ""}
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield box
        return
    with _STDERR_LOCK:
        try:
            with tempfile.TemporaryFile() as tmp:
                os.dup2(tmp.fileno(), 2)
                try:
                    yield box
                finally:
                    os.dup2(saved, 2)
                    tmp.seek(0)
                    box["text"] = tmp.read(1 << 16).decode("utf-8", "replace")
        finally:
            os.close(saved)


def _decodes(cv2, fmt: str) -> bool:
    """Whether this OpenCV build decodes ``fmt`` ("gif", "webp"): a 1x1 image of it."""
    tiny = {"gif": b'GIF87a\x01\x00\x01\x00\x81\x00\x00\xff\xff\xff\x00\x00\x00\x00\x00\x00\x00\x00\x00,\x00\x00\x00\x00\x01\x00\x01\x00\x00\x08\x04\x00\x01\x04\x04\x00;',
            "webp": b'RIFF\x1e\x00\x00\x00WEBPVP8L\x11\x00\x00\x00/\x00\x00\x00\x00\x07\xd0\xff\xfe\xf7\xbf\xff\x81\x88\xe8\x7f\x00\x00'}
    try:
        return cv2.imdecode(np.frombuffer(tiny[fmt], np.uint8), cv2.IMREAD_UNCHANGED) is not None
    except cv2.error:
        return False


def _check_size(p: object, w: int, h: int, max_pixels: Optional[int]) -> None:
    if max_pixels is not None and w * h > max_pixels:
        raise ImageError(f"{p}: image too large: {w}x{h} pixels ({w * h / 1e6:.4g} megapixels), above the limit "
                         f"of {max_pixels / 1e6:.4g} megapixels (max_pixels, --max-pixels)")


def _unit_range(img: np.ndarray, p: object) -> np.ndarray:
    """``img`` as float32 in [0, 1]: uint8 by 255, uint16 by ``2^k - 1`` for the k bits its
    largest value needs (8 to 16: 12-bit data stored in 16 bits reads as full range), floats
    within [0, 1] as they are; other types (int8/16/32/64, uint32/64: no standard full scale, a
    TIFF of counts or labels) and floats outside [0, 1] by the data's own range, min to max (a
    constant image reads as 0). Before, an int32 TIFF was divided by 2^31 - 1: no edges, no mask."""
    if img.dtype == np.uint8:
        return img.astype(np.float32) / np.float32(255.0)
    if img.dtype == np.uint16:
        # by the bit depth the data uses, at least 8: 10-, 12- and 14-bit sensors and scanners
        # store into 16 bits (a 12-bit image divided by 65535 would be black: no edges)
        bits = max(8, int(img.max()).bit_length())
        return img.astype(np.float32) / np.float32((1 << bits) - 1)
    if img.dtype == np.bool_:
        return img.astype(np.float32)
    if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
        raise ImageError(f"{p}: unsupported pixel type {img.dtype}")
    if np.issubdtype(img.dtype, np.floating) and not np.isfinite(img).all():
        raise ImageError(f"{p}: image has NaN or Inf values")
    chans = img[..., :3] if img.ndim == 3 and img.shape[2] in (3, 4) else img      # alpha keeps its own scale
    lo, hi = float(chans.min()), float(chans.max())
    if np.issubdtype(img.dtype, np.floating) and lo >= 0.0 and hi <= 1.0:
        return img.astype(np.float32)
    g = img.astype(np.float64)
    if chans is not img:
        alpha = g[..., 3:]
        amax = float(alpha.max())
        alpha = alpha / amax if amax > 1.0 else alpha            # an integer alpha: opaque is its largest value
        g = np.concatenate([(g[..., :3] - lo) / (hi - lo) if hi > lo else np.zeros_like(g[..., :3]), alpha], 2)
    else:
        g = (g - lo) / (hi - lo) if hi > lo else np.zeros_like(g)
    return g.astype(np.float32)


def read_image(path: Union[str, os.PathLike], max_pixels: Optional[int] = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Read an image file as grayscale ``(H, W)`` float32 in ``[0, 1]`` (see :func:`decode_image`).

    Raises:
        ImageError: missing file, unreadable / truncated / not an image, larger than
            ``max_pixels`` (None: no limit), several pages (one line, naming it).
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ImageError(f"read_image: expected a path (str or path object), got {type(path).__name__}"
                         + (" (for the file's bytes: decode_image)" if isinstance(path, (bytes, bytearray)) else ""))
    p = Path(path)
    return decode_image(read_file_bytes(p, ImageError, "an image"), p, max_pixels=max_pixels)


def decode_image(data: bytes, name: object = "image", max_pixels: Optional[int] = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """The bytes of an image file (any format OpenCV decodes) as grayscale ``(H, W)`` float32
    in ``[0, 1]``; ``name`` (e.g. the path) starts every error message.

    Colour is converted to gray (OpenCV weights); an alpha channel, when present and not
    fully opaque, multiplies the gray value (a transparent background reads as black), except
    when the colour is the same wherever alpha > 0 (a one-colour icon, black glyph on
    transparent): then the image is the alpha channel itself (opaque reads as white).
    8-bit images are scaled to ``[0, 1]`` by 255, 16-bit ones by the bit depth they use (8 to
    16 bits: 12-bit data stored in 16 bits is full range), floats in ``[0, 1]``
    kept, other pixel types (signed, 32-bit) and floats beyond ``[0, 1]`` by their own min and max. The header is checked first
    (module docstring): more than ``max_pixels`` pixels (None: no limit) or several TIFF pages
    raise :class:`ImageError`; the EXIF orientation is applied.

    >>> import cv2
    >>> decode_image(cv2.imencode(".png", np.full((2, 3), 255, np.uint8))[1].tobytes()).tolist()
    [[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ImageError(f"decode_image: expected the file's bytes, got {type(data).__name__}")
    if max_pixels is not None:
        try:
            ok = operator.index(max_pixels) >= 0 and not isinstance(max_pixels, bool)
        except TypeError:
            ok = False
        if not ok:
            raise ImageError(f"max_pixels must be None or an integer >= 0 (0: no limit), got {max_pixels!r:.30}")
        max_pixels = operator.index(max_pixels) or None
    cv2 = import_cv2()
    p = name
    raw = np.frombuffer(data, dtype=np.uint8)
    if raw.size == 0:
        raise ImageError(f"{p}: empty file, not an image")
    head = image_header(data)
    if head is not None:
        _check_size(p, head.width, head.height, max_pixels)
        if head.pages > 1:
            kind, unit = ((f"animated {head.format.upper().replace('WEBP', 'WebP')}", "frames")
                          if head.format != "tiff" else ("multi-page TIFF", "pages"))
            raise ImageError(f"{p}: {kind} ({head.pages} {unit}): only single images are read "
                             f"(split the {unit} first)")
    img = None
    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)     # a corrupt file is reported once, by us, not by OpenCV too
    try:
        with _native_stderr() as said:
            try:
                img = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
            except cv2.error:
                img = None
    finally:
        log.setLogLevel(level)
    if img is None or img.size == 0:
        if head is not None and head.format in ("gif", "webp") and not _decodes(cv2, head.format):
            raise ImageError(f"{p}: this OpenCV ({cv2.__version__}) cannot decode {head.format.upper()} images "
                             f"(GIF needs OpenCV 4.11 or later); convert it to PNG")
        raise ImageError(f"{p}: not a readable image (unknown format, truncated or corrupt)")
    damage = [ln.strip() for ln in said["text"].splitlines() if ln.strip().startswith(_JPEG_DAMAGE)]
    if damage:
        raise ImageError(f"{p}: truncated or corrupt JPEG (libjpeg: {damage[0][:120]})")
    if said["text"].strip():                       # a decoder's other warnings: pass them on
        sys.stderr.write(said["text"] if said["text"].endswith("\n") else said["text"] + "\n")
    _check_size(p, int(img.shape[1]), int(img.shape[0]), max_pixels)
    if head is not None and head.orientation != 1 and head.format in ("jpeg", "png"):
        img = _orient(img, head.orientation)        # OpenCV's TIFF decoder applies it itself
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    g = _unit_range(img, p)
    if g.ndim == 3 and g.shape[2] in (2, 3, 4):
        alpha = g[:, :, -1] if g.shape[2] in (2, 4) else None
        g = g[:, :, 0] if g.shape[2] == 2 else cv2.cvtColor(np.ascontiguousarray(g[:, :, :3]), cv2.COLOR_BGR2GRAY)
        if alpha is not None and (alpha < 1).any():
            seen = g[alpha > 0]
            if seen.size == 0 or float(seen.max() - seen.min()) <= 1.0 / 255.0:
                g = alpha                   # one colour everywhere it shows: the shape is the alpha
            else:
                g = g * alpha               # composited on black
    if not np.isfinite(g).all():
        raise ImageError(f"{p}: image has NaN or Inf values")
    if g.ndim != 2:
        raise ImageError(f"{p}: unsupported image layout {tuple(img.shape)}")
    return np.ascontiguousarray(np.clip(g, 0.0, 1.0), dtype=np.float32)

