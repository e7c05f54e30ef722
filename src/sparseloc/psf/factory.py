"""Build a PSF model from a short name or a mask file: what the command line's ``--psf`` takes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .base import PSFModel
from .masks import AstigmatismMask, DoubleHelixMask, load_mask
from .pupil import PupilPSF

__all__ = ["PSF_NAMES", "make_psf"]

#: Built-in model names and what they are.
PSF_NAMES: dict[str, str] = {
    "dh": "double-helix pupil model (Laguerre-Gauss mask, NA 1.45, 670 nm, z -1000..1000 nm)",
    "astig": "astigmatic pupil model (0.2 waves Z(2,2), NA 1.45, 670 nm, z -600..600 nm)",
    "clear": "standard widefield pupil model (no mask, z -1000..1000 nm)",
    "PSF.h5": "a calibration written by 'sparseloc calibrate' (measured spline or fitted pupil)",
    "dh-analytic": "two Gaussian lobes rotating with z (cheap, for tests)",
    "astig-gauss": "elliptical Gaussian with Huang 2008 width curves (cheap, for tests)",
}

_MASK_SUFFIXES = (".mat", ".npy", ".tif", ".tiff", ".csv")


def make_psf(spec: str | Path | PSFModel, **kwargs: Any) -> PSFModel:
    """Return a PSF model for a built-in name, a phase-mask file, or pass a model through.

    Parameters
    ----------
    spec : str, path or PSFModel
        One of :data:`PSF_NAMES`, or a path to a pupil phase mask (``.mat``, ``.npy``,
        ``.tif``, ``.csv``; radians), or an existing model.
    **kwargs
        Passed to the model's constructor (e.g. ``na``, ``wavelength``, ``z_range`` for pupil
        models; ``waist`` for ``dh``; ``waves`` for ``astig``; ``key``, ``centre``, ``radius``,
        ``flip`` for mask files).

    Raises
    ------
    ValueError
        For an unknown name or an unreadable mask file.
    """
    if isinstance(spec, PSFModel):
        return spec
    name = str(spec)
    low = name.lower()
    if low == "dh":
        # 0.33: the lobes turn 163 degrees over -1000..1000 nm; short of 180, so the ends
        # stay distinct
        waist = kwargs.pop("waist", 0.33)
        kwargs.setdefault("z_range", (-1000.0, 1000.0))
        return PupilPSF(DoubleHelixMask(waist), name="dh", **kwargs)
    if low == "astig":
        waves = kwargs.pop("waves", 0.2)
        kwargs.setdefault("z_range", (-600.0, 600.0))
        return PupilPSF(AstigmatismMask(waves), name="astig", **kwargs)
    if low == "clear":
        return PupilPSF(None, name="clear", **kwargs)
    if low == "dh-analytic":
        from .analytic import TwoLobeDHPSF

        return TwoLobeDHPSF(**kwargs)
    if low == "astig-gauss":
        from .analytic import GaussianAstigPSF

        return GaussianAstigPSF(**kwargs)
    path = Path(name)
    if path.suffix.lower() in (".h5", ".hdf5"):
        from ..io.calibration import load_calibration

        return load_calibration(path, model=kwargs.pop("model", None))
    if path.suffix.lower() in _MASK_SUFFIXES:
        mask_kw = {k: kwargs.pop(k) for k in ("key", "centre", "radius", "flip") if k in kwargs}
        mask = load_mask(path, **mask_kw)
        return PupilPSF(mask, name=path.stem, **kwargs)
    allowed = ", ".join(PSF_NAMES)
    raise ValueError(
        f"unknown PSF {name!r}: use one of {allowed}, a calibration file (.h5) from "
        f"'sparseloc calibrate', or a phase-mask file ({', '.join(_MASK_SUFFIXES)})"
    )
