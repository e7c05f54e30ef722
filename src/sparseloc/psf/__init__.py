"""PSF models behind one protocol (:class:`PSFModel`)."""

from .base import PSFBase, PSFModel
from .masks import ArrayMask, AstigmatismMask, DoubleHelixMask, ZernikeMask, load_mask, zernike
from .pupil import PupilPSF

__all__ = [
    "ArrayMask",
    "AstigmatismMask",
    "DoubleHelixMask",
    "PSFBase",
    "PSFModel",
    "PupilPSF",
    "ZernikeMask",
    "load_mask",
    "zernike",
]
