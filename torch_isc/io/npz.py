"""The lossless curve format: an implicit curve batch in a compressed ``.npz``.

Arrays: ``verts (V, 2)``, ``faces (T, 3)`` (global indices), ``values (V,)``,
``verts_per_item (B,)``, ``faces_per_item (B,)``, each in its own dtype, plus ``dtypes`` (the
torch dtype names), ``format`` and ``metadata`` (a JSON string; tensors and numpy values become
lists, NaN/Inf become null), and ``enclosed (B,)`` bool for curves whose mesh holes take their
boundary's sign (mask mode's band meshes; absent: none). No pickles: the file loads with
``allow_pickle=False``.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, BinaryIO, Dict, Optional, Tuple, Union

import numpy as np
import torch

from torch_isc._helpers import load_npz_arrays, one_line
from torch_isc.core.curve import ImplicitCurve, InvalidValuesError
from torch_isc.core.mesh import InvalidMeshError, MeshBatch
from torch_isc.io.errors import CurveFileError
from torch_isc.io.files import PathLike, atomic_write
from torch_isc.io.json import jsonable

__all__ = ["NPZ_FORMAT", "encode_curve", "save_npz", "load_npz", "result_metadata", "encode_npz", "write_npz"]

#: Version of the ``.npz`` layout written by :func:`save_npz`.
NPZ_FORMAT = 1

_ARRAYS = ("verts", "faces", "values", "verts_per_item", "faces_per_item")


def _to_numpy(t: torch.Tensor) -> Tuple[np.ndarray, str]:
    """Tensor -> numpy array and torch dtype name; bfloat16 (no numpy dtype) keeps its raw bits."""
    t = t.detach().cpu().contiguous()
    name = str(t.dtype).replace("torch.", "")
    if t.dtype == torch.bfloat16:
        return t.view(torch.int16).numpy(), name
    return t.numpy(), name


def _from_numpy(a: np.ndarray, name: str) -> torch.Tensor:
    t = torch.from_numpy(np.ascontiguousarray(a))
    if name == "bfloat16":
        return t.view(torch.bfloat16)
    return t


def encode_curve(curve: ImplicitCurve, fh: BinaryIO, metadata: Optional[Dict[str, Any]] = None) -> None:
    """Write ``curve`` (and ``metadata``) as a compressed ``.npz`` into ``fh``."""
    m = curve.mesh
    arrays: Dict[str, np.ndarray] = {}
    dtypes: Dict[str, str] = {}
    for key, t in zip(_ARRAYS, (m.verts, m.faces, curve.values, m.verts_per_item, m.faces_per_item)):
        arrays[key], dtypes[key] = _to_numpy(t)
    if curve.enclosed is not None:
        arrays["enclosed"] = curve.enclosed.detach().cpu().numpy().astype(np.bool_)
    arrays["dtypes"] = np.array(json.dumps(dtypes, sort_keys=True))
    arrays["format"] = np.array(NPZ_FORMAT, dtype=np.int64)
    arrays["metadata"] = np.array(json.dumps(jsonable(metadata or {}), sort_keys=True))
    np.savez_compressed(fh, **arrays)


def save_npz(path: PathLike, curve: ImplicitCurve, metadata: Optional[Dict[str, Any]] = None) -> Path:
    """Save a curve batch losslessly (atomic write; the layout of this module's docstring)."""
    return atomic_write(path, lambda fh: encode_curve(curve, fh, metadata))


def load_npz(path: PathLike, device: Union[str, torch.device, None] = None,
             validate: bool = True) -> Tuple[ImplicitCurve, Dict[str, Any]]:
    """Load a file written by :func:`save_npz`.

    Returns:
        ``(curve, metadata)``: the :class:`ImplicitCurve` batch, bit-exact, dtypes as saved (on
        ``device``, default CPU), and the metadata dict.

    Raises:
        CurveFileError: missing, unreadable or inconsistent file (one line naming the file).
    """
    p = Path(path)
    # bounded: a regular file, members' decompressed and declared sizes checked before numpy allocates
    z = load_npz_arrays(p, CurveFileError, "a curve file")
    try:
        missing = [k for k in _ARRAYS + ("dtypes",) if k not in z]
        if missing:
            raise CurveFileError(f"{p}: not a torch_isc curve file (no '{missing[0]}' array)")
        fmt = int(z["format"]) if "format" in z else NPZ_FORMAT
        if fmt > NPZ_FORMAT:
            raise CurveFileError(f"{p}: curve file format {fmt} is newer than this version reads ({NPZ_FORMAT})")
        dtypes = json.loads(str(z["dtypes"]))
        t = {k: _from_numpy(z[k], dtypes.get(k, "")) for k in _ARRAYS}
        meta = json.loads(str(z["metadata"])) if "metadata" in z else {}
        # what save_npz writes of a curve: float coordinates, real values, integer indices and
        # counts (integer vertices or complex values failed later inside torch, negative counts
        # in MeshBatch, float faces were truncated)
        for k, ok in (("verts", t["verts"].dtype.is_floating_point),
                      ("values", not (t["values"].dtype.is_complex or t["values"].dtype == torch.bool))):
            if not ok:
                raise CurveFileError(f"{p}: invalid curve ({k} of dtype {str(t[k].dtype).replace('torch.', '')}, "
                                     f"expected {'floats' if k == 'verts' else 'real numbers'})")
        for k in ("faces", "verts_per_item", "faces_per_item"):
            if t[k].dtype.is_floating_point or t[k].dtype.is_complex or t[k].dtype == torch.bool:
                raise CurveFileError(f"{p}: invalid curve ({k} of dtype {str(t[k].dtype).replace('torch.', '')}, "
                                     f"expected integers)")
            if k != "faces" and t[k].numel() and int(t[k].min()) < 0:
                raise CurveFileError(f"{p}: invalid curve ({k} holds a negative count)")
        if not isinstance(meta, dict):
            raise CurveFileError(f"{p}: invalid curve (metadata is a JSON {type(meta).__name__}, not an object)")
        enclosed = None
        if "enclosed" in z:
            e = np.asarray(z["enclosed"])
            if e.dtype != np.bool_ or e.shape != tuple(t["verts_per_item"].shape):
                raise CurveFileError(f"{p}: invalid curve (enclosed of dtype {e.dtype} and shape {e.shape}, expected "
                                     f"{tuple(t['verts_per_item'].shape)} bool)")
            enclosed = torch.from_numpy(e.copy())
    except CurveFileError:
        raise
    except Exception as e:  # ValueError, KeyError, json errors, RecursionError from a corrupt file
        raise CurveFileError(f"{p}: unreadable curve file ({type(e).__name__}: {one_line(e)})") from None
    try:
        if device is not None:
            t = {k: v.to(device) for k, v in t.items()}
            enclosed = enclosed.to(device) if enclosed is not None else None
        mesh = MeshBatch(t["verts"], t["faces"], t["verts_per_item"], t["faces_per_item"])
        if validate:
            # orientation is checked in units of a power of 2 near the largest coordinate (exact),
            # so determinants of extreme magnitudes (1e-300, 1e300) neither underflow nor overflow
            v = t["verts"]
            if not bool(torch.isfinite(v).all()):
                raise InvalidMeshError("vertices hold NaN or Inf")
            m = float(v.abs().max()) if v.numel() else 0.0
            unit = math.ldexp(1.0, math.frexp(m)[1]) if m > 0 else 1.0
            ImplicitCurve(MeshBatch(v / unit, t["faces"], t["verts_per_item"], t["faces_per_item"]),
                          t["values"], validate=True, enclosed=enclosed)
        curve = ImplicitCurve(mesh, t["values"], validate=False, enclosed=enclosed)
    except (InvalidMeshError, InvalidValuesError) as e:
        raise CurveFileError(f"{p}: invalid curve ({one_line(e)})") from None
    return curve, meta


def result_metadata(result) -> Dict[str, Any]:
    """What a result's ``.npz`` carries besides the curve: name, convergence, limit, counts,
    config and per-level stats."""
    return {
        "name": result.name,
        "converged": bool(result.converged),
        "limit": result.limit,
        "num_closed": result.num_closed,
        "num_open": result.num_open,
        "config": result.config.to_dict(),
        "stats": [lv.to_dict() for lv in result.stats],
    }


def encode_npz(result, fh: BinaryIO) -> None:
    """``result.curve`` and :func:`result_metadata` as a compressed ``.npz`` into ``fh``."""
    encode_curve(result.curve, fh, result_metadata(result))


def write_npz(path: PathLike, result) -> Path:
    """:func:`encode_npz` into ``path`` (atomic write)."""
    return atomic_write(path, lambda fh: encode_npz(result, fh))
