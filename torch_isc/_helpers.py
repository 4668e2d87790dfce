"""Helpers shared by images, io, the runner and the CLI. This module imports nothing from
torch_isc, so every layer may use it without an import cycle."""
from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Optional, Union

__all__ = ["one_line", "import_cv2", "read_file_bytes", "decode_text", "MAX_FILE_BYTES", "is_regular_file", "printable", "load_npz_arrays", "npy_header"]


def finite_real(v: object) -> bool:
    """Whether ``v`` is a real number (Python or numpy; not a bool) that float64 holds as a
    finite value: an integer like ``2**70`` is, ``10**400`` (beyond float64) is not."""
    import math
    import numbers

    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        return False
    try:
        return math.isfinite(float(v))
    except (OverflowError, ValueError, TypeError):
        return False


def one_line(msg: object, default: str = "") -> str:
    """The first line of ``str(msg)`` stripped, or ``default`` when it is empty.

    >>> one_line(ValueError("bad\\nmore")), one_line(KeyError(), "KeyError")
    ('bad', 'KeyError')
    """
    lines = str(msg).strip().splitlines()
    return lines[0] if lines else default


def printable(name: object, limit: Optional[int] = None) -> str:
    """``str(name)`` as it is printed in a message: control characters (a newline in a file
    name) escaped, so a message stays one line; longer than ``limit`` characters: cut with "...".

    >>> printable("a\\nb.xy"), printable("x" * 10, limit=6)
    ('a\\\\nb.xy', 'xxx...')
    """
    t = str(name)
    if not t.isprintable():
        t = "".join(c if c.isprintable() else repr(c)[1:-1] for c in t)
    if limit is not None and len(t) > limit:
        t = t[:max(limit - 3, 0)] + "..."
    return t


def import_cv2():
    """OpenCV, imported on first use: only image input and PNG output need it."""
    import cv2

    return cv2


#: The largest input file read (point files, images, manifests): a clear error instead of the
#: out-of-memory kill that would end the whole run (2 GiB: about 80 million text points).
MAX_FILE_BYTES = 1 << 31

_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))


def read_file_bytes(path: Union[str, os.PathLike], error: type, what: str, limit: Optional[int] = MAX_FILE_BYTES,
                    too_large: str = "file") -> bytes:
    """The bytes of ``path``, or ``error`` with one line naming the file (missing, a folder,
    unreadable, not a regular file, larger than ``limit`` bytes); ``what`` names the expected
    kind of file (e.g. ``"a point file"``), ``too_large`` the file in the size message.

    Only regular files are read: a FIFO would block the run forever and ``/dev/zero`` would fill
    the memory. The FIFO is opened without waiting for a writer (``O_NONBLOCK``), then refused."""
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    except FileNotFoundError:
        if os.path.islink(p):
            raise error(f"{p}: a dangling symbolic link (to {os.readlink(p)!r}), not {what}") from None
        raise error(f"{p}: no such file") from None
    except IsADirectoryError:
        raise error(f"{p}: is a directory, not {what}") from None
    except OSError as e:
        raise error(f"{p}: cannot read ({e.strerror or e})") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise error(f"{p}: is a directory, not {what}")
        if not stat.S_ISREG(st.st_mode):
            kind = next((k for test, k in _KINDS if test(st.st_mode)), "a special file")
            raise error(f"{p}: not a regular file ({kind}), not {what}")
        if limit is not None and st.st_size > limit:
            raise error(f"{p}: {too_large} larger than {limit} bytes ({st.st_size} bytes)")
        with os.fdopen(fd, "rb") as fh:
            fd = -1
            raw = fh.read() if limit is None else fh.read(limit + 1)
    except OSError as e:
        raise error(f"{p}: cannot read ({e.strerror or e})") from None
    finally:
        if fd >= 0:
            os.close(fd)
    if limit is not None and len(raw) > limit:          # grew while being read
        raise error(f"{p}: {too_large} larger than {limit} bytes")
    return raw


