"""PSF models behind one protocol (:class:`PSFModel`)."""

from .analytic import GaussianAstigPSF, TwoLobeDHPSF
from .base import PSFBase, PSFModel
from .factory import PSF_NAMES, make_psf
from .masks import ArrayMask, AstigmatismMask, DoubleHelixMask, ZernikeMask, load_mask, zernike
from .pupil import PupilPSF

__all__ = [
    "PSF_NAMES",
    "ArrayMask",
    "AstigmatismMask",
    "DoubleHelixMask",
    "GaussianAstigPSF",
    "PSFBase",
    "PSFModel",
    "PupilPSF",
    "TwoLobeDHPSF",
    "ZernikeMask",
    "load_mask",
    "make_psf",
    "zernike",
]
