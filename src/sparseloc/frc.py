"""Fourier ring correlation (FRC) resolution of a 2D localization set (Nieuwenhuizen et al.,
Nat. Methods 10, 557, 2013); :mod:`sparseloc.render` re-exports everything here.

The localizations are split in two halves, each is binned on the same grid (counts per
``px_nm`` pixel), and the FRC of the two images is computed over rings one frequency step wide
(``1 / (max(rows, cols) px_nm)``) from the first ring up to Nyquist. The curve is smoothed with
a Gaussian over ``smooth_rings`` rings; the resolution is ``1 / q`` where the smoothed curve
first falls below 1/7, linearly interpolated between rings.

Splits: ``"blocks"`` (default) cuts the frame range into ``n_blocks`` equal blocks of
consecutive frames and gives even blocks to one half, odd to the other, so that a molecule's
repeated localizations in consecutive frames stay together (splitting them correlates the
halves' noise and makes the resolution look too good). ``"random"`` assigns localizations at
random (balanced, seeded) and is optimistic for such data.

A set with no structure finer than the field (e.g. uniform random points) correlates only at
the lowest frequencies, where the two halves share the field's outline; its curve drops below
1/7 within the first few rings and the "resolution" is a sizeable fraction of the field. When
the curve is below 1/7 already at the first ring, or never falls below it, ``resolution_nm``
is NaN and ``warning`` says why.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy import ndimage as ndi

from .render_grid import axis_grid, check_size, check_table, finite_rows, positive_nm

__all__ = ["FRC_THRESHOLD", "FRCResult", "frc", "frc_report", "plot_frc"]

# Messages keep the logger of sparseloc.render, where the FRC has always logged.
log = logging.getLogger("sparseloc.render")

#: The FRC threshold (Nieuwenhuizen et al. 2013).
FRC_THRESHOLD: float = 1.0 / 7.0


@dataclass(frozen=True)
class FRCResult:
    """Fourier ring correlation of two half data sets.

    Attributes
    ----------
    frequency : ndarray, shape (n_rings,)
        Ring centres (1/nm), from the first non-zero ring up to the Nyquist frequency.
    curve : ndarray, shape (n_rings,)
        Smoothed FRC.
    curve_raw : ndarray, shape (n_rings,)
        FRC before smoothing.
    resolution_nm : float
        ``1 / q`` at the first crossing of ``threshold`` (nm), NaN when there is none.
    threshold : float
        The threshold (1/7).
    warning : str
        Why ``resolution_nm`` is NaN; empty otherwise.
    n_halves : (int, int)
        Localizations in each half.
    px_nm : float
        Pixel size of the half images (nm).
    split : str
        ``"blocks"`` or ``"random"``.
    """

    frequency: NDArray[np.float64]
    curve: NDArray[np.float64]
    curve_raw: NDArray[np.float64]
    resolution_nm: float
    threshold: float = FRC_THRESHOLD
    warning: str = ""
    n_halves: tuple[int, int] = (0, 0)
    px_nm: float = float("nan")
    split: str = "blocks"
    extra: dict[str, Any] = field(default_factory=dict)


def frc(
    locs: pd.DataFrame,
    *,
    px_nm: float = 5.0,
    split: str = "blocks",
    n_blocks: int = 20,
    seed: int = 0,
    extent: tuple[float, float, float, float] | None = None,
    smooth_rings: float | None = None,
    shuffle_blocks: bool = False,
) -> FRCResult:
    """Fourier ring correlation resolution of a 2D (xy) localization set.

    The method, the splits and what a set without structure gives are described in the
    module docstring.

    Parameters
    ----------
    locs : DataFrame
        Needs ``x_nm``, ``y_nm``, and ``frame`` for ``split="blocks"``.
    px_nm : float
        Bin size (nm); should be a few times finer than the resolution.
    split : {"blocks", "random"}
    n_blocks : int
        Number of frame blocks (at least 2).
    seed : int
        Seed of the random split.
    extent : (x0, x1, y0, y1), optional
        Image edges (nm); default the data bounds plus two pixels.
    smooth_rings : float, optional
        Standard deviation (rings) of the smoothing; default ``max(1, n_rings / 100)``.
    shuffle_blocks : bool
        With ``split="blocks"``: give the blocks to the halves by a random (``seed``),
        balanced assignment instead of alternately; another valid split of the same data.

    Returns
    -------
    FRCResult
    """
    px = positive_nm(px_nm, "px_nm")
    if split not in ("blocks", "random"):
        raise ValueError(f"split must be 'blocks' or 'random', got {split!r}")
    check_table(locs, ("x", "y"))
    pos, ok = finite_rows(locs, ("x", "y"))
    half, counts = _halves(locs, ok, pos.shape[0], split, n_blocks, seed, shuffle_blocks)
    x0, y0, nx, ny = _frc_grid(pos, px, extent)
    spectra, shape = _half_spectra(pos, half, px, (x0, y0, nx, ny))
    freq, raw = _ring_correlation(spectra, shape, px)
    width = max(1.0, freq.size / 100.0) if smooth_rings is None else float(smooth_rings)
    curve = ndi.gaussian_filter1d(raw, width, mode="nearest") if width > 0 else raw.copy()
    res, warning = _resolution(curve, freq, px)
    if warning:
        # Logged at INFO: the result carries the warning, and render, the report and the FRC
        # plot state it; a log warning besides printed it twice on a correct run's terminal.
        log.info("FRC: %s", warning)
    return FRCResult(
        frequency=freq,
        curve=curve,
        curve_raw=raw,
        resolution_nm=res,
        threshold=FRC_THRESHOLD,
        warning=warning,
        n_halves=counts,
        px_nm=px,
        split=split,
        extra={"extent_nm": (x0, x0 + nx * px, y0, y0 + ny * px), "smooth_rings": width},
    )


#: Other splits of the frame blocks that :func:`frc_report` repeats the FRC over.
SPREAD_SPLITS: int = 4
#: The FRC's range over those splits, as a fraction of its value, above which the report
#: cautions that the data are too few for the resolution to be measured.
SPREAD_CAUTION: float = 0.25


def frc_report(locs: pd.DataFrame) -> tuple[FRCResult | None, str]:
    """The FRC of a table as ``render`` and the report give it, and its one-line message.

    Bins of 5 nm, coarser on wide fields so that the half images stay under about 8000 px a
    side. The FRC is repeated over :data:`SPREAD_SPLITS` random assignments of the frame
    blocks to the halves; the message gives the range, with a caution where it exceeds
    :data:`SPREAD_CAUTION` of the value (few localizations: the number measures the split,
    not the resolution). A table the FRC cannot use gives ``None`` and a message saying why.

    Parameters
    ----------
    locs : DataFrame
        Localizations (``x_nm``, ``y_nm``, ``frame``), e.g. the rows that render draws.

    Returns
    -------
    (FRCResult or None, str)
        The result (its ``extra["spread_nm"]`` the other splits' resolutions) and e.g.
        ``"FRC resolution: 33.9 nm (32.7-34.1 nm over 4 other splits of the frame blocks)"``.
    """
    span = float(max(np.ptp(locs["x_nm"]), np.ptp(locs["y_nm"]), 1.0))
    px = max(5.0, span / 8000.0)
    try:
        res = frc(locs, px_nm=px)
    except ValueError as exc:
        return None, f"FRC not computed: {exc}"
    if not np.isfinite(res.resolution_nm):
        return res, f"FRC resolution: not determined ({res.warning})"
    others = np.array(
        [
            frc(locs, px_nm=px, shuffle_blocks=True, seed=k).resolution_nm
            for k in range(1, SPREAD_SPLITS + 1)
        ]
    )
    res.extra["spread_nm"] = others.tolist()
    msg = f"FRC resolution: {res.resolution_nm:.1f} nm"
    if not np.all(np.isfinite(others)):
        return res, msg + (
            f"; caution: not determined on {int(np.sum(~np.isfinite(others)))} of "
            f"{others.size} other splits of the frame blocks ({sum(res.n_halves)} "
            "localizations): too few to measure the resolution"
        )
    lo, hi = min(others.min(), res.resolution_nm), max(others.max(), res.resolution_nm)
    msg += f" ({lo:.1f}-{hi:.1f} nm over {others.size} other splits of the frame blocks)"
    if hi - lo > SPREAD_CAUTION * res.resolution_nm:
        msg += (
            f"; caution: it depends on the split ({sum(res.n_halves)} localizations): too few "
            "to measure the resolution"
        )
    return res, msg


def _halves(
    locs: pd.DataFrame,
    ok: NDArray[np.bool_],
    n: int,
    split: str,
    n_blocks: int,
    seed: int,
    shuffle_blocks: bool = False,
) -> tuple[NDArray[np.bool_], tuple[int, int]]:
    """Which half each of the ``n`` finite rows goes to, and the count of each half."""
    span = "n/a"
    if split == "blocks":
        if int(n_blocks) < 2:
            raise ValueError(f"n_blocks must be at least 2, got {n_blocks!r}")
        if "frame" not in locs.columns:
            raise ValueError("FRC by blocks of frames needs a 'frame' column; the table has none")
        frames = locs["frame"].to_numpy()[ok].astype(np.int64)
        f0, f1 = int(frames.min()), int(frames.max())
        # Fewer frames than blocks: one block per frame (else short tables fall in one half).
        nb = min(int(n_blocks), f1 - f0 + 1)
        block = (frames - f0) * nb // (f1 - f0 + 1)
        order = np.random.default_rng(seed).permutation(nb) if shuffle_blocks else np.arange(nb)
        half = (order % 2 == 1)[block]
        span = f"{f0}..{f1}"
    else:
        half = np.random.default_rng(seed).permutation(n) % 2 == 1
    counts = (int((~half).sum()), int(half.sum()))
    if min(counts) == 0:
        raise ValueError(
            f"the {split} split left the halves with {counts[0]} and {counts[1]} localizations; "
            f"FRC needs both (the table's frames span {span}: too few to split by blocks)"
        )
    return half, counts


def _frc_grid(
    pos: NDArray, px: float, extent: tuple[float, float, float, float] | None
) -> tuple[float, float, int, int]:
    """Start (nm) and pixel count along x and y of the half images: ``x0, y0, nx, ny``."""
    if extent is None:
        lo, hi = pos.min(axis=0) - 2 * px, pos.max(axis=0) + 2 * px
        x0 = math.floor(lo[0] / px) * px
        y0 = math.floor(lo[1] / px) * px
        nx = max(2, math.ceil((hi[0] - x0) / px))
        ny = max(2, math.ceil((hi[1] - y0) / px))
        return x0, y0, nx, ny
    if len(extent) != 4:
        raise ValueError(f"extent must be (x0, x1, y0, y1) in nm, got {extent!r}")
    x0, nx = axis_grid(pos[:, 0], np.zeros(1), px, extent[:2], "x")
    y0, ny = axis_grid(pos[:, 1], np.zeros(1), px, extent[2:], "y")
    return x0, y0, nx, ny


def _half_spectra(
    pos: NDArray, half: NDArray[np.bool_], px: float, grid: tuple[float, float, int, int]
) -> tuple[list[NDArray], tuple[int, int]]:
    """Real FFTs of the two halves' count images on ``grid`` (``x0, y0, nx, ny``), and the
    padded image shape."""
    from scipy import fft

    x0, y0, nx, ny = grid
    # Zero padding to fast FFT sizes changes nothing: both images are zero there.
    shape = (fft.next_fast_len(ny, real=True), fft.next_fast_len(nx, real=True))
    check_size(shape, "FRC image")
    col = np.floor((pos[:, 0] - x0) / px).astype(np.int64)
    row = np.floor((pos[:, 1] - y0) / px).astype(np.int64)
    inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    if not inside.all():
        log.info("FRC: %d localizations outside the extent are ignored", (~inside).sum())
    flat = row * shape[1] + col
    spectra = []
    for sel in (~half & inside, half & inside):
        img = np.zeros(shape[0] * shape[1], dtype=np.float32)
        np.add.at(img, flat[sel], 1.0)
        spectra.append(fft.rfft2(img.reshape(shape), workers=-1))
        del img
    return spectra, shape


def _ring_correlation(
    spectra: list[NDArray], shape: tuple[int, int], px: float
) -> tuple[NDArray, NDArray]:
    """Ring frequencies (1/nm) from the first ring to Nyquist, and the FRC on each ring."""
    qy = np.fft.fftfreq(shape[0], d=px)
    qx = np.fft.rfftfreq(shape[1], d=px)
    dq = 1.0 / (max(shape) * px)
    n_rings = math.floor(0.5 / px / dq)
    # rfft2 holds half the plane: every column but the first (and the Nyquist one, for even
    # widths) stands for itself and its mirror image.
    mult = np.full(qx.size, 2.0)
    mult[0] = 1.0
    if shape[1] % 2 == 0:
        mult[-1] = 1.0
    sums = np.zeros((3, n_rings + 1))
    step = max(1, 4_000_000 // qx.size)  # row blocks bound the memory of the ring sums
    for r0 in range(0, shape[0], step):
        a, b = spectra[0][r0 : r0 + step], spectra[1][r0 : r0 + step]
        ring = np.rint(np.hypot(qy[r0 : r0 + step, None], qx[None, :]) / dq).astype(np.int64)
        keep = ring <= n_rings
        r = ring[keep]
        m = np.broadcast_to(mult, ring.shape)[keep]
        a, b = a[keep], b[keep]
        for j, prod_ in enumerate(
            (a.real * b.real + a.imag * b.imag, a.real**2 + a.imag**2, b.real**2 + b.imag**2)
        ):
            sums[j] += np.bincount(r, weights=m * prod_, minlength=n_rings + 1)
    num, p1, p2 = sums
    with np.errstate(invalid="ignore", divide="ignore"):
        raw = (num / np.sqrt(p1 * p2))[1:]
    raw = np.nan_to_num(raw, nan=0.0)
    freq = np.arange(1, n_rings + 1) * dq
    return freq, raw


def _resolution(curve: NDArray, freq: NDArray, px: float) -> tuple[float, str]:
    """``1 / q`` (nm) where ``curve`` first falls below :data:`FRC_THRESHOLD`, else NaN and
    the reason."""
    thr = FRC_THRESHOLD
    below = np.flatnonzero(curve < thr)
    if below.size == 0:
        warning = (
            f"the FRC never falls below 1/7 up to the Nyquist frequency 1/{2 * px:g} nm: the "
            "resolution is finer than two bins; use a smaller px_nm"
        )
        return float("nan"), warning
    if below[0] == 0:
        warning = (
            f"the FRC is below 1/7 already at the lowest frequency (1/{1 / freq[0]:.0f} nm): "
            "the two halves share no structure"
        )
        return float("nan"), warning
    k = int(below[0])
    c0, c1 = curve[k - 1], curve[k]
    q = freq[k - 1] + (c0 - thr) / (c0 - c1) * (freq[k] - freq[k - 1])
    return float(1.0 / q), ""


def plot_frc(result: FRCResult, path: str | Path) -> Path:
    """Plot an FRC curve (raw and smoothed) with the 1/7 threshold and the resolution.

    Parameters
    ----------
    result : FRCResult
        From :func:`frc`.
    path : str or Path
        Output image (e.g. ``.png``), written atomically.

    Returns
    -------
    Path
    """
    from matplotlib.figure import Figure

    from .plotting import save_figure

    fig = Figure(figsize=(6.0, 4.0), layout="constrained")
    ax = fig.subplots()
    q = result.frequency * 1000.0  # 1/um reads better than 1/nm
    ax.plot(q, result.curve_raw, color="0.7", lw=0.8, label="FRC")
    ax.plot(q, result.curve, color="tab:blue", lw=1.6, label="smoothed")
    ax.axhline(result.threshold, color="tab:red", ls="--", lw=1.0, label="1/7")
    if math.isfinite(result.resolution_nm):
        ax.axvline(1000.0 / result.resolution_nm, color="tab:green", lw=1.0)
        title = f"FRC resolution {result.resolution_nm:.1f} nm"
    else:
        title = "FRC resolution not determined"
        ax.text(0.02, 0.04, result.warning, transform=ax.transAxes, fontsize=7, wrap=True)
    ax.set_xlabel("spatial frequency (1/µm)")
    ax.set_ylabel("FRC")
    ax.set_ylim(-0.2, 1.05)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    n0, n1 = result.n_halves
    ax.set_title(f"{title}  ({result.split} split, {n0:,} / {n1:,} locs)", fontsize=10)
    return save_figure(fig, path)
