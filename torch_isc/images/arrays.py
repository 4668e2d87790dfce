"""Image batches as tensors: the accepted input forms, binarization to masks, and the
error every image function raises."""
from __future__ import annotations

from typing import List, Optional, Sequence, Union

import numpy as np
import torch

__all__ = ["ImageLike", "ImageError", "as_masks", "image_list", "binarize", "default_names"]

ImageLike = Union[np.ndarray, torch.Tensor]


class ImageError(ValueError):
    """An image that cannot be used (unreadable, empty mask...); the message is one line
    naming the image."""


def image_list(images: Union[ImageLike, Sequence[ImageLike]], what: str = "image") -> List[torch.Tensor]:
    """A batch of 2D images as a list of ``(H_b, W_b)`` tensors: accepts a list of 2D
    arrays/tensors (sizes may differ) or one ``(B, H, W)`` / ``(B, 1, H, W)`` array."""
    if isinstance(images, (np.ndarray, torch.Tensor)):
        t = _tensor(images, what, "batch")
        if t.dim() == 4 and t.shape[1] == 1:
            t = t[:, 0]
        if t.dim() == 2:
            raise ImageError(f"expected a batch of {what}s (B, H, W) or a list; wrap a single {what} in a list")
        if t.dim() != 3:
            raise ImageError(f"expected {what}s of shape (B, H, W) or (B, 1, H, W), got {tuple(t.shape)}")
        return list(t.unbind(0))
    out = []
    for b, im in enumerate(images):
        t = _tensor(im, what, b)
        if t.dim() == 3 and t.shape[0] == 1:
            t = t[0]
        if t.dim() != 2:
            raise ImageError(f"{what} {b}: expected a 2D (H, W) array, got shape {tuple(t.shape)}")
        if t.shape[0] == 0 or t.shape[1] == 0:
            raise ImageError(f"{what} {b}: empty image of shape {tuple(t.shape)}")
        out.append(t)
    return out


def _tensor(im, what: str, b) -> torch.Tensor:
    """``im`` as a tensor of a bool, integer or float dtype (numpy views of any strides
    copied); an ImageError naming the item otherwise."""
    if isinstance(im, torch.Tensor):
        t = im
    else:
        a = np.asarray(im)
        if a.dtype.kind not in "biuf":
            raise ImageError(f"{what} {b}: unsupported dtype {a.dtype} (expected bool, integer or float)")
        if a.dtype.kind == "u" and a.dtype.itemsize > 1:
            # torch has no comparisons for uint16/32/64: int64 holds uint16/32 exactly, float64
            # keeps uint64 in order (and nonzero nonzero)
            a = a.astype(np.int64 if a.dtype.itemsize < 8 else np.float64)
        t = torch.from_numpy(np.ascontiguousarray(a))
    if t.is_complex():
        raise ImageError(f"{what} {b}: unsupported dtype {t.dtype} (expected bool, integer or float)")
    if t.dtype in (torch.uint16, torch.uint32, torch.uint64):
        t = t.to(torch.float64)
    return t


def binarize(t: torch.Tensor, threshold: Optional[float]) -> torch.Tensor:
    """Foreground ``(H, W)`` bool: ``t > threshold``. Default (None): a bool mask as it is,
    an integer mask nonzero (OpenCV's rule for ``findContours``, negative values included), a
    float mask above 0.5."""
    if t.dtype == torch.bool:
        return t
    if threshold is None:
        return t > 0.5 if t.dtype.is_floating_point else t != 0
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.integer, np.floating)):
        raise ImageError(f"threshold must be a number, got {threshold!r}")
    return t > threshold


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
    """``names`` as a list, or ``["<what> 0", "<what> 1", ...]`` for ``n`` items."""
    return list(names) if names is not None else [f"{what} {b}" for b in range(n)]
