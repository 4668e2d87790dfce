"""Point sets as text: ``x y``, ``x,y`` or ``x;y`` rows, ``#`` comments, blank lines, one
optional header line of words (e.g. ``x,y``); fields may be quoted (``"1.5","2"``). A decimal comma (``1,5;2,5``) is not read as one:
such a row has four fields and is refused with its line number."""
from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import Iterator, List, Optional, Tuple

import numpy as np

from torch_isc._helpers import decode_text
from torch_isc.io.errors import PointFileError

__all__ = ["SUFFIXES", "decode_points"]

#: Suffixes of text point files picked up from a folder (any file given by name is tried as text).
SUFFIXES = (".xy", ".txt", ".csv")

_FIELD_SPLIT = re.compile(r"\s*[,;]\s*|\s+")
_COMMENT = re.compile(r"#[^\n]*")
_FIRST_LINE = re.compile(r"^[ \t\f\v]*(\S[^\n]*)$", re.M)
_QUOTED = re.compile(r'"([^"\n]*)"')
_NON_ASCII_DIGIT = re.compile(r"(?![0-9])\d")
# an empty field: a separator first on a line, or followed by another or by the line's end (two
# patterns that each start on a literal scan 2-3x faster than one with alternatives)
_EMPTY_FIELD = (re.compile(r"^[ \t]*[,;]", re.M), re.compile(r"[,;][ \t]*(?:[,;]|\n|\Z)"))


def _is_number(tok: str) -> bool:
    if "_" in tok:            # Python's float reads "1_000" as 1000; numpy (the fast path) does not
        return False
    try:
        float(tok)
    except ValueError:
        return False
    return True


def decode_points(p: Path, raw: bytes) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """Text rows -> ``(points (N, 2) float64, line numbers (N,) or None)``; ``p`` names the file
    in messages.

    Fast path: comments are cut and the header blanked with regexes over the whole text, then
    numpy parses all rows at once (blank lines skipped). Only when that fails, or when a row
    number is needed for a message, are the lines walked one by one.

    >>> decode_points(Path("a.xy"), b"x,y\\n1,2\\n3 4  # comment\\n")[0].tolist()
    [[1.0, 2.0], [3.0, 4.0]]
    """
    text = decode_text(raw, str(p), "text point file", PointFileError)
    # each pass copies the whole text: only those the text needs
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    if "#" in text:
        text = _COMMENT.sub("", text)
    if '"' in text:
        text = _QUOTED.sub(r"\1", text)          # "1.5","2" (spreadsheets quote every field)
    first = _FIRST_LINE.search(text)
    if first is None:
        raise PointFileError(f"{p}: no points (the file has no data lines)")
    toks = _FIELD_SPLIT.split(first.group(1).strip())
    line = first.group(1).strip()
    if text.strip() == line and all(tok and not _is_number(tok) for tok in toks):
        shown = line if len(line) <= 40 else line[:37] + "..."
        raise PointFileError(f"{p}: no points (its one line {shown!r} is not numbers; expected rows of x y)")
    if all(tok and not _is_number(tok) and (tok[0].isalpha() or tok[0] == "_") for tok in toks):
        # a header line of names (a letter or _ first; 1D2, 0x1p0 or 10% are malformed numbers,
        # refused with their line, not a header dropped): blank it, keeping the line count
        header = first.group(1).strip()
        text = text[:first.start(1)] + text[first.end(1):]
        if not text.strip():
            shown = header if len(header) <= 40 else header[:37] + "..."
            raise PointFileError(f"{p}: no points (its one line {shown!r} is not numbers; expected rows of x y)")
    if not text.isascii():
        # Python's float reads Arabic-Indic or full-width digits, numpy's parser in part: refused
        m = _NON_ASCII_DIGIT.search(text)
        if m is not None:
            ch = m.group(0)
            raise PointFileError(f"{p}: line {text.count(chr(10), 0, m.start()) + 1}: non-ASCII digit {ch!r} "
                                 f"(U+{ord(ch):04X}); write numbers with the digits 0-9")
    pts: Optional[np.ndarray] = None
    # an empty field needs a separator: whitespace-only files skip the (slow, whole-text) search
    if not ("," in text or ";" in text) or not any(pat.search(text) for pat in _EMPTY_FIELD):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")          # "input contained no data"
                pts = np.loadtxt(_rows(text), dtype=np.float64, ndmin=2, comments=None)
        except ValueError:
            pts = None
    if pts is not None and pts.size == 0:
        raise PointFileError(f"{p}: no points (the file has no data lines)")
    if pts is None or pts.shape[1] != 2 or not np.isfinite(pts).all():
        return _parse_lines(p, text)
    return pts, None


def _rows(text: str, chunk: int = 1 << 18) -> Iterator[str]:
    """The lines of ``text`` with ``,`` and ``;`` as spaces, a chunk of about ``chunk`` characters
    at a time: numpy parses them as they come, and no whole copy of the text is made (a
    ``StringIO`` of it held four bytes a character, the file's size several times over)."""
    i, n = 0, len(text)
    while i < n:
        j = text.find("\n", min(i + chunk, n))
        j = n if j < 0 else j + 1
        # split at "\n" only: splitlines would also break at \f, \v or U+2028, making two rows of
        # one that the line-by-line path refuses
        yield from text[i:j].replace(",", " ").replace(";", " ").split("\n")
        i = j


def _parse_lines(p: Path, text: str) -> Tuple[np.ndarray, np.ndarray]:
    """The slow path: parse row by row, raising at the first bad line (1-based numbers)."""
    rows: List[Tuple[float, float]] = []
    line_no: List[int] = []
    for i, line in enumerate(text.split("\n")):
        s = line.strip()
        if not s:
            continue
        toks = _FIELD_SPLIT.split(s)
        for tok in toks:
            if tok == "":
                raise PointFileError(f"{p}: line {i + 1}: empty field")
            if not _is_number(tok):
                shown = tok if len(tok) <= 20 else tok[:17] + "..."
                raise PointFileError(f"{p}: line {i + 1}: non-numeric value {shown!r}")
        if len(toks) != 2:
            raise PointFileError(f"{p}: line {i + 1}: expected 2 columns (x y), found {len(toks)}")
        rows.append((float(toks[0]), float(toks[1])))
        line_no.append(i + 1)
    if not rows:
        raise PointFileError(f"{p}: no points (the file has no data lines)")
    return np.asarray(rows, dtype=np.float64), np.asarray(line_no, dtype=np.int64)
