"""The ``torch-isc`` command's entry: an interrupt while the libraries load (torch takes a
second or more) ends the command quietly with status 130, as one later does."""
from __future__ import annotations

import sys


def main() -> int:
    try:
        # numpy first, from Python: imported lazily by torch's C++ instead, an interrupt during
        # its import is cleared there (numpy half-imported, the run then goes on and fails later)
        import numpy  # noqa: F401
        from torch_isc.cli import main as cli_main
        return cli_main()        # its own handler covers the run; this one also the parser's set-up
    except KeyboardInterrupt:
        sys.stderr.write("torch-isc: interrupted\n")
        return 130
