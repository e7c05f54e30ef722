"""What a frame's localizations leave unexplained, and what they claim without light.

The check a microscopist makes by eye over an overlay (one marker per PSF image, none on the
background), as numbers and a picture. The localizations of one frame, rendered with the PSF
model over the frame's background estimate, make the frame's model image; then:

- **support** of each localization: ``2 (log L - log L_without)``, the frame's likelihood
  with its light against without it, the other localizations fixed. Where the check's model
  of a window is the fit's (the same background and light), refitting the others could only
  lower the ratio, so it would bound the removal test's from above; the check's background
  and light are only close to the fits' (below), so it approximates that bound. A marker on
  empty background has little support.
- **unexplained light**: the detection test (:func:`~sparseloc.detect.detect_candidates`)
  on the frame less the localizations' light, its variance with their shot noise: each
  significant peak is a PSF image, or part of one, that no localization explains.
- the **residual** in noise standard deviations, ``(frame - model) / sqrt(variance)``, for
  the picture (:func:`residual_figure`).

The variance is the likelihood's, ``mu / w + v`` (shot noise ``F mu / qe``, read variance
``v``); the unexplained peaks' signal-to-noise is taken with it, so that its square
approximates the likelihood ratio of an emitter added there (compare it with the count
selection's bar). The peaks themselves are found by the run's detection test, on its own
scale (``F mu + v``, :func:`~sparseloc.detect.detect_candidates`).

The likelihood is the fits' (:mod:`sparseloc.solvers.mle`: Poisson in photons, weighted by
``qe / noise factor``, shifted by the read variance for sCMOS and EMCCD read noise). Each
localization's light is counted within a detection template's box around it: as in the
solver's windows, the light of a model's far halo lies in the background estimate. The
background is the run's estimate except within each localization's box, where the table gives
its window's fitted constant (``window_background``): a spatial estimate over a dense cell
holds much of its emitters' light, which the fits' free backgrounds leave out. Each support
takes its own window's constant, as its fit did; the picture and the unexplained light take
the mean where boxes overlap.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .detect import detect_candidates, snr_at
from .psf.base import PSFModel
from .solvers.mle import likelihood_weight
from .solvers.variance import noise_factor_of

__all__ = ["FrameResidual", "frame_residual", "residual_figure"]


@dataclass(frozen=True)
class FrameResidual:
    """The check of one frame's localizations (see the module notes).

    Attributes
    ----------
    frame : ndarray, shape (rows, cols)
        The frame (photons).
    emitters : ndarray, shape (K, 4)
        The localizations checked: x, y, z (nm), photons.
    model_image : ndarray, shape (rows, cols)
        Background plus the localizations' light (photons/pixel).
    residual : ndarray, shape (rows, cols)
        ``(frame - model_image) / sqrt(variance)``: noise standard deviations.
    support : ndarray, shape (K,)
        Each localization's ``2 delta log L`` against the frame without it (others fixed).
    unexplained : ndarray, shape (M, 2)
        Pixels (row, col) of significant peaks in the frame less the localizations' light,
        strongest first.
    unexplained_snr : ndarray, shape (M,)
        Their signal-to-noise with the likelihood's variance (noise standard deviations): its
        square approximates the likelihood ratio of an emitter added there.
    """

    frame: NDArray[np.float64]
    emitters: NDArray[np.float64]
    model_image: NDArray[np.float64]
    residual: NDArray[np.float64]
    support: NDArray[np.float64]
    unexplained: NDArray[np.float64]
    unexplained_snr: NDArray[np.float64]

    def summary(self, bar: float, min_snr: float) -> str:
        """Two sentences: the localizations' support against ``bar`` (the count selection's
        threshold on ``2 delta log L``, the likelihood's scale) and the peaks above ``min_snr``
        left unexplained, with those above ``sqrt(bar)`` (an emitter added there would about
        pass the bar: the squared signal-to-noise approximates its ratio)."""
        s = np.sort(self.support)
        if len(s):
            lowest = ", ".join(f"{v:.0f}" for v in s[:3])
            first = (
                f"{len(s)} localizations: support (2 delta log L with and without each, the "
                f"others fixed) median {np.median(s):.0f}, lowest {lowest}; "
                f"{int(np.sum(s < bar))} below the count selection's bar of {bar:g}"
            )
        else:
            first = "no localizations"
        strong = int(np.sum(self.unexplained_snr > np.sqrt(bar)))
        return (
            f"{first}; {len(self.unexplained)} peaks above {min_snr:g} noise SD left in the "
            f"frame less their light, {strong} of them above {np.sqrt(bar):.1f} SD"
        )


def frame_residual(
    frame: ArrayLike,
    background: ArrayLike,
    model: PSFModel,
    emitters: ArrayLike,
    pixel_size: float,
    *,
    noise: str = "poisson",
    qe: float = 1.0,
    read_variance: ArrayLike = 0.0,
    templates: ArrayLike,
    min_snr: float = 5.0,
    window_background: ArrayLike | None = None,
    known_light: ArrayLike | None = None,
) -> FrameResidual:
    """Check one frame's localizations against the frame (see the module notes).

    Parameters
    ----------
    frame : array_like, shape (rows, cols)
        The frame in photons (offset removed, gain applied).
    background : array_like, shape (rows, cols) or scalar
        Its background estimate (photons/pixel).
    model : PSFModel
        The PSF model the localizations were fitted with.
    emitters : array_like, shape (K, 4)
        The frame's localizations: x, y, z (nm, the tables' coordinates) and photons.
    pixel_size : float
        Pixel size (nm).
    noise : {"poisson", "scmos", "emccd"}
        The run's noise model.
    qe : float
        The run's quantum efficiency (the likelihood's weight).
    read_variance : array_like
        Read noise variance (photons^2, scalar or a map of the frame's shape) for sCMOS or an
        EMCCD's read noise; 0 for photon counting.
    min_snr : float
        The detection threshold of the unexplained-light test (noise standard deviations),
        as the run's ``min_snr``.
    window_background : array_like, shape (K,), optional
        Each localization's fitted background (photons/pixel, the tables' ``background``):
        the background within its box instead of ``background`` (the mean where boxes
        overlap; each localization's support takes its own).
    known_light : array_like, shape (rows, cols), optional
        Light the run knew besides the localizations' (photons/pixel; bright emitters'
        halos, :func:`sparseloc.pipeline.check_frame`), added to the background.
    templates : array_like, shape (P, T, T)
        Centred unit images the unexplained-light test correlates with (odd ``T``; each
        localization's light is counted within ``T`` x ``T`` pixels): the run's detection
        planes (:func:`sparseloc.pipeline.check_frame` passes them).
    Returns
    -------
    FrameResidual
    """
    y = np.asarray(frame, dtype=np.float64)
    if y.ndim != 2:
        raise ValueError(f"the frame must be one image (rows, cols), got shape {y.shape}")
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), y.shape)
    em = np.asarray(emitters, dtype=np.float64).reshape(-1, 4)
    rv = np.broadcast_to(np.asarray(read_variance, dtype=np.float64), y.shape)
    templates = np.asarray(templates, dtype=np.float64)
    boxes, lights = _lights(model, em, y.shape, pixel_size, templates.shape[-1])
    light = np.zeros(y.shape)
    for (r0, r1, c0, c1), lk in zip(boxes, lights, strict=True):
        light[r0:r1, c0:c1] += lk
    own = None
    if window_background is not None:
        own = np.asarray(window_background, dtype=np.float64)
        bg = _fitted_background(bg, boxes, own)
    if known_light is not None:
        bg = bg + np.asarray(known_light, dtype=np.float64)
    mu = np.maximum(bg + light, 1e-9)
    factor = noise_factor_of(noise)
    w = likelihood_weight(noise, qe)
    variance = mu / w + rv
    residual = (y - mu) / np.sqrt(variance)
    support = _support(y, mu, bg, own, boxes, lights, w * rv, w)
    unexplained = detect_candidates(
        y,
        bg + light,
        templates,
        threshold=min_snr,
        noise_factor=factor,
        read_variance=rv,
    )
    snr = (
        snr_at(y - mu, variance, templates, unexplained.astype(np.intp))
        if len(unexplained)
        else np.zeros(0)
    )
    return FrameResidual(y, em, mu, residual, support, unexplained, snr)


def _lights(model: PSFModel, em: NDArray, shape: tuple[int, int], px: float, size: int):
    """Each localization's light (photons/pixel) over the ``size`` x ``size`` pixels centred
    on its pixel, clipped to the frame: the boxes (r0, r1, c0, c1) and the images."""
    h = size // 2
    boxes, lights = [], []
    for x, yy, z, n in em:
        r, c = int(np.floor(yy / px)), int(np.floor(x / px))
        r0, r1 = max(r - h, 0), min(r + h + 1, shape[0])
        c0, c1 = max(c - h, 0), min(c + h + 1, shape[1])
        if r0 >= r1 or c0 >= c1:  # outside the frame: no light in it
            r0 = r1 = c0 = c1 = 0
            lights.append(np.zeros((0, 0)))
        else:
            img = model.images([x], [yy], [z], (r1 - r0, c1 - c0), px, origin=(c0 * px, r0 * px))
            lights.append(n * img[0])
        boxes.append((r0, r1, c0, c1))
    return boxes, lights


def _fitted_background(bg: NDArray, boxes: list, fitted: NDArray) -> NDArray[np.float64]:
    """``bg`` with each box's pixels set to the mean of the fitted constants of the boxes
    covering them."""
    if fitted.shape != (len(boxes),):
        raise ValueError(
            f"window_background must hold one value per localization ({len(boxes)}), "
            f"got shape {fitted.shape}"
        )
    total = np.zeros(bg.shape)
    count = np.zeros(bg.shape)
    for (r0, r1, c0, c1), b in zip(boxes, fitted, strict=True):
        if np.isfinite(b):
            total[r0:r1, c0:c1] += b
            count[r0:r1, c0:c1] += 1
    return np.where(count > 0, total / np.maximum(count, 1), bg)


def _support(y, mu, bg, own, boxes, lights, v, weight: float) -> NDArray[np.float64]:
    """``2 w sum((y + v) log((mu + v) / (mu - l_k + v)) - l_k)`` over each localization's box,
    ``l_k`` its light, ``v`` the read variance on the likelihood's scale (``w`` times it, see
    :mod:`sparseloc.solvers.mle`): the likelihood ratio of the frame with and without it,
    others fixed. Where ``own`` gives its window's fitted background, ``mu`` holds that
    constant in its box, as its fit did, not the mean the picture shows."""
    out = np.empty(len(lights))
    for k, ((r0, r1, c0, c1), lk) in enumerate(zip(boxes, lights, strict=True)):
        m = mu[r0:r1, c0:c1]
        if own is not None and np.isfinite(own[k]):
            m = np.maximum(m - bg[r0:r1, c0:c1] + own[k], 1e-9)
        m = m + v[r0:r1, c0:c1]
        without = np.maximum(m - lk, 1e-9)
        yv = y[r0:r1, c0:c1] + v[r0:r1, c0:c1]
        out[k] = 2.0 * weight * float(np.sum(yv * np.log(m / without) - lk))
    return out


def residual_figure(
    check: FrameResidual,
    pixel_size: float,
    path: str | Path,
    *,
    z_range: tuple[float, float] | None = None,
    title: str = "",
    dpi: int = 100,
) -> Path:
    """Write the frame with its localizations, their model image and the residual side by
    side (x, y in µm), the unexplained peaks ringed on the residual.

    Parameters
    ----------
    check : FrameResidual
        :func:`frame_residual` of a frame.
    pixel_size : float
        Pixel size (nm).
    path : str or Path
        The picture (.png, .pdf, .svg); written to a temporary name, then renamed.
    z_range : (float, float), optional
        The colour scale of z (nm); default the localizations' range.
    title : str
        The figure's title.
    dpi : int
        Resolution of a PNG.
    """
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    from .render import DEPTH_CMAP

    y, em = check.frame, check.emitters
    rows, cols = y.shape
    extent = (0.0, cols * pixel_size / 1e3, rows * pixel_size / 1e3, 0.0)
    lo, hi = np.percentile(y, [0.5, 99.8])
    fig = Figure(figsize=(15, 5.2 * rows / cols + 2.2), layout="constrained")
    axes = fig.subplots(1, 3, sharex=True, sharey=True)
    axes[0].imshow(y, cmap="gray", vmin=lo, vmax=hi, extent=extent)
    zr = z_range or ((em[:, 2].min(), em[:, 2].max()) if len(em) else (0.0, 1.0))
    depth = ScalarMappable(Normalize(*zr), DEPTH_CMAP)
    axes[0].scatter(
        em[:, 0] / 1e3, em[:, 1] / 1e3, s=30, facecolors="none",
        edgecolors=depth.to_rgba(em[:, 2]), linewidths=1.0,
    )  # fmt: skip
    fig.colorbar(depth, ax=axes[0], location="bottom", shrink=0.6).set_label("z (nm)")
    axes[0].set_title(f"frame, {len(em)} localizations")
    mid = axes[1].imshow(check.model_image, cmap="gray", vmin=lo, vmax=hi, extent=extent)
    fig.colorbar(mid, ax=axes[1], location="bottom", shrink=0.6).set_label("photons / pixel")
    axes[1].set_title("model: background + localizations")
    im = axes[2].imshow(check.residual, cmap="RdBu_r", vmin=-5, vmax=5, extent=extent)
    u = check.unexplained
    axes[2].scatter(
        (u[:, 1] + 0.5) * pixel_size / 1e3, (u[:, 0] + 0.5) * pixel_size / 1e3,
        s=160, facecolors="none", edgecolors="k", linewidths=1.2,
    )  # fmt: skip
    fig.colorbar(im, ax=axes[2], location="bottom", shrink=0.6).set_label(
        "(frame - model) / noise SD"
    )
    axes[2].set_title(f"residual; {len(u)} unexplained peaks ringed")
    for ax in axes:
        ax.set_xlabel("x (µm)")
    axes[0].set_ylabel("y (µm)")
    if title:
        fig.suptitle(title)
    out = Path(path)
    tmp = out.with_name(f".{out.stem}.tmp{out.suffix}")
    try:
        fig.savefig(tmp, dpi=dpi)
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    return out
