"""The model check after a run: do the PSF and the noise model describe the data?

Every fitted window reports its deviance per degree of freedom (the table's ``gof``). Where
the model and the noise model describe the data, a window's deviance follows approximately a
chi-square distribution with the window's ``dof`` degrees of freedom (pixels less fitted
parameters; Wilks' theorem, the large-count limit of the Poisson deviance), so ``gof`` has
mean 1 and standard deviation ``sqrt(2 / dof)``.

The check compares the median ``gof`` over the windows with one window's chi-square
quantiles at :data:`ALPHA`. A median beyond the upper quantile means that more than half of
the windows fail the goodness-of-fit test at level ``ALPHA``, which a correct model does for
a fraction ``ALPHA`` of them: the model (or the noise model) does not describe the data. A
median below the lower quantile means less noise than the noise model expects (a gain set
too low, an EMCCD declared for a camera without EM gain, read noise overstated).

In crowded frames (most fitted windows holding more than :data:`CROWDED_EMITTERS` emitters)
a correct model fails the check too: the light of emitters the solver could not resolve is
left in every window, single-emitter windows included, so those cannot stand in for the
check. A wrong PSF looks crowded as well (the solver explains each image with several
emitters of the wrong shape), so the message names the wrong model first and the crowding
after it, with the localizations' density for the user to compare with the sample's.

A bead calibration measures how far its own model misses its beads (the model error,
:mod:`sparseloc.solvers.variance`): coarse pixels, a truncated ROI or few beads make it larger,
and every window's deviance then carries that error's expected share, ``sum(E / V)`` (the
count selection's allowance). The upper limit is raised by the median of that share per
degree of freedom over the windows, so the check flags misfit beyond what the calibration
says its model misses; an exact model adds nothing.

The yardstick is one window's spread, not the median's own sampling spread: that shrinks as
``1 / sqrt(windows)``, so on a long movie it would reject every model short of exact (a spline
table of a pupil model is ~1 % off), and the verdict would depend on the movie's length.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["ALPHA", "CROWDED_EMITTERS", "LOW_COUNT", "ModelCheck", "check_fit"]

#: Level of the per-window goodness-of-fit test whose quantiles bound the median ``gof``.
ALPHA = 1e-3

#: Median background (photons per pixel, on the likelihood's scale) below which the lower
#: limit is not applied: there a correct model's Poisson deviance per pixel falls below 1
#: (1.01 at 0.5 photons, 0.84 at 0.3, 0.47 at 0.1), so a low ``gof`` is expected.
LOW_COUNT = 0.5

#: Emitters per fitted window above which (in the median) the frames count as crowded: most
#: fits are then of groups of three or more overlapping images.
CROWDED_EMITTERS = 2

_CROWDED = (
    "; or crowding: a median of {k:g} emitters per fitted window{density}, whose unresolved "
    "light raises the goodness of fit with any model (if the sample is that dense, the model "
    "may be right; a wrong PSF or camera setting inflates both counts)"
)
_CAUSES_HIGH = (
    "likely causes: the wrong PSF (a calibration or mask of another microscope, or the "
    "built-in default where another was meant), wrong camera settings (offset, gain in "
    "e-/ADU), read noise not given for an sCMOS camera, an EMCCD camera not declared or "
    "its EM gain not given (--em-gain), or a background that changes across the field "
    "(an illumination profile, a haze: --haze lets the fits follow it)"
)
_CAUSES_LOW = (
    "likely causes: an offset set too low (the camera's dark level then counts as light), a "
    "gain (e-/ADU) set too low, an EMCCD camera declared for one without EM gain, or read "
    "noise overstated"
)


@dataclass(frozen=True)
class ModelCheck:
    """The verdict of :func:`check_fit` and the numbers behind it.

    Attributes
    ----------
    verdict : {"ok", "misfit", "too_little_noise", "unchecked"}
        ``"unchecked"``: no fitted window to judge.
    median_gof : float
        Median deviance per degree of freedom over the windows (NaN without windows).
    fits : int
        Fitted windows (the frame solver's groups) judged, one ``gof`` each.
    dof : float
        Median degrees of freedom of a window.
    lower, upper : float
        The chi-square quantiles (``ALPHA`` and ``1 - ALPHA``) of one window's ``gof``.
    alpha : float
        The test's level.
    message : str
        One sentence for the user: the verdict and, for a failed check, the likely causes.
    emitters : float
        Median emitters per fitted window (NaN when not given).
    """

    verdict: str
    median_gof: float
    fits: int
    dof: float
    lower: float
    upper: float
    alpha: float
    message: str
    emitters: float = float("nan")

    @property
    def ok(self) -> bool:
        """Whether the check found nothing wrong (``"ok"`` or ``"unchecked"``)."""
        return self.verdict in ("ok", "unchecked")

    def to_dict(self) -> dict:
        """Plain numbers and text, for a table's JSON metadata."""
        return {k: (float(v) if isinstance(v, np.floating) else v) for k, v in asdict(self).items()}

    def summary(self) -> str:
        """One line for a run's summary."""
        if self.verdict == "unchecked":
            return "model check: no fits to check"
        m = f"median goodness of fit {self.median_gof:.2f} over {self.fits} fits"
        if self.verdict == "ok":
            return f"model check: ok, {m} (a correct model: {self.lower:.2f}-{self.upper:.2f})"
        side = f"above {self.upper:.2f}" if self.verdict == "misfit" else f"below {self.lower:.2f}"
        return f"model check: {self.verdict.replace('_', ' ')}, {m}, {side} (see the warning)"


def check_fit(
    gof: ArrayLike,
    dof: ArrayLike,
    background: ArrayLike | None = None,
    emitters: ArrayLike | None = None,
    *,
    density: float | None = None,
    alpha: float = ALPHA,
    unresolved_ratio: float | None = None,
    allowance: ArrayLike | None = None,
) -> ModelCheck:
    """Judge a run by the median goodness of fit of its windows (see the module notes).

    Parameters
    ----------
    gof : array_like, shape (W,)
        Deviance per degree of freedom of each window (one value per window, not per
        localization). Non-finite values are left out.
    dof : array_like, shape (W,)
        Each window's degrees of freedom; the limits use their median.
    background : array_like, shape (W,), optional
        Each window's background (photons per pixel, on the likelihood's scale); the lower
        limit applies only where their median is at least :data:`LOW_COUNT`.
    emitters : array_like, shape (W,), optional
        Emitters fitted in each window; a median above :data:`CROWDED_EMITTERS` names the
        crowding as a cause of a failed check, after the model's.
    density : float, optional
        Localizations per um^2 per frame, stated with the crowding.
    alpha : float
        Level of the per-window test.
    unresolved_ratio : float, optional
        The count selection's addition threshold (a likelihood ratio): an emitter left
        unresolved for its ratio adds less than this to its window's deviance (one rejected
        for too few photons or by the model error's allowance may add more). Crowding is
        named as a cause only where the median ``gof`` lies within what as many unresolved
        emitters as fitted ones add, ``upper + k * ratio / dof``: a rough bound (the unresolved
        are not counted), far beyond which crowding is not a plausible cause.
    allowance : array_like, optional
        The calibration's model error's expected share of windows' deviance per degree of
        freedom (``sum(E / V) / dof``, the count selection's allowance,
        :mod:`sparseloc.solvers.variance`), for a sample of windows: the upper limit is raised
        by their median, the misfit the model is known to have (a bead calibration on coarse
        pixels misses its beads by more than one on fine pixels, and says so).

    Returns
    -------
    ModelCheck
    """
    from scipy.stats import chi2

    g = np.asarray(gof, dtype=np.float64).ravel()
    d = np.asarray(dof, dtype=np.float64).ravel()
    if g.shape != d.shape:
        raise ValueError(f"gof has {g.size} values but dof {d.size}")
    keep = np.isfinite(g) & np.isfinite(d) & (d >= 1)
    g, d = g[keep], d[keep]
    if not g.size:
        nan = float("nan")
        return ModelCheck("unchecked", nan, 0, nan, nan, nan, alpha, "no fits to check")
    k = float(np.median(d))
    lower, upper = float(chi2.ppf(alpha, k) / k), float(chi2.ppf(1.0 - alpha, k) / k)
    known = _known_misfit(allowance)
    upper += known
    med = float(np.median(g))
    bg = None if background is None else np.asarray(background, dtype=np.float64).ravel()[keep]
    counts_ok = bg is None or float(np.nanmedian(bg)) >= LOW_COUNT
    k_med = (
        float("nan")
        if emitters is None
        else float(np.median(np.asarray(emitters, dtype=np.float64).ravel()[keep]))
    )
    dens = f" ({density:.2g} localizations per um^2 per frame with this model)" if density else ""
    reach = np.inf if unresolved_ratio is None else upper + k_med * unresolved_ratio / k
    crowding = k_med > CROWDED_EMITTERS and med <= reach
    crowded = _CROWDED.format(k=k_med, density=dens) if crowding else ""
    said = (
        f"the median goodness of fit (deviance per degree of freedom) of {g.size} fits is {med:.2f}"
    )
    if med > upper:
        verdict = "misfit"
        with_error = (
            f" (with {known:.2g} for the calibration's measured model error)" if known else ""
        )
        message = (
            f"the model does not describe the data: {said}, above {upper:.2f}{with_error}, "
            f"which fewer than {alpha:.1%} of the fits of a correct model exceed; "
            f"{_CAUSES_HIGH}{crowded}"
        )
    elif med < lower and counts_ok:
        verdict = "too_little_noise"
        message = (
            f"the noise model does not describe the data: {said}, below {lower:.2f}, which "
            f"fewer than {alpha:.1%} of the fits of a correct model fall under; {_CAUSES_LOW}"
        )
    else:
        verdict = "ok"
        message = f"the model describes the data: {said} (a correct model: about 1)"
    return ModelCheck(verdict, med, int(g.size), k, lower, upper, float(alpha), message, k_med)


def _known_misfit(allowance: ArrayLike | None) -> float:
    """The median of the windows' model-error allowances per degree of freedom (0 without)."""
    if allowance is None:
        return 0.0
    a = np.asarray(allowance, dtype=np.float64).ravel()
    a = a[np.isfinite(a)]
    return float(np.median(a)) if a.size else 0.0
