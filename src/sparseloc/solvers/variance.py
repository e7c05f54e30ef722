"""The pixel variance every test of the solvers uses: the camera's noise plus the model's error.

A pixel's variance is the camera's (Poisson photons, EMCCD excess noise, read noise) plus
``(e * signal)^2``: the PSF model is not exact, and its error grows with the emitters' light
at that pixel (``e``: relative model error; a bead calibration measures it, see
:mod:`sparseloc.calibrate_error`; a dictionary's grid adds its quantization error).

A likelihood-ratio test of one emitter more or fewer asks whether the data depart from the
smaller model by more than noise. A model error is not independent noise: it has the shape of
the PSF's features, and a trial emitter can absorb much of it. Its expected share of the
window's chi-square, ``B = sum(E / V)`` with ``E`` the model error's variance of each pixel
and ``V`` the camera's, is the most it can add to the ratio: the model error's allowance. The
count selection requires a ratio above its chi-square threshold plus ``B``, so an emitter must
explain more light than the model's error in the window (``B = 0`` for an exact model).
``E`` comes from the calibration's error table where it has one (the beads' residual
variance pixel by pixel, :attr:`sparseloc.calibrate_error.ModelError.table`, rendered for
each emitter), else ``(e * signal)^2``: an error proportional to the signal overstates it in
a bright core and understates it in dim wings, where a calibrated double helix errs most.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "PIXEL_MAPS",
    "cropped_maps",
    "error_allowance",
    "misfit",
    "model_error_of",
    "model_error_variance",
    "noise_factor_of",
    "pixel_variance",
    "read_variance_crop",
]


def model_error_of(model: object) -> float:
    """A PSF model's relative error ``e`` (0 for an exact model, or one that does not say)."""
    e = float(getattr(model, "model_error", 0.0) or 0.0)
    return e if np.isfinite(e) and e > 0 else 0.0


def pixel_variance(
    mu: NDArray,
    noise_factor: float = 1.0,
    signal: NDArray | None = None,
    model_error: float = 0.0,
) -> NDArray:
    """Variance (photons^2) of each pixel: ``noise_factor * max(mu, 1) + (e * signal)^2``.

    Parameters
    ----------
    mu : ndarray
        Expected photons per pixel (emitters and background).
    noise_factor : float
        The camera's variance per expected photon (1 photon counting, 2 EMCCD).
    signal : ndarray, optional
        The emitters' part of ``mu`` (photons/pixel), which the model error scales with.
    model_error : float
        Relative model error ``e``.
    """
    var = noise_factor * np.maximum(mu, 1.0)
    if signal is not None and model_error > 0:
        var = var + (model_error * signal) ** 2
    return var


def error_allowance(noise_var: NDArray, error_var: NDArray) -> float:
    """The model error's expected chi-square over a window (see the module notes), on the
    scale of the likelihood ratio ``2 delta log L``.

    Parameters
    ----------
    noise_var : ndarray
        The camera's variance of each pixel under the smaller model (photons^2).
    error_var : ndarray
        The model error's variance of each pixel under the smaller model (photons^2): the
        error table rendered for its emitters, or ``(e * signal)^2``.
    """
    v = np.maximum(noise_var, 1e-12)
    return float(np.sum(np.asarray(error_var) / v))


#: Fit keywords that hold a map over the frame (or one number): a window's or a crop's fit
#: takes each map cut to its pixels (:func:`cropped_maps`).
PIXEL_MAPS = ("read_variance", "background_shape", "censored")


def cropped_maps(kw: dict, shape: tuple[int, int], box: tuple) -> dict:
    """``kw`` with each of :data:`PIXEL_MAPS` it holds cut to ``box`` (``r0, r1, c0, c1``) of
    a frame of ``shape`` (:func:`read_variance_crop`)."""
    out = dict(kw)
    for key in PIXEL_MAPS:
        if out.get(key) is not None:
            out[key] = read_variance_crop(out[key], shape, box)
    return out


