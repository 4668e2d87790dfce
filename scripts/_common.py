"""Small helpers shared by the scripts (not part of the library)."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Optional

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def resolve_dir(arg: Optional[str], default: Path) -> Path:
    """``arg`` as given when it exists from the current folder, else relative to the repo root."""
    if arg is None:
        return default.resolve()
    p = Path(arg)
    if p.is_absolute() or p.exists():
        return p.resolve()
    return (REPO / p).resolve()


def json_text(obj: Any) -> str:
    from torch_isc.io import json_dumps
    return json_dumps(obj)


def add_run_args(ap, what: str) -> None:
    """The options every reconstruction script shares (``what``: the unit, e.g. ``"case"``)."""
    ap.add_argument("--config", default=None, help="YAML config file (keys of ReconstructConfig)")
    ap.add_argument("--set", nargs="+", action="extend", default=[], metavar="KEY=VALUE",
                    help="config overrides (YAML scalars), e.g. --set tolerance=0.006 seed=1")
    ap.add_argument("--filter", default=None, metavar="SUBSTR", help=f"only {what}s whose name contains SUBSTR")
    ap.add_argument("--one-by-one", action="store_true", help=f"one reconstruct_batch call per {what}")
    ap.add_argument("--device", default="cpu", help="device of the point tensors (cpu, cuda)")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")


def run_main(main) -> None:
    """Exit with ``main()``'s status: 130 on Ctrl-C, 1 with the traceback on a crash."""
    import traceback
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        sys.exit(130)
    except Exception:
        traceback.print_exc()
        sys.exit(1)
