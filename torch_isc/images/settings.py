"""The reconstruction settings for images, in pixels."""
from __future__ import annotations

from typing import Any, Dict, Mapping, Optional, Sequence, Union

from torch_isc.pipeline.config import ConfigError, ReconstructConfig, flat_keys, from_dict, load_config

__all__ = ["MASK_CONFIG", "EDGE_CONFIG", "IMAGE_CONFIG", "image_config", "as_image_config"]

#: Reconstruction settings for masks, in pixels (applied by :func:`image_config`): the test
#: tolerance is half a pixel (the quantization step of a mask's boundary), absolute; and no
#: noise-based widening of it (``noise_factor: 0``): a mask's boundary has no noise beyond the
#: quantization, and the noise estimate (line fits at each point's neighbours) would read the
#: two sides of a stroke a few pixels wide as noise and stop refining before the stroke is resolved.
#: The denoising keeps the neighbour search it was measured with on masks (window 12, no
#: neighbour descent): a mask's boundary points sit on the pixel lattice, and the wider search
#: made for noisy point sets is not judged there (with both, a 3 px ring crossed by a line lost a
#: curve, tests/test_images.py). The unsupported-tip flips of the band stage stay off: a mask's
#: oracle gives every vertex its true sign.
MASK_CONFIG: Dict[str, Any] = {"tolerance": 0.5, "tolerance_mode": "absolute", "noise_factor": 0.0,
                               "denoise_refine_hops": 0, "denoise_window": 12, "spike_unsupported": False}
#: Settings for Canny edge points: half a pixel, absolute; the noise estimate stays on (edge
#: points do jitter). A wall across a stroke a few pixels wide (a thin ring cut into pieces, two
#: close discs joined) is split below the data's reach on every item, not only on noisy ones
#: (``transverse_noisy: 0``): edge points lie a pixel apart, far below the tolerance's
#: neighbourhood reach, and their estimated noise is a fraction of the tolerance, so the
#: point-set default never applied (scripts/evaluate_edges.py, seeds 0-5: 193 -> 212 of 240).
EDGE_CONFIG: Dict[str, Any] = {"tolerance": 0.5, "tolerance_mode": "absolute", "transverse_noisy": 0.0}
IMAGE_CONFIG = {"mask": MASK_CONFIG, "edges": EDGE_CONFIG}


def image_config(base: Optional[ReconstructConfig] = None, keep: Sequence[str] = (),
                 mode: str = "mask") -> ReconstructConfig:
    """``base`` (default config when None; a mapping of keys, which are then kept) with the pixel settings of :data:`MASK_CONFIG`
    (``mode="mask"``) or :data:`EDGE_CONFIG` (``mode="edges"``), except the keys in ``keep``
    (e.g. those a user set explicitly).

    >>> cfg = image_config()
    >>> cfg.test.tolerance, cfg.test.tolerance_mode, cfg.test.noise_factor
    (0.5, 'absolute', 0.0)
    """
    if mode not in IMAGE_CONFIG:
        raise ConfigError(f"image mode must be one of {', '.join(IMAGE_CONFIG)}, got {mode!r}")
    if isinstance(base, Mapping):
        keep = list(keep) + flat_keys(base)
        base = from_dict(base)
    if base is not None and not isinstance(base, ReconstructConfig):
        raise ConfigError(f"config: expected a ReconstructConfig or a mapping of its keys, got {type(base).__name__}")
    base = base if base is not None else load_config()
    return base.replace(**{k: v for k, v in IMAGE_CONFIG[mode].items() if k not in set(keep)})


def as_image_config(config: Union[None, ReconstructConfig, Mapping[str, Any]], mode: str) -> ReconstructConfig:
    """The config of an image call: :func:`image_config` for None; a mapping (``{"max_level": 2}``)
    is the pixel settings with those keys changed, as ``--set`` does on the command line (it was
    the plain defaults, in units of the image's diagonal, and a retry raised AttributeError); a
    :class:`ReconstructConfig` is used as it is."""
    if config is None or isinstance(config, Mapping):
        return image_config(config, mode=mode)
    if not isinstance(config, ReconstructConfig):
        raise ConfigError(f"config: expected a ReconstructConfig or a mapping of its keys, got {type(config).__name__}")
    return config

