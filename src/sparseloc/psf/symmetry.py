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

__all__ = ["CHANGED", "MIRROR_AGREEMENT", "mirror_focus", "mirror_warning"]

#: Normalised correlation of the images at ``focus +- d`` above which they are one image.
MIRROR_AGREEMENT = 0.98
#: Normalised correlation with the focal image below which an image has changed (a depth
#: the PSF measures).
CHANGED = 0.9


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = float(np.linalg.norm(a) * np.linalg.norm(b))
    return float((a * b).sum() / den) if den > 0 else 1.0


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
    pairs = [
        (focus + k, focus - k)
        for k in range(1, min(focus, zs.size - 1 - focus) + 1)
        if _ncc(imgs[focus + k], imgs[focus]) < CHANGED
    ]
    if not pairs:
        return None
    agree = np.median([_ncc(imgs[a], imgs[b]) for a, b in pairs])
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
