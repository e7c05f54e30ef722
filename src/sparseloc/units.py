"""Lengths given in nm, checked against what microscopes make.

A pixel size in the sample (camera pixel over magnification) or a bead scan's stage step far
outside the range of real instruments is a unit slip: a value in micrometres (the unit of
storm-analysis, ThunderSTORM's settings and most stage software) given where nm are meant.
Accepted, every later step would run on it without a word; refused, it costs one sentence.
"""

from __future__ import annotations

import math

__all__ = [
    "PIXEL_SIZE_RANGE_NM",
    "TOLERANCE_RANGE_NM",
    "WAVELENGTH_RANGE_NM",
    "Z_SPAN_MIN_NM",
    "Z_STEP_RANGE_NM",
    "check_length_nm",
    "check_pixel_size",
    "check_z_limits",
    "check_z_step",
]

#: Pixel sizes in the sample that microscopes give (nm): 10 nm is beyond any magnification of
#: a camera pixel, 20 um beyond any objective used for single molecules.
PIXEL_SIZE_RANGE_NM = (10.0, 20_000.0)
#: Stage steps of a bead z-scan (nm): piezo stages step down to a few nm; a step above 1 um
#: leaves two or three planes over a double helix's or an astigmatic PSF's 2-3 um and a
#: handful over a tetrapod's 6 um, too few for the spline's cubic interpolation in z.
Z_STEP_RANGE_NM = (1.0, 1_000.0)
#: Emission wavelengths of fluorophores (nm), ultraviolet to infrared.
WAVELENGTH_RANGE_NM = (200.0, 2_000.0)
#: Distances that decide something about localizations (match tolerances, largest
#: uncertainties kept, image pixels; nm): below a nm no localization is that precise.
TOLERANCE_RANGE_NM = (1.0, 1_000_000.0)
#: The narrowest z range (nm) worth searching or keeping: no 3D PSF resolves depth finer, and
#: limits within +-10 of zero that span less are micrometres given for nm.
Z_SPAN_MIN_NM = 10.0


def check_length_nm(
    value: object, what: str, plausible: tuple[float, float], too_large: str | None = None
) -> float:
    """``value`` (nm) as a float if it is positive and within ``plausible`` (nm); else
    ValueError in one sentence naming ``what`` (a flag, say) and, below the range, the value
    it would be in micrometres; above it, ``too_large`` says why (default: beyond what
    microscopes make)."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number of nm, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{what} must be a positive number of nm, got {v:g}")
    lo, hi = plausible
    if v < lo:
        raise ValueError(
            f"{what} {v:g} nm is below {lo:g} nm, less than any microscope's: is it in "
            f"micrometres? {v:g} um is {v * 1000:g} nm"
        )
    if v > hi:
        why = too_large or f"above what microscopes make ({lo:g}-{hi:g} nm)"
        raise ValueError(f"{what} {v:g} nm is {why}")
    return v


def check_pixel_size(value: object, what: str = "--pixel-size") -> float:
    """A pixel size in the sample (nm), checked (:data:`PIXEL_SIZE_RANGE_NM`)."""
    return check_length_nm(value, what, PIXEL_SIZE_RANGE_NM)


def check_z_step(value: object, what: str = "--z-step") -> float:
    """A bead scan's stage step (nm), checked (:data:`Z_STEP_RANGE_NM`)."""
    too_large = (
        f"above {Z_STEP_RANGE_NM[1]:g} nm: a bead scan needs several planes over the PSF's "
        "depth of a few micrometres (steps of 10-100 nm are usual)"
    )
    return check_length_nm(value, what, Z_STEP_RANGE_NM, too_large)


def check_z_limits(lo: float | None, hi: float | None, what: str = "--z-min/--z-max") -> None:
    """ValueError in one sentence when the lower z limit (nm) lies above the upper, or both
    were given in micrometres: within +-10 and spanning less than :data:`Z_SPAN_MIN_NM`."""
    if lo is None or hi is None:
        return
    if lo > hi:
        low, high = what.split("/") if "/" in what else (what, what)
        raise ValueError(f"{low} {lo:g} is above {high} {hi:g}")
    if hi - lo < Z_SPAN_MIN_NM and max(abs(lo), abs(hi)) <= Z_SPAN_MIN_NM:
        raise ValueError(
            f"{what} {lo:g}..{hi:g} nm spans {hi - lo:g} nm: are they in micrometres? "
            f"{lo:g}..{hi:g} um is {lo * 1000:g}..{hi * 1000:g} nm"
        )
