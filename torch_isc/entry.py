"""The ``torch-isc`` command's entry: an interrupt while the libraries load (torch takes a
second or more) ends the command quietly with status 130, as one later does; SIGTERM is
handled the same way (the same clean-up), with status 143.

What cannot be handled here: an interrupt during Python's own start-up, before this module runs
(``site`` and the ``.pth`` hooks of an install: about 0.05-0.07 s, 0.03 s of it an editable
install's finder), prints Python's traceback. Only a native launcher that blocks SIGINT until
the handler is installed could cover it (a blocked signal stays pending across ``exec``; a shell
can only ignore it, which loses the interrupt).
"""
from __future__ import annotations

import signal
import sys

#: set by the handler: an interrupt that native code caught and cleared (while torch imports,
#: a C++ call of Python code can clear the exception) is still seen
_INTERRUPTED = [False]


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, a job scheduler's stop, ``timeout``), raised like an interrupt so the
    same clean-up runs (temporary files removed, no manifest for a partial set); exit status 143."""


#: exit statuses of an interrupted (SIGINT) and a terminated (SIGTERM) run: 128 + the signal
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143


def _on_interrupt(signum, frame):
    _INTERRUPTED[0] = True
    raise KeyboardInterrupt


def _on_terminate(signum, frame):
    _INTERRUPTED[0] = "terminated"
    raise Terminated


def stop_status(e: BaseException) -> "tuple[str, int]":
    """The message and exit status of a run stopped by ``e`` (an interrupt or a SIGTERM)."""
    if isinstance(e, Terminated) or _INTERRUPTED[0] == "terminated":
        return "terminated", EXIT_TERMINATED
    return "interrupted", EXIT_INTERRUPTED


def main() -> int:
    mine = mine_term = False
    try:
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:   # not a caller's own handler
            signal.signal(signal.SIGINT, _on_interrupt)
            mine = True
        if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
            signal.signal(signal.SIGTERM, _on_terminate)
            mine_term = True
    except ValueError:                      # not the main thread: no handler can be installed
        pass
    try:
        # numpy first, from Python: imported lazily by torch's C++ instead, an interrupt during
        # its import is cleared there (numpy half-imported, the run then goes on and fails later)
        import numpy  # noqa: F401
        from torch_isc.cli import main as cli_main
        if _INTERRUPTED[0]:                 # raised during the imports and cleared by native code
            raise KeyboardInterrupt
        code = cli_main()        # its own handler covers the run; this one also the parser's set-up
        if _INTERRUPTED[0] and code not in (EXIT_INTERRUPTED, EXIT_TERMINATED):
            raise KeyboardInterrupt         # cleared during the run: the outputs are complete sets
        return code
    except KeyboardInterrupt as e:
        word, code = stop_status(e)
        sys.stderr.write(f"torch-isc: {word}\n")
        return code
    finally:
        if mine:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        if mine_term:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
        _INTERRUPTED[0] = False