def read_variance_crop(
    read_variance: float | NDArray | None,
    shape: tuple[int, int],
    box: tuple[int | None, int | None, int | None, int | None],
) -> float | NDArray | None:
    """The read-noise variance over a crop of a frame: a number (or None) as it is, a map
    (photons^2, the frame's ``shape`` or broadcastable to it) cut to ``box``
    (``r0, r1, c0, c1`` pixels, slice bounds: None is an open end).

    Parameters
    ----------
    read_variance : float, ndarray or None
        The frame's read-noise variance (photons^2).
    shape : (int, int)
        The frame's shape (pixels).
    box : tuple
        The crop's first and end row and column.

    Returns
    -------
    float, ndarray or None
        The crop's read-noise variance: a view of the map, or the number.
    """
    if read_variance is None or np.ndim(read_variance) == 0:
        return read_variance
    r0, r1, c0, c1 = box
    return np.broadcast_to(read_variance, shape)[r0:r1, c0:c1]


def model_error_variance(
    model: object,
    emitters: NDArray,
    signal: NDArray,
    pixel_size: float,
    origin: tuple[float, float] = (0.0, 0.0),
) -> NDArray | None:
    """The model error's variance (photons^2) of each pixel of a window: the model's error
    table rendered for ``emitters`` where it has one, else ``(e * signal)^2``; None for an
    exact model (see the module notes).

    Parameters
    ----------
    model : PSFModel
        The PSF model (its ``error_table`` and ``model_error``, where it has them).
    emitters : ndarray, shape (K, 4)
        x, y, z (nm) and photons of the window's emitters.
    signal : ndarray, shape (rows, cols)
        The light (photons/pixel) that the error scales with where the model has no table.
    pixel_size : float
        Pixel size (nm).
    origin : (float, float)
        x, y (nm) of the window's corner.
    """
    table = getattr(model, "error_table", None)
    e = model_error_of(model)
    if table is None:
        return (e * np.asarray(signal)) ** 2 if e > 0 else None
    em = np.asarray(emitters, dtype=np.float64).reshape(-1, 4)
    lo, hi = table.z_range
    return table.render(
        em[:, 0], em[:, 1], np.clip(em[:, 2], lo, hi), em[:, 3] ** 2, np.shape(signal),
        pixel_size, origin=origin,
    )  # fmt: skip


def noise_factor_of(noise: str) -> float:
    """The camera's variance per expected photon for a likelihood's ``noise`` name: 2 for an
    EMCCD's excess noise, else 1."""
    return 2.0 if noise == "emccd" else 1.0


def misfit(
    y: NDArray,
    mu: NDArray,
    error_var: NDArray | None,
    noise_factor: float,
    rv,
    censored: NDArray | None = None,
) -> float:
    """How far a window's Pearson chi-square ``X = sum((y - mu)^2 / V)`` lies above its
    expectation, in standard deviations: ``(X - n) / sqrt(sum(2 + 1 / mu))`` for ``n`` pixels
    (the Poisson spread of ``X``), censored pixels left out.

    Parameters
    ----------
    y : ndarray, shape (rows, cols)
        The window (photons).
    mu : ndarray, shape (rows, cols)
        The fit's expected photons per pixel.
    error_var : ndarray, shape (rows, cols), or None
        The model error's variance (photons^2; :func:`model_error_variance` of the window's
        emitters), added to ``V``; None for an exact model.
    noise_factor : float
        The camera's variance per expected photon (:func:`pixel_variance`).
    rv : float or ndarray
        Read-noise variance (photons^2), scalar or the window's map.
    censored : ndarray of bool, shape (rows, cols), optional
        Pixels at the camera's saturation (their values say nothing of ``mu``).

    Returns
    -------
    float
        The excess of ``X`` in its standard deviations.
    """
    var = pixel_variance(mu, noise_factor) + rv
    if error_var is not None:
        var = var + error_var
    chi = (y - mu) ** 2 / var
    spread = 2.0 + 1.0 / np.maximum(mu, 1.0)
    n = np.size(y)
    if censored is not None:
        keep = ~np.asarray(censored, bool)
        chi, spread, n = chi[keep], spread[keep], int(keep.sum())
    return (float(np.sum(chi)) - n) / np.sqrt(max(float(np.sum(spread)), 1e-12))
