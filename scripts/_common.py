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