def decode_text(raw: bytes, label: str, what: str, error: type) -> str:
    """``raw`` as UTF-8 text (a BOM allowed), or UTF-16 / UTF-32 when it starts with their BOM
    (what Windows editors and PowerShell write), or ``error`` saying ``"<label>: not a <what>"``
    and why (a byte that is not UTF-8, NUL bytes: a binary file)."""
    import codecs

    for bom, enc in ((codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"),
                     (codecs.BOM_UTF16_LE, "utf-16"), (codecs.BOM_UTF16_BE, "utf-16")):
        if raw.startswith(bom):
            try:
                text = raw.decode(enc).removeprefix("\ufeff")
            except UnicodeDecodeError as e:
                raise error(f"{label}: not a {what} (byte {e.start} is not {enc.upper()})") from None
            break
    else:
        try:
            text = raw.decode("utf-8-sig")
        except UnicodeDecodeError as e:
            raise error(f"{label}: not a {what} (byte {e.start} is not UTF-8)") from None
    if "\x00" in text:
        raise error(f"{label}: not a {what} (contains NUL bytes)")
    return text


def is_regular_file(path: Union[str, os.PathLike]) -> bool:
    """Whether ``path`` is a regular file (following links); False for anything that cannot be
    stat'ed. Reading a FIFO or a device would block or never end."""
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except (OSError, ValueError):
        return False


def npy_header(fp) -> tuple:
    """``(shape, fortran_order, dtype)`` of the ``.npy`` header at ``fp`` (after its magic),
    versions 1.0, 2.0 and 3.0 (utf-8 names), read without touching the data."""
    import numpy as np

    fmt = np.lib.format
    version = fmt.read_magic(fp)
    if version == (1, 0):
        return fmt.read_array_header_1_0(fp)
    if version == (2, 0):
        return fmt.read_array_header_2_0(fp)
    impl = getattr(fmt, "_read_array_header", None)
    if impl is None:                    # numpy 2 keeps it in the private implementation module
        from numpy.lib import _format_impl
        impl = _format_impl._read_array_header
    return impl(fp, version)


def load_npz_arrays(path: Union[str, os.PathLike], error: type, what: str = "an .npz file",
                    limit: int = MAX_FILE_BYTES) -> dict:
    """The arrays of an ``.npz`` file, ``{name: array}``, read with bounds, or ``error`` with one
    line naming the file: a regular file of at most ``limit`` bytes, members that decompress to
    at most ``limit`` bytes in all (a 1 MB zip bomb may hold a GB of zeros), each ``.npy``
    header's declared size checked against its bytes before numpy allocates it, no pickles."""
    import io
    import zipfile

    import numpy as np

    p = Path(path)
    raw = read_file_bytes(p, error, what, limit=limit)
    try:
        zf = zipfile.ZipFile(io.BytesIO(raw))
        infos = [i for i in zf.infolist() if not i.is_dir()]
        total = sum(i.file_size for i in infos)
        if total > limit:
            raise error(f"{p}: its members decompress to {total} bytes, more than {limit}")
        out = {}
        for info in infos:
            data = zf.read(info)
            fp = io.BytesIO(data)
            shape, _, dtype = npy_header(fp)
            if dtype.hasobject:
                raise error(f"{p}: member {printable(info.filename, 60)} is an object array (pickles are not read)")
            need = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if need > len(data) - fp.tell():
                raise error(f"{p}: member {printable(info.filename, 60)} is truncated (its header declares "
                            f"{need} bytes)")
            if need < len(data) - fp.tell():
                raise error(f"{p}: member {printable(info.filename, 60)} has {len(data) - fp.tell() - need} bytes "
                            f"after the data its header declares")
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            out[name] = np.load(io.BytesIO(data), allow_pickle=False)
        return out
    except error:
        raise
    except Exception as e:      # zipfile.BadZipFile, NotImplementedError (zip version), ValueError of a header
        raise error(f"{p}: not a readable {what.split(' ', 1)[1] if what.startswith(('a ', 'an ')) else what} "
                    f"({type(e).__name__}: {printable(one_line(e), 120)})") from None
