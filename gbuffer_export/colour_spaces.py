"""Colour spaces, through colour-science (numpy): the sRGB encoding of display images.

``colour`` is imported inside the functions that need it (its import took 0.7-0.9 s here:
``python -X importtime -c 'import colour'``).
"""
from __future__ import annotations

import numpy as np


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding (inverse EOTF) of linear values, clipped to [0, 1] first; float64."""
    import colour
    return np.asarray(colour.cctf_encoding(np.clip(np.asarray(x, np.float64), 0.0, 1.0), function="sRGB"))


__all__ = ["srgb_encode"]
