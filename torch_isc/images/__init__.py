"""Images to curves: binary masks and grayscale images in, implicit simplicial curves out.

Pixel convention (used by every function here, by the CLI and by the outputs): ``x`` to the
right, ``y`` down, in pixels; pixel ``(row i, column j)`` covers the square
``[j, j+1] x [i, i+1]``, so its centre is ``(j + 0.5, i + 0.5)`` and the whole image of width
``W`` and height ``H`` is ``[0, W] x [0, H]``. A curve point ``(x, y)`` is drawn on the image at
column ``x``, row ``y`` without any offset. OpenCV puts pixel centres at integers instead: an
OpenCV point ``(u, v)`` is ``(u + 0.5, v + 0.5)`` here (:func:`to_cv_contours` converts back).

Pipeline:

- :func:`mask_to_points` -- ``cv2.findContours`` (every boundary pixel, all contours) traces the
  foreground; each traced boundary pixel is replaced by the midpoints of its pixel edges that
  face the background (the *cracks*), in tracing order. The points lie on the boundary between
  foreground and background pixels, not on the pixel centres of one side, so the reconstructed
  curve can be sub-pixel accurate. The crack midpoints of a contour are then resampled to a
  uniform spacing along the contour (:func:`resample_closed`).
- :func:`edge_points` -- kornia's Canny edges of a batch of grayscale images, each edge pixel
  refined to sub-pixel along the gradient (a parabola through the gradient magnitude).
- :class:`MaskOracle` -- the mask as the inside/outside function of Section 3.2: the
  reconstruction reads the vertex signs from the mask instead of estimating the topology.
- :func:`reconstruct_masks` / :func:`reconstruct_edges` -- the batched reconstructions, with the
  pixel defaults of :func:`image_config`.
- :func:`to_cv_contours` -- results as OpenCV contours with a ``RETR_TREE`` / ``RETR_CCOMP``
  hierarchy; :func:`find_contours` is a drop-in for ``cv2.findContours``.
- :func:`read_image` -- image files as gray arrays.

Modules: ``read`` (decode image files), ``arrays`` (accepted image forms, masks, ImageError),
``settings`` (pixel config), ``masks`` (crack boundary points, resampling, MaskOracle, mask
reconstruction), ``edges`` (Canny points, edge reconstruction), ``contours`` (hierarchy, OpenCV
contours, the contours ``.npz`` layout), ``polylines`` (the one polyline converter). Writing files
(overlay, contours ``.npz``) is :mod:`torch_isc.io`'s job: nothing here imports it.

Example:
    >>> import cv2, numpy as np
    >>> mask = np.zeros((64, 64), np.uint8)
    >>> _ = cv2.circle(mask, (31, 31), 20, 255, -1)        # OpenCV centre 31 = our 31.5
    >>> res = reconstruct_masks([mask])[0]
    >>> res.num_closed, res.num_open
    (1, 0)
    >>> contours, hierarchy = to_cv_contours(res)
    >>> len(contours), hierarchy.shape
    (1, (1, 1, 4))
"""
from __future__ import annotations

from torch_isc.images.arrays import ImageError, ImageLike, as_masks
from torch_isc.images.contours import (CHAIN_METHODS, CONTOURS_FORMAT, contour_arrays, contour_hierarchy, find_contours, find_contours_batch, grid_contours,
                                       load_contours, to_cv_contours)
from torch_isc.images.edges import edge_points, reconstruct_edges
from torch_isc.images.grid import RETR_MODES, GridCurves, cv_layout, grid_mesh, retr_mode, trace_masks
from torch_isc.images.masks import (MaskOracle, auto_threshold, mask_crack_contours, mask_points, mask_to_points,
                                    reconstruct_masks, resample_closed, solve_masks, grid_results)
from torch_isc.images.polylines import closed_polygons, polyline_dicts
from torch_isc.images.read import IMAGE_SUFFIXES, decode_image, read_image
from torch_isc.images.settings import EDGE_CONFIG, IMAGE_CONFIG, MASK_CONFIG, image_config

__all__ = [
    "IMAGE_SUFFIXES", "IMAGE_CONFIG", "MASK_CONFIG", "EDGE_CONFIG", "ImageError", "ImageLike", "image_config",
    "read_image", "decode_image", "as_masks", "mask_crack_contours", "resample_closed", "mask_to_points",
    "mask_points", "auto_threshold", "solve_masks", "edge_points", "MaskOracle", "reconstruct_masks",
    "reconstruct_edges", "grid_results", "polyline_dicts", "closed_polygons", "to_cv_contours", "contour_hierarchy",
    "find_contours", "CONTOURS_FORMAT", "contour_arrays", "load_contours", "find_contours_batch", "grid_contours",
    "CHAIN_METHODS", "RETR_MODES", "GridCurves", "cv_layout", "grid_mesh", "retr_mode", "trace_masks",
]
