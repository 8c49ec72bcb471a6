"""Colour spaces, through colour-science (numpy): the sRGB encoding of display images, the working spaces a clip
may be rendered in and their conversion into the one training space, and the BT.709 YCbCr matrices.

A clip's colour buffers are stored in the scene-linear (working) space of the .blend that rendered them, named by
the manifest's ``scene_linear`` (Blender 5.0 offers Linear Rec.709, its default, Linear Rec.2020 and ACEScg).
Training and evaluation see every clip in ``TRAINING_SPACE``: ``convert_buffer`` maps the buffers of
``COLOUR_BUFFERS`` with the 3x3 matrix of ``conversion_matrix`` (primaries through CIE XYZ, Bradford adaptation
between whites, as Blender's OCIO configuration does).

``colour`` is imported inside the functions that need it, through ``colour_module`` (its import took 0.7-0.9 s
here: ``python -X importtime -c 'import colour'``), which keeps colour-science's import-time warnings about
optional packages BlendSR does not use (``"Matplotlib" related API features are not available`` on a core install)
out of the commands' output.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from .errors import BlendSRError

#: The RGB space of every colour buffer that training and evaluation see: scene-referred linear RGB with the
#: ITU-R BT.709 (= sRGB) primaries and D65 white; Blender's name, as the manifest's ``scene_linear`` writes it.
TRAINING_SPACE = "Linear Rec.709"
#: Working space of a clip whose manifest has no ``scene_linear`` (Blender's default).
DEFAULT_WORKING_SPACE = "Linear Rec.709"
#: Blender's working spaces (``bpy.data.colorspace.working_space``) -> the ``colour.RGB_COLOURSPACES`` entry with
#: the same primaries and white point.
WORKING_SPACES: dict[str, str] = {
    "Linear Rec.709": "ITU-R BT.709",
    "Linear Rec.2020": "ITU-R BT.2020",
    "ACEScg": "ACEScg",
}
#: Chromatic adaptation transform between different whites (ACEScg's ~D60 and D65); Blender's configuration
#: converts ACEScg with Bradford too ("ACES-AP1_to_CIE-XYZ-D65_BFD").
CHROMATIC_ADAPTATION = "Bradford"
#: Buffers holding RGB colours in the working space, converted by ``convert_buffer``. ``radiance`` and
#: ``emission`` are radiance; ``albedo`` (base colour) and ``fbeta`` (directional albedo, a per-channel ratio) are
#: reflectances, converted like colours: the reflected colour of white light, exact for white light and a first-order
#: approximation otherwise. White maps to white (rows of the matrix sum to 1), so fbeta = 1 on background stays 1.
#: Demodulation runs after the conversion, so radiance = fbeta * irradiance + emission holds in the training space.
COLOUR_BUFFERS = ("radiance", "emission", "albedo", "fbeta")

#: BT.709 luma weights (Kr, Kg, Kb) of ITU-R BT.709-6.
BT709_LUMA = (0.2126, 0.7152, 0.0722)


def _ycbcr_matrices(kr: float, kb: float) -> tuple[np.ndarray, np.ndarray]:
    """(RGB -> YCbCr, YCbCr -> RGB) 3x3 full-range matrices from the luma weights Kr and Kb."""
    kg = 1.0 - kr - kb
    fwd = np.array([[kr, kg, kb],
                    [-0.5 * kr / (1.0 - kb), -0.5 * kg / (1.0 - kb), 0.5],
                    [0.5, -0.5 * kg / (1.0 - kr), -0.5 * kb / (1.0 - kr)]])
    return fwd, np.linalg.inv(fwd)


#: Full-range float R'G'B' -> Y'CbCr of BT.709 (no offsets, no quantisation): Y' in [0, 1], Cb and Cr in
#: [-0.5, 0.5] for inputs in [0, 1]. ``ycbcr = rgb @ RGB_TO_YCBCR_709.T``. Applied to linear RGB it gives
#: luminance Y and linear chroma differences. Equal to colour-science's ``RGB_to_YCbCr`` with BT.709 weights and
#: ``out_legal=False, out_int=False`` (tested).
RGB_TO_YCBCR_709, YCBCR_TO_RGB_709 = _ycbcr_matrices(BT709_LUMA[0], BT709_LUMA[2])
RGB_TO_YCBCR_709.setflags(write=False)
YCBCR_TO_RGB_709.setflags(write=False)


def colour_module():
    """``import colour`` without its import-time warnings (optional features: matplotlib, OpenImageIO, ...)."""
    import sys
    import warnings
    if "colour" in sys.modules and sys.modules["colour"] is not None:
        return sys.modules["colour"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour
    return colour


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding (inverse EOTF) of linear values, clipped to [0, 1] first; float64."""
    colour = colour_module()
    return np.asarray(colour.cctf_encoding(np.clip(np.asarray(x, np.float64), 0.0, 1.0), function="sRGB"))


