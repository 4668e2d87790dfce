"""The ``torch-isc`` command's entry: an interrupt while the libraries load (torch takes a
second or more) ends the command quietly with status 130, as one later does.

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


def _on_interrupt(signum, frame):
    _INTERRUPTED[0] = True
    raise KeyboardInterrupt


def main() -> int:
    mine = False
    try:
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:   # not a caller's own handler
            signal.signal(signal.SIGINT, _on_interrupt)
            mine = True
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
        if _INTERRUPTED[0] and code != 130:
            raise KeyboardInterrupt         # cleared during the run: the outputs are complete sets
        return code
    except KeyboardInterrupt:
        sys.stderr.write("torch-isc: interrupted\n")
        return 130
    finally:
        if mine:
            signal.signal(signal.SIGINT, signal.default_int_handler)
            _INTERRUPTED[0] = False
