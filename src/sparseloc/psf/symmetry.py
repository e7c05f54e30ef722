"""Whether a PSF tells z from its mirror about focus.

An unengineered PSF (a clear pupil without aberrations) blurs the same way above and below
its focus: an emitter at ``focus + d`` and one at ``focus - d`` give the same image, and a fit
finds either. Engineered PSFs break that symmetry (an astigmatic image stretches along x on
one side and along y on the other; a double helix's lobes turn one way). Here the images at
``focus +- d`` are compared wherever the image has changed from the focal one: where they
agree as closely as :data:`MIRROR_AGREEMENT`, z is known only up to its sign about focus.
"""

from __future__ import annotations

import numpy as np

from .base import PSFModel

__all__ = ["CHANGED", "MIRROR_AGREEMENT", "mirror_focus", "mirror_warning", "ncc_planes"]

#: Normalised correlation of the images at ``focus +- d`` above which they are one image:
#: between a clear pupil's (about 1) and the most symmetric engineered PSF's (well below;
#: docs/benchmarks/hidden_data_rehearsal.txt, E).
MIRROR_AGREEMENT = 0.98
#: Normalised correlation with the focal image below which an image has changed (a depth
#: the PSF measures).
CHANGED = 0.9


def ncc_planes(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation of two stacks (N, rows, cols), plane by plane (N,)."""
    a = a.reshape(a.shape[0], -1)
    b = b.reshape(b.shape[0], -1)
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    den = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    return (a * b).sum(axis=1) / np.maximum(den, 1e-300)


def mirror_focus(
    model: PSFModel, pixel_size: float, z_range: tuple[float, float] | None = None
) -> float | None:
    """The focus (nm) about which ``model`` images z and its mirror alike over ``z_range``
    (default the model's), or None where it tells them apart.

    Parameters
    ----------
    model : PSFModel
        The PSF model.
    pixel_size : float
        Pixel size (nm).
    z_range : (float, float), optional
        The depths to judge.
    """
    lo, hi = model.z_range if z_range is None else z_range
    lo, hi = max(lo, model.z_range[0]), min(hi, model.z_range[1])
    if not hi > lo:
        return None
    side = 31
    c = np.full(1, side * pixel_size / 2)
    zs = np.linspace(lo, hi, 41)
    imgs = model.images(np.repeat(c, zs.size), np.repeat(c, zs.size), zs, (side, side), pixel_size)
    focus = int(np.argmax(imgs.reshape(zs.size, -1).max(axis=1)))
    k = np.arange(1, min(focus, zs.size - 1 - focus) + 1)
    if not k.size:  # focus at an end of the range: one side only
        return None
    above, below = imgs[focus + k], imgs[focus - k]
    changed = ncc_planes(above, np.broadcast_to(imgs[focus], above.shape)) < CHANGED
    if not changed.any():
        return None
    agree = np.median(ncc_planes(above[changed], below[changed]))
    return float(zs[focus]) if agree > MIRROR_AGREEMENT else None


def mirror_warning(
    model: PSFModel, pixel_size: float, z_range: tuple[float, float] | None = None
) -> str:
    """One sentence where ``model`` images z and its mirror alike (:func:`mirror_focus`),
    else ""."""
    focus = mirror_focus(model, pixel_size, z_range)
    if focus is None:
        return ""
    return (
        f"the PSF looks the same above and below its focus (z {focus:.0f} nm): each fit's z is "
        "known only up to that mirror; image on one side of focus and give --z-min / --z-max "
        "to match, or use an engineered PSF (astigmatic, double helix)"
    )
