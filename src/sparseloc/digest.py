"""Content hashes recorded with results: of a PSF model (as it renders) and of an array."""

from __future__ import annotations

import hashlib

import numpy as np
from numpy.typing import NDArray

from .psf.base import PSFModel

__all__ = ["array_digest", "psf_hash"]


def array_digest(a: NDArray) -> str:
    """Short content hash of an array (as little-endian float64), for run metadata."""
    return hashlib.sha256(np.ascontiguousarray(a, "<f8").tobytes()).hexdigest()[:16]


def psf_hash(model: PSFModel, pixel_size: float) -> str:
    """Content hash of a PSF model (16 hex digits): a calibration's own ``content_hash`` (the
    one ``sparseloc calibrate`` prints and writes to the file), else SHA-256 of the model's
    images at 5 planes (float32)."""
    own = getattr(model, "content_hash", None)
    if isinstance(own, str) and own:
        return own
    zs = np.linspace(*model.z_range, 5)
    c = 8.5 * pixel_size
    imgs = model.images(np.full(5, c), np.full(5, c), zs, (17, 17), pixel_size)
    return hashlib.sha256(imgs.astype(np.float32).tobytes()).hexdigest()[:16]
