"""Image batches as tensors: the accepted input forms, binarization to masks, and the
error every image function raises."""
from __future__ import annotations

from typing import List, Optional, Sequence, Union

import numpy as np
import torch

from torch_isc._helpers import finite_real

__all__ = ["ImageLike", "ImageError", "as_masks", "image_list", "binarize", "default_names"]

ImageLike = Union[np.ndarray, torch.Tensor]


class ImageError(ValueError):
    """An image that cannot be used (unreadable, empty mask...); the message is one line
    naming the image."""


def image_list(images: Union[ImageLike, Sequence[ImageLike]], what: str = "image") -> List[torch.Tensor]:
    """A batch of 2D images as a list of ``(H_b, W_b)`` tensors: accepts a list of 2D
    arrays/tensors (sizes may differ; one-channel ``(H, W, 1)`` or ``(1, H, W)`` too) or one
    ``(B, H, W)`` / ``(B, 1, H, W)`` array."""
    if isinstance(images, (np.ndarray, torch.Tensor)):
        t = _as_real_tensor(images, f"{what}s")
        if t.dim() == 4 and t.shape[1] == 1:
            t = t[:, 0]
        if t.dim() == 2:
            raise ImageError(f"expected a batch of {what}s (B, H, W) or a list; wrap a single {what} in a list")
        if t.dim() != 3:
            raise ImageError(f"expected {what}s of shape (B, H, W) or (B, 1, H, W), got {tuple(t.shape)}")
        out = list(t.unbind(0))
    else:
        if isinstance(images, (str, bytes)) or not hasattr(images, "__iter__"):
            raise ImageError(f"expected a list of {what}s or a (B, H, W) array, got {type(images).__name__}")
        out = []
        for b, im in enumerate(images):
            t = _as_real_tensor(im, f"{what} {b}")
            if t.dim() == 3 and (t.shape[0] == 1 or t.shape[2] == 1):
                # one channel: (H, W, 1) as OpenCV reads arrays, (1, H, W) as torch lays tensors out;
                # a (1, n, 1) array is a row, a (1, n, 1) tensor a column
                last = t.shape[2] == 1 and (t.shape[0] != 1 or not torch.is_tensor(im))
                t = t[..., 0] if last else t[0]
            if t.dim() != 2:
                raise ImageError(f"{what} {b}: expected a 2D (H, W) array, got shape {tuple(t.shape)}")
            if t.shape[0] == 0 or t.shape[1] == 0:
                raise ImageError(f"{what} {b}: empty image of shape {tuple(t.shape)}")
            out.append(t)
    # NaN compares false with every threshold: it would silently read as background; an Inf pixel
    # is foreground under any threshold and turns Canny's gradients into NaN (one host read)
    floats = [b for b, t in enumerate(out) if t.dtype.is_floating_point]
    if floats and bool(torch.stack([~out[b].isfinite().all() for b in floats]).any()):
        first = next(b for b in floats if not bool(out[b].isfinite().all()))
        raise ImageError(f"{what} {first}: has {'NaN' if bool(out[first].isnan().any()) else 'Inf'} values")
    return out


_UNSIGNED = {torch.uint16: torch.int32, torch.uint32: torch.int64}


def _as_real_tensor(im, label: str) -> torch.Tensor:
    """``im`` as a tensor of real numbers (bool, integer or float), on its device; unsigned
    types that torch cannot compare widened; anything else an :class:`ImageError`."""
    if not isinstance(im, torch.Tensor):
        try:
            a = np.asarray(im)
        except (TypeError, ValueError) as e:
            raise ImageError(f"{label}: not an array of numbers ({type(e).__name__})") from None
        if a.dtype.kind not in "biuf":
            raise ImageError(f"{label}: expected a bool, integer or float array, got dtype {a.dtype}")
        if a.dtype == np.uint64:
            a = a.astype(np.float64)                 # beyond int64; torch compares no uint64
        elif a.dtype.kind == "f" and a.dtype.itemsize > 8:
            a = a.astype(np.float64)                 # long double: no torch dtype
        if not a.dtype.isnative:
            a = a.astype(a.dtype.newbyteorder("="))
        if not a.flags.c_contiguous:             # (ascontiguousarray made a 0-d array 1-d)
            a = np.ascontiguousarray(a)
        if not a.flags.writeable:
            a = a.copy()                             # torch warns on read-only arrays (it never writes)
        im = torch.from_numpy(a)
    if im.layout != torch.strided or im.device.type == "meta":
        raise ImageError(f"{label}: expected a dense tensor with values (got layout {im.layout}, device {im.device})")
    if im.is_complex() or not (im.dtype.is_floating_point or im.dtype == torch.bool or not im.dtype.is_signed
                               or im.dtype in (torch.int8, torch.int16, torch.int32, torch.int64)):
        raise ImageError(f"{label}: expected a bool, integer or float array, got dtype {im.dtype}")
    if im.dtype in _UNSIGNED:
        im = im.to(_UNSIGNED[im.dtype])
    elif im.dtype.is_floating_point and im.element_size() == 1:
        im = im.float()                              # float8: few kernels exist for it (isfinite, >)
    elif im.dtype == torch.uint64:
        im = im.double()
    return im.detach()


def binarize(t: torch.Tensor, threshold: Optional[float]) -> torch.Tensor:
    """Foreground ``(H, W)`` bool: ``t > threshold``. Default (None): a bool mask as it is,
    an integer mask nonzero (OpenCV's rule for ``findContours``, negative values included), a
    float mask above 0.5."""
    if t.dtype == torch.bool:
        return t
    if threshold is not None and not finite_real(threshold):
        raise ImageError(f"threshold must be a finite number or None, got {threshold!r:.50}")
    if threshold is None:
        return t > 0.5 if t.dtype.is_floating_point else t != 0
    if not t.dtype.is_floating_point:
        # beyond the pixel type's range every pixel is on one side (torch cannot cast 2**70 to uint8)
        info = torch.iinfo(t.dtype)
        if threshold >= info.max:
            return torch.zeros_like(t, dtype=torch.bool)
        if threshold < info.min:
            return torch.ones_like(t, dtype=torch.bool)
    return t > float(threshold) if t.dtype.is_floating_point else t > threshold


def as_masks(masks: Union[ImageLike, Sequence[ImageLike]], threshold: Optional[float] = None) -> List[torch.Tensor]:
    """Binary masks ``[(H_b, W_b) bool]`` from a list of 2D arrays/tensors or a ``(B, H, W)``
    stack: a pixel is foreground when its value is above ``threshold`` (default: nonzero for
    integer masks, as ``cv2.findContours`` reads them; above 0.5 for float masks in [0, 1];
    bool masks as they are).

    >>> [m.sum().item() for m in as_masks([np.eye(3), np.full((2, 4), 1, np.uint8)])]
    [3, 8]
    """
    return [binarize(t, threshold) for t in image_list(masks, "mask")]



def default_names(names: Optional[Sequence[str]], n: int, what: str) -> List[str]:
    """``names`` as a list, or ``["<what> 0", "<what> 1", ...]`` for ``n`` items; one name per
    item or an :class:`ImageError` (a short list silently dropped items)."""
    if names is None:
        return [f"{what} {b}" for b in range(n)]
    if isinstance(names, (str, bytes)):
        raise ImageError(f"names: expected a sequence of {n} name(s), got one string")
    names = list(names)
    if len(names) != n:
        raise ImageError(f"names: {len(names)} name(s) for {n} {what}(s)")
    return [str(x) for x in names]
