"""Compiled evaluation of a cubic B-spline PSF table (numba), with a NumPy reference beside it.

:meth:`SplinePSF._images <sparseloc.psf.spline.SplinePSF>` spends most of its time in Python
and small-array overhead when it is called thousands of times on small windows (the
maximum-likelihood fits of a frame call it once per iteration). This kernel does the same
three gathers (z planes, x columns, y rows) in one compiled loop per emitter: same numbers,
no temporaries. It is used when numba is importable and ``SPARSELOC_NUMBA`` is not ``0``;
otherwise the NumPy path runs. ``tests/test_compiled.py`` checks that the two agree.
"""

from __future__ import annotations

import logging
import os

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

__all__ = ["available", "spline_images"]

_kernel = None
_tried = False


def available() -> bool:
    """Whether the compiled kernel can be used (numba importable, not disabled)."""
    return _get() is not None


def _get():
    global _kernel, _tried
    if os.environ.get("SPARSELOC_NUMBA", "1") == "0":
        return None
    if not _tried:
        _tried = True
        try:
            _kernel = _compile()
        except Exception as exc:  # any numba failure means: use NumPy
            log.warning(
                "numba kernels unavailable (%s): using the NumPy paths (same results, ~2-8x "
                "slower fits)",
                exc,
            )
            _kernel = None
    return _kernel


def _compile():
    # numba is imported, and the kernels compiled (or loaded from numba's cache), on first
    # use only. Compiling is lazy in numba, so both kernels run once here on tiny inputs: a
    # failure then means NumPy, not an error in the middle of a fit.
    from ._spline_numba import spline_kernel

    coef = np.zeros((6, 6, 6))
    one = np.ones(1)
    spline_kernel(coef, one, one, one, 2, 2, 1, np.empty((1, 2, 2)), np.empty((1, 3, 2, 2)), True)
    from ..solvers._fit_numba import lm_fit

    geo = np.array([2.0, 2.0, 1.0, 100.0, 50.0, 50.0, 0.0, 10.0, 2.0])
    y = np.full((2, 2), 5.0)
    lm_fit(
        coef,
        geo,
        y,
        np.zeros((2, 2)),
        np.zeros((2, 2)),
        np.ones((1, 2, 2)),
        1.0,
        np.array([100.0, 100.0, 10.0, 100.0, 5.0]),
        1,
        np.array([0.0, 0.0, 0.0, 1.0]),
        np.array([200.0, 200.0, 20.0, np.inf]),
        1e-3,
        2,
        1e-6,
    )
    return spline_kernel


def spline_images(
    coef: NDArray[np.float64],
    tz: NDArray[np.float64],
    tx: NDArray[np.float64],
    ty: NDArray[np.float64],
    shape: tuple[int, int],
    stride: int,
    derivatives: bool,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Images (and raw derivatives in spline-node units) of K emitters, compiled.

    Parameters
    ----------
    coef : ndarray, shape (Nz + 2, Ny + 1, Nx + 1)
        Spline coefficients with one mirrored plane at each z end and a zero last row and
        column (where out-of-table indices point).
    tz, tx, ty : ndarray, shape (K,)
        Fractional plane index and the positions of pixel (0, 0) in node units.
    shape : (rows, cols)
        Window size (pixels).
    stride : int
        Nodes per pixel (the table's oversampling).
    derivatives : bool
        Also return d/dtx, d/dty, d/dtz (per node unit; the caller scales them).

    Returns
    -------
    out : ndarray, shape (K, rows, cols)
    der : ndarray, shape (K, 3, rows, cols) or None
    """
    kern = _get()
    if kern is None:
        raise RuntimeError("the compiled spline kernel is unavailable")
    rows, cols = shape
    k = tz.shape[0]
    out = np.empty((k, rows, cols))
    der = np.empty((k, 3, rows, cols)) if derivatives else np.empty((0, 3, 1, 1))
    kern(
        np.ascontiguousarray(coef, dtype=np.float64),
        np.ascontiguousarray(tz, dtype=np.float64),
        np.ascontiguousarray(tx, dtype=np.float64),
        np.ascontiguousarray(ty, dtype=np.float64),
        int(rows),
        int(cols),
        int(stride),
        out,
        der,
        bool(derivatives),
    )
    return out, (der if derivatives else None)
