"""PSF models behind one protocol (:class:`PSFModel`)."""

from .analytic import GaussianAstigPSF, TwoLobeDHPSF
from .base import PSFBase, PSFModel
from .factory import PSF_NAMES, make_psf
from .masks import ArrayMask, AstigmatismMask, DoubleHelixMask, ZernikeMask, load_mask, zernike
from .pupil import PupilPSF
from .retrieval import RetrievalResult, fit_pupil, zernike_terms

__all__ = [
    "PSF_NAMES",
    "ArrayMask",
    "AstigmatismMask",
    "DoubleHelixMask",
    "GaussianAstigPSF",
    "PSFBase",
    "PSFModel",
    "PupilPSF",
    "RetrievalResult",
    "TwoLobeDHPSF",
    "ZernikeMask",
    "fit_pupil",
    "load_mask",
    "make_psf",
    "zernike",
    "zernike_terms",
]