def srgb_decode(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding (EOTF) of encoded values in [0, 1] to linear; float64 (the inverse of
    ``srgb_encode`` on [0, 1])."""
    colour = colour_module()
    return np.asarray(colour.cctf_decoding(np.asarray(x, np.float64), function="sRGB"))


@lru_cache(maxsize=None)
def _matrix(src: str, dst: str) -> np.ndarray:
    colour = colour_module()
    m = colour.matrix_RGB_to_RGB(colour.RGB_COLOURSPACES[WORKING_SPACES[src]],
                                 colour.RGB_COLOURSPACES[WORKING_SPACES[dst]],
                                 chromatic_adaptation_transform=CHROMATIC_ADAPTATION)
    m = np.asarray(m, dtype=np.float64)
    m.setflags(write=False)
    return m


def luminance_weights(space: str) -> tuple[float, float, float]:
    """The weights (wr, wg, wb) with luminance Y = wr R + wg G + wb B for linear RGB in the working space ``space``:
    the Y row of its RGB -> CIE XYZ matrix (``BT709_LUMA`` for Linear Rec.709). ValueError naming the space when it
    is not one of ``WORKING_SPACES``."""
    if space not in WORKING_SPACES:
        raise BlendSRError(f"working colour space {space!r} is not one blendsr converts (known: "
                           f"{', '.join(WORKING_SPACES)})")
    if space == "Linear Rec.709":
        return BT709_LUMA
    return _luminance_row(space)


@lru_cache(maxsize=None)
def _luminance_row(space: str) -> tuple[float, float, float]:
    import colour
    row = np.asarray(colour.RGB_COLOURSPACES[WORKING_SPACES[space]].matrix_RGB_to_XYZ, np.float64)[1]
    return float(row[0]), float(row[1]), float(row[2])


def conversion_matrix(src: str, dst: str = TRAINING_SPACE) -> np.ndarray | None:
    """3x3 matrix M (float64) with ``rgb_dst = M @ rgb_src`` between two working spaces, or None when they are the
    same space. ValueError naming the space when one is not in ``WORKING_SPACES``."""
    for name in (src, dst):
        if name not in WORKING_SPACES:
            raise BlendSRError(f"working colour space {name!r} is not one blendsr converts (known: "
                             f"{', '.join(WORKING_SPACES)})")
    if src == dst:
        return None
    return _matrix(src, dst)


def convert_buffer(name: str, arr: np.ndarray, matrix: np.ndarray | None) -> np.ndarray:
    """Buffer ``name`` (H x W x C) with ``matrix`` applied to its RGB when it is one of ``COLOUR_BUFFERS``;
    unchanged (the same array) otherwise or when ``matrix`` is None. Keeps the float dtype of ``arr``."""
    if matrix is None or name not in COLOUR_BUFFERS:
        return arr
    out = np.asarray(arr, np.float64) @ matrix.T
    return out.astype(arr.dtype if arr.dtype.kind == "f" else np.float32, copy=False)


__all__ = ["TRAINING_SPACE", "DEFAULT_WORKING_SPACE", "WORKING_SPACES", "CHROMATIC_ADAPTATION", "COLOUR_BUFFERS",
           "BT709_LUMA", "RGB_TO_YCBCR_709", "YCBCR_TO_RGB_709", "srgb_encode", "srgb_decode", "colour_module",
           "conversion_matrix", "convert_buffer", "luminance_weights"]
