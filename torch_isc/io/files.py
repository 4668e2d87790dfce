"""Bytes in, bytes out: :func:`read_file_bytes` and the one writer of every output,
:func:`atomic_write`.

An output goes to a temporary file in the destination folder (same file system), which is
flushed, synced and moved over the destination with ``os.replace``: an interrupted run never
leaves a half-written output, a file either has its old content or its complete new content.
"""
from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Callable, Optional, Union

from torch_isc._helpers import read_file_bytes

__all__ = ["PathLike", "Content", "read_file_bytes", "atomic_write"]

PathLike = Union[str, os.PathLike]
#: What :func:`atomic_write` writes: bytes, text (UTF-8), or a function that writes into an
#: open binary file object.
Content = Union[bytes, bytearray, str, Callable[[BinaryIO], Any]]

_UMASK: Optional[int] = None


def _file_mode() -> int:
    global _UMASK
    if _UMASK is None:
        _UMASK = os.umask(0)
        os.umask(_UMASK)
    return 0o666 & ~_UMASK


def atomic_write(path: PathLike, data: Content, fsync: bool = True) -> Path:
    """Write ``path`` atomically.

    ``data`` is the content (``bytes``, or ``str`` written as UTF-8) or a function called with an
    open binary file object that writes the content. On any error (an interrupt included) the
    temporary file is removed, the error is re-raised and ``path`` is left as it was. The
    destination folder must exist. ``fsync=False`` skips the sync to disk: the move is still
    atomic for the processes of this machine, but after a power loss the file may be empty or
    torn (the batch runner's manifests hash every output, so such a set is detected and redone).

    Returns:
        ``path`` as a :class:`Path`.

    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> atomic_write(d / "a.txt", "hi").read_text()
    'hi'
    """
    dest = Path(path)
    if dest.is_dir() and not dest.is_symlink():
        # found before writing, and named as the caller's path (the move would name the temporary file)
        raise IsADirectoryError(errno.EISDIR, "Is a directory", str(dest))
    folder = dest.parent if str(dest.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            if callable(data):
                data(fh)
            elif isinstance(data, str):
                fh.write(data.encode("utf-8"))
            else:
                fh.write(data)
            fh.flush()
            if fsync:
                os.fsync(fh.fileno())
        os.chmod(tmp, _file_mode())        # mkstemp creates 0600; give the usual permissions
        try:
            os.replace(tmp, dest)
        except OSError as e:
            # the error names the destination, not the temporary file (removed below)
            raise type(e)(e.errno, e.strerror, str(dest)) from None
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return dest
