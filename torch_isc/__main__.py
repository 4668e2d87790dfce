"""``python -m torch_isc ...``: the same as the ``torch-isc`` command."""
import sys

from torch_isc.entry import main

if __name__ == "__main__":
    sys.exit(main())
