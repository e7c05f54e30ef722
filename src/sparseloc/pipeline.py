"""From camera frames (photons) to a localization table.

``localize`` reads frames in blocks (any object with ``len()`` and ``frames(start, stop)``, such
as :class:`sparseloc.io.Movie`, or an array) and estimates each frame's background (a sliding
temporal percentile, or a spatial estimate for short movies). The default method, ``"frame"``,
then solves each whole frame: :func:`~sparseloc.solvers.frame.tiled_pursuit` finds the starting
emitters and :func:`~sparseloc.solvers.frame.frame_fit` fits them by groups. The window
methods (``"hybrid"``, ``"mp"``, ``"co"``) instead find candidates with the z-averaged PSF and
solve the windows that hold them (:mod:`sparseloc.detect` explains the tiling that keeps every
localization exactly once). Either way the result is a
:data:`sparseloc.io.tables.LOCS_COLUMNS` table in frame coordinates. Frames run in this
process or in a pool of worker processes, on the engine that ``LocalizeParams.engine`` chooses.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from . import __version__
from .config import METHODS, LocalizeParams
from .detect import (
    Tile,
    capped_bumps,
    detect_candidates,
    spatial_background,
    temporal_backgrounds,
    tiles,
    z_averaged_psf,
)
from .dictionary import Dictionary
from .digest import array_digest, psf_hash
from .engine import resolve_engine, use_engine
from .frame_residual import FrameResidual, frame_residual
from .io.tables import LOCS_COLUMNS, empty_locs
from .model_check import ModelCheck, check_fit
from .pool import in_processes
from .psf.base import PSFModel, light_radius
from .psf.spline import SplinePSF
from .solvers import WindowSolution, convex_solve, hybrid_solve, matching_pursuit
from .solvers.emitters import Emitters
from .solvers.frame import FrameFit, add_threshold, frame_fit, frame_templates, tiled_pursuit
from .solvers.frame_compose import (
    crowded_boxes,
    joined,
    likelier_per_region,
    same_as,
    shifted,
    subset,
)
from .solvers.frame_grow import grown_groups
from .solvers.frame_l1 import l1_templates, tiled_l1_starts
from .solvers.frame_windows import background_shape, inside, light_pieces, sum_pieces
from .solvers.halo import Halo, halo_of
from .solvers.refine import LR_THRESHOLD, refine_solution
from .solvers.two_tier import detection_match, detection_planes, solve_two_tier
from .solvers.variance import PIXEL_MAPS, cropped_maps, noise_factor_of

log = logging.getLogger(__name__)

__all__ = [
    "METHODS",
    "LocalizeParams",
    "LocalizeResult",
    "addition_bar",
    "check_frame",
    "check_model",
    "localize",
    "psf_hash",
    "run_templates",
    "work_model_for",
]


@dataclass
class LocalizeResult:
    """The table and a summary of the run."""

    table: pd.DataFrame
    n_frames: int
    n_windows: int
    seconds: float
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def per_second(self) -> float:
        return len(self.table) / max(self.seconds, 1e-9)

    def summary(self) -> str:
        """One line: frames, fitted groups (frame solver) or windows, localizations, speed."""
        method = self.metadata.get("params", {}).get("method", "frame")
        units = "group" if method == "frame" else "window"
        return (
            f"{_count(self.n_frames, 'frame')}, {_count(self.n_windows, units)}, {len(self.table)} "
            f"localizations in {self.seconds:.1f} s ({self.per_second:.1f} localizations/s)"
        )


def _count(n: int, noun: str) -> str:
    """``"1 frame"``, ``"2 frames"``."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


class _Solver:
    """Dictionaries built once; solves one window (window coordinates, origin 0)."""

    def __init__(self, model: PSFModel, params: LocalizeParams) -> None:
        self.model = model
        self.p = params
        zr = params.z_range or model.z_range
        w, px = params.window, params.pixel_size
        self.coarse = Dictionary(model, w, px, *params.coarse, zr)
        self.fine = Dictionary(model, w, px, *params.fine, zr) if params.method != "co" else None

    def __call__(self, y: NDArray, read_variance: NDArray | None = None) -> WindowSolution:
        """Solve window ``y``; ``read_variance``: the window's crop of a read-variance map."""
        p = self.p
        if p.method == "hybrid":
            return hybrid_solve(
                y,
                self.coarse,
                self.fine,
                refine=p.refine,
                noise=p.noise,
                noise_factor=_variance_factor(p),
                max_emitters=p.max_emitters,
                **_noise_kwargs(p, read_variance),
            )
        if p.method == "mp":
            sol = matching_pursuit(
                y,
                self.fine,
                orthogonal=True,
                max_emitters=p.max_emitters,
                replace_sweeps=2,
                noise_factor=_variance_factor(p),
            )
        else:
            sol = convex_solve(y, self.coarse)
        if p.refine and len(sol.emitters):
            sol = refine_solution(
                y,
                sol,
                self.model,
                pixel_size=p.pixel_size,
                noise=p.noise,
                max_emitters=p.max_emitters,
                **_noise_kwargs(p, read_variance),
            )
        return sol


def _noise_kwargs(p: LocalizeParams, read_variance: Any = None) -> dict:
    """The noise keywords of the maximum-likelihood stage beside ``noise``: ``qe`` and, for
    sCMOS (or an EMCCD's read noise), ``read_variance`` (a map) or else ``p.read_variance``."""
    kw: dict[str, Any] = {"qe": p.qe}
    if p.noise == "scmos" or (p.noise == "emccd" and p.read_variance > 0):
        kw["read_variance"] = p.read_variance if read_variance is None else read_variance
    return kw


def _background_noise(p: LocalizeParams, read_variance: Any = None) -> dict:
    """The camera's noise as the background estimates and the detections take it: the
    excess factor and the read variance (a map, else the run's)."""
    return dict(
        noise_factor=_variance_factor(p),
        read_variance=_noise_kwargs(p, read_variance).get("read_variance", 0.0),
    )


def _residual_spatial_background(
    frame: NDArray,
    emitters: NDArray,
    model: PSFModel,
    pixel_size: float,
    reach: float,
    noise: dict,
    halo: NDArray | None = None,
    censored: tuple[NDArray, NDArray] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The spatial background of ``frame`` less the light of ``emitters`` (K, 4; nm, photons;
    finite) within ``reach`` (nm) of each, as the frame solver's windows count it (a model's
    far halo stays in the background), and that light; both (rows, cols), photons per
    pixel. Where part of the far halo is known (``halo``, photons/pixel: the light of
    bright emitters' models beyond their spline table), it is taken away too, and the
    emitters' light is the table's whole (the halo begins where the table ends).
    ``censored``: the pixels at the camera's saturation and the background known before;
    a clipped pixel less its fitted light would read far below the background and pull its
    block's percentile down, so there the estimate reads that background, without the
    light's shot noise in its noise correction."""
    f = np.asarray(frame, dtype=np.float64)
    em = np.asarray(emitters, dtype=np.float64).reshape(-1, 4)
    rows, cols = f.shape
    if halo is not None and isinstance(model, SplinePSF):
        reach = max(model.zero_beyond(pixel_size))
    pieces = light_pieces(model, em, f.shape, pixel_size, (0.0, 0.0), reach)
    light = sum_pieces(pieces, (0, rows, 0, cols))
    known = light if halo is None else light + halo
    if censored is not None:
        mask, prior = censored
        f, known = np.where(mask, prior, f), np.where(mask, 0.0, known)
    return _spatial_background_without(f, known, noise), light


def _halo_gate(work: PSFModel, templates, p: LocalizeParams) -> tuple[Halo, float] | None:
    """The halo of the model the spline table ``work`` was made from beyond that table
    (:class:`~sparseloc.solvers.halo.Halo`) against the two tiers' detection planes, and
    that detection's threshold; None for a table made from data (a bead calibration) or a
    model the solver renders itself."""
    source = getattr(work, "source", None)
    if source is None:
        return None
    planes = detection_planes(templates)
    zr = p.z_range or work.z_range
    halo = Halo.measure(source, work, p.pixel_size, planes, zr)
    return halo, _detection_threshold(templates, planes, p)


def _detection_threshold(templates, planes: NDArray, p: LocalizeParams) -> float:
    """The two tiers' detection threshold (standard deviations) of a run with ``planes``."""
    return p.min_snr * detection_match(templates, planes)


def _noise_variance(background: ArrayLike, noise: dict) -> NDArray[np.float64]:
    """The noise variance (photons^2) per pixel over ``background`` (photons/pixel) with the
    camera's ``noise`` (:func:`_background_noise`), as the detection takes it."""
    bg = np.asarray(background, dtype=np.float64)
    return noise["noise_factor"] * np.maximum(bg, 1e-3) + noise["read_variance"]


def _halo_light(
    gate: tuple[Halo, float] | None,
    work: PSFModel,
    emitters: NDArray,
    background: NDArray,
    noise: dict,
    p: LocalizeParams,
    counted: int | None = None,
) -> NDArray | None:
    """The halos (photons/pixel) of the emitters (K, 4) that the detection could see over
    ``background`` with the camera's ``noise`` (:func:`_background_noise`): the light of the
    model the spline table ``work`` was made from beyond the table's
    (:func:`~sparseloc.solvers.halo.halo_of`; the table's light counted within ``counted``
    px of each emitter's pixel where given), or None."""
    if gate is None:
        return None
    halo, threshold = gate
    variance = np.broadcast_to(_noise_variance(background, noise), np.shape(background))
    return halo_of(halo, work.source, work, emitters, variance, p.pixel_size, threshold, counted)


def _spatial_background_without(frame: NDArray, light: NDArray, noise: dict) -> NDArray:
    """The spatial background (:func:`~sparseloc.detect.spatial_background`) of ``frame``
    less ``light`` (photons/pixel). What is left keeps the shot noise of the light taken
    away: the percentile's noise correction counts it with the read variance of ``noise``
    (:func:`_background_noise`), in the same units (photons, without ``qe``)."""
    kw = dict(noise)
    kw["read_variance"] = kw["read_variance"] + kw["noise_factor"] * light
    return spatial_background(np.asarray(frame, dtype=np.float64) - light, **kw)


def _reach(templates) -> float:
    """How far (nm) an emitter's light counts in the frame solver's windows: half a
    template's width; beyond it the light lies in the background estimate."""
    return 0.5 * templates.images.shape[-1] * templates.pixel_size


def _temporal(p: LocalizeParams, n_frames: int) -> bool:
    """Whether a run over a movie of ``n_frames`` frames takes each frame's background over
    time (else from the frame's own pixels, :func:`~sparseloc.detect.spatial_background`)."""
    return p.background == "temporal" or (
        p.background == "auto" and n_frames >= p.min_temporal_frames
    )


def _variance_factor(p: LocalizeParams) -> float:
    """Shot-noise variance per expected photon in the detection's signal-to-noise: 2 for EMCCD
    data, else 1. The detection thresholds were set on this scale, so ``qe`` stays out."""
    return noise_factor_of(p.noise)


#: Emitters closer than this many half-light radii of a typical plane are fitted as one group:
#: 2, their half-light discs intersect, so emitters whose images trade light are fitted
#: jointly rather than each with the other's light held fixed (a double helix's false emitters
#: on the lobes of missed ones survive the latter; docs/benchmarks/group_span.txt).
GROUP_SPAN = 2.0

#: Largest pad (pixels) of a group's window around its emitters in the frame solver. The pad is
#: the radius holding 90 % of the PSF's light (5 px for storm-analysis's calibrated double
#: helix, 20 px for the pupil double helix's halo); the cap bounds the cost.
PAD_CAP = 12.0


def run_templates(model: PSFModel, params: LocalizeParams):
    """The frame solver's templates for a run: the pursuit's dictionary over the run's z range
    at its coarse steps (:func:`~sparseloc.solvers.frame_mp.frame_templates`)."""
    zr = params.z_range or model.z_range
    return frame_templates(
        model, params.pixel_size, dxy=params.coarse[0], dz=params.coarse[1], z_range=zr
    )


def addition_bar(params: LocalizeParams) -> float:
    """The count selection's bar on the likelihood ratio of one emitter more, for a run: the
    frame solver's (:func:`~sparseloc.solvers.frame.add_threshold`) or the windowed methods'
    (:data:`~sparseloc.solvers.refine.LR_THRESHOLD`); without the model error's allowance,
    which each window adds to it."""
    if params.method == "frame":
        return add_threshold(None, params.qe)
    return float(LR_THRESHOLD)


class _FrameSolver:
    """Templates and FFTs built once per frame shape; solves one whole frame."""

    def __init__(
        self,
        model: PSFModel,
        params: LocalizeParams,
        shape: tuple[int, int],
        read_variance: NDArray | None = None,
        spatial: bool = False,
    ) -> None:
        self.model = model
        self.p = params
        self.noise_kw = _noise_kwargs(params, read_variance)
        # the frames' backgrounds come from their own pixels: estimated again without the
        # fitted emitters' light (see residual_background)
        self.spatial = spatial
        self.background_noise = _background_noise(params, read_variance)
        self.templates = run_templates(model, params)
        self.correlators: dict = {}  # per frame (or tile) shape, see tiled_pursuit
        # Groups: emitters whose half-light discs (of a typical plane) intersect are fitted
        # together: their images overlap enough to trade light.
        self.group_distance = GROUP_SPAN * self.templates.typical_radius * params.pixel_size
        self.pad = int(np.ceil(min(self.templates.radius90, PAD_CAP)))
        self.reach = _reach(self.templates)
        self.detection_cache: dict = {}
        self.l1 = l1_templates(model, self.templates) if params.second_start else None
        planes = np.unique(self.l1.z) if self.l1 is not None else np.zeros(1)
        self.l1_spacing = float(np.min(np.diff(planes))) if planes.size > 1 else 0.0
        self._halo: tuple[Halo, float] | None = None
        self._halo_measured = False  # when first needed

    def halo(self, fit: FrameFit, background: NDArray) -> NDArray | None:
        """The light of ``fit``'s emitters beyond what the solver renders of them (the spline
        table's), where the detection could see it (:func:`_halo_light`), or None."""
        if not self._halo_measured:
            self._halo = _halo_gate(self.model, self.templates, self.p)
            self._halo_measured = True
        em = fit.emitters.as_array().reshape(-1, 4)
        return _halo_light(self._halo, self.model, em, background, self.background_noise, self.p)

    def start(self, frame: NDArray, background: NDArray, read_variance: Any = None):
        """The pursuit's emitters of one frame or crop (the fits' starting point); the read
        variance is the run's unless given (the crop's)."""
        p = self.p
        rv = self.noise_kw.get("read_variance", 0.0) if read_variance is None else read_variance
        return tiled_pursuit(
            frame,
            background,
            self.templates,
            min_snr=p.min_snr,
            noise_factor=_variance_factor(p),
            read_variance=rv,
            correlators=self.correlators,
        )

    def background_shape(self, background: NDArray) -> NDArray | None:
        """The shape the fits give a frame's (or crop's) background ``background``
        (:func:`~sparseloc.solvers.frame_windows.background_shape`) where the run says the
        sample has a haze (``haze``), else None (a constant)."""
        if not self.p.haze:
            return None
        return background_shape(
            np.asarray(background, dtype=np.float64), self.templates.core_radius
        )

    def fit_kwargs(
        self,
        read_variance: Any = None,
        shape: NDArray | None = None,
        censored: NDArray | None = None,
    ) -> dict:
        """Keywords of :func:`frame_fit` but the frame's own; the read variance is the run's
        unless given (a crop's); ``shape``: the background's (:meth:`background_shape`);
        ``censored``: the frame's (or crop's) pixels at the camera's saturation."""
        p = self.p
        kw = dict(
            pixel_size=p.pixel_size,
            group_distance=self.group_distance,
            pad=self.pad,
            reach=self.reach,
            count_selection=p.refine,
            max_emitters=p.max_emitters,
            noise=p.noise,
            relocate=int(p.relocate),
            **self.noise_kw,
        )
        if read_variance is not None and "read_variance" in kw:
            kw["read_variance"] = read_variance
        if shape is not None:
            kw["background_shape"] = shape
        if censored is not None:
            kw["censored"] = censored
        return kw

    def __call__(
        self,
        frame: NDArray,
        background: NDArray,
        start: NDArray | None = None,
        censored: NDArray | None = None,
    ) -> FrameFit:
        """Solve one frame: by the run's schedule (:meth:`solve`), or the fits from ``start``
        (K, 4) if given. Where bright emitters' halos (:meth:`halo`) could be detected, the
        frame is solved again with them known (a spatial background estimated again from the
        frame less them). Where the background is the frame's own spatial
        estimate, then :meth:`residual_background` (without its search where ``start`` is
        given). ``censored`` (rows, cols; bool): pixels at the camera's saturation, left out
        of every fit's likelihood, or None."""
        if censored is not None and not np.any(censored):
            censored = None
        fit = self.solved(frame, background, start, censored=censored)
        halo = self.halo(fit, background)
        if halo is not None:
            if self.spatial:
                background = _spatial_background_without(frame, halo, self.background_noise)
            fit = self.solved(frame, background, start, halo, censored)
        if not self.spatial:
            return fit
        cens = None if censored is None else (censored, background)
        return self.residual_background(frame, fit, search=start is None, halo=halo, censored=cens)

    def solved(
        self,
        frame: NDArray,
        background: NDArray,
        start: NDArray | None,
        fixed_light: NDArray | None = None,
        censored: NDArray | None = None,
    ) -> FrameFit:
        """The frame's fit by the run's schedule, or from ``start`` (K, 4) if given, with the
        light ``fixed_light`` (photons/pixel) known and the pixels ``censored`` left out."""
        shape = self.background_shape(background)
        if start is None:
            return self.solve(frame, background, shape, fixed_light, censored)
        emitters = Emitters.from_array(np.asarray(start, dtype=np.float64).reshape(-1, 4))
        kw = self.fit_kwargs(shape=shape, censored=censored)
        return frame_fit(
            frame, self.model, emitters, background=background, fixed_light=fixed_light, **kw
        )

    def residual_background(
        self,
        frame: NDArray,
        fit: FrameFit,
        search: bool = True,
        halo: NDArray | None = None,
        censored: tuple[NDArray, NDArray] | None = None,
    ) -> FrameFit:
        """``fit`` refitted with the frame's spatial background estimated again from the frame
        less ``fit``'s light, from its emitters and those the pursuit finds in what that
        background and that light leave; ``halo`` (photons/pixel), bright emitters' light
        beyond their spline table, is left out of the estimate and known in the fits.

        The spatial estimate takes each block's darker pixels for the background. Where
        emitters' images cover most of a block (a crowded frame, a broad PSF) those pixels
        hold their light too, the estimate lies above the background, and a dim or broad
        emitter's image sinks below the detection's threshold. Without the fitted light the
        same estimator sees the background (``docs/benchmarks/residual_background.txt``).
        The refit replaces ``fit`` without a likelihood comparison: the two are fits over
        different backgrounds. ``search``: False refits ``fit``'s emitters alone;
        ``censored``: the frame's pixels at the camera's saturation (left out of the fits)
        and the background the frame was solved over (see
        :func:`_residual_spatial_background`).
        """
        arr = fit.emitters.as_array().reshape(-1, 4)
        arr = arr[np.all(np.isfinite(arr), axis=1)]
        if not len(arr):
            return fit
        f = np.asarray(frame, dtype=np.float64)
        background, light = _residual_spatial_background(
            f, arr, self.model, self.p.pixel_size, self.reach, self.background_noise, halo,
            censored,
        )  # fmt: skip
        seen = background + light if halo is None else background + light + halo
        if search:
            arr = np.vstack([arr, self.start(f, seen).as_array().reshape(-1, 4)])
        emitters = Emitters.from_array(arr)
        mask = None if censored is None else censored[0]
        kw = self.fit_kwargs(shape=self.background_shape(background), censored=mask)
        return frame_fit(f, self.model, emitters, background=background, fixed_light=halo, **kw)

    def solve(
        self,
        frame: NDArray,
        background: NDArray,
        shape: NDArray | None,
        fixed_light: NDArray | None = None,
        censored: NDArray | None = None,
    ) -> FrameFit:
        """The frame's fit by the run's schedule (``shape``: :meth:`background_shape`), with
        the light ``fixed_light`` (photons/pixel) known and the pixels ``censored`` left
        out."""
        if self.p.frame_schedule in ("two-tier", "auto"):
            fit = solve_two_tier(
                frame,
                background,
                self.model,
                self.templates,
                pursuit=self.start,
                fit_options=self.fit_kwargs(shape=shape, censored=censored),
                min_snr=self.p.min_snr,
                **self.background_noise,
                cache=self.detection_cache,
                whole_when_crowded=self.p.frame_schedule == "auto",
                whole=self.whole if self.p.frame_schedule == "auto" else None,
                fixed_light=fixed_light,
            )
            if fit is not None:
                return fit
        return self.whole(frame, background, fixed_light, shape=shape, censored=censored)

    def whole(
        self,
        frame: NDArray,
        background: NDArray,
        fixed_light: NDArray | None = None,
        read_variance: Any = None,
        shape: NDArray | None = None,
        censored: NDArray | None = None,
    ) -> FrameFit:
        """The whole-frame solver on ``frame`` (or a crop of the frame, with its read
        variance, background shape and censored pixels): the pursuit, the fits, the second
        start and the regrown groups, with the light ``fixed_light`` (photons/pixel, the
        image's shape) known."""
        seen = background if fixed_light is None else background + fixed_light
        start = self.start(frame, seen, read_variance)
        kw = self.fit_kwargs(read_variance, shape, censored)
        fit = frame_fit(
            frame, self.model, start, background=background, fixed_light=fixed_light, **kw
        )
        if self.l1 is not None:
            fit = self.second(frame, background, fit, fixed_light, kw)
        if self.p.regrow and self.p.refine:  # its growth is the count selection's
            fit = self.regrown(frame, background, fit, fixed_light, kw)
        return fit

    def second(
        self,
        frame: NDArray,
        background: NDArray,
        first: FrameFit,
        fixed_light: NDArray | None = None,
        kw: dict | None = None,
    ) -> FrameFit:
        """``first`` with each region where a fit from the L1 deconvolution's peaks places
        the emitters otherwise, and is likelier, replaced by that fit. Only the parts of the
        frame where ``first`` has groups of two or more are solved again (with a template's
        reach around them, the light of ``first``'s other emitters and ``fixed_light``
        known). ``kw``: :meth:`fit_kwargs` of the frame (or crop), the run's by default."""
        p = self.p
        px = p.pixel_size
        margin = self.templates.images.shape[-1] // 2
        boxes = crowded_boxes(first, np.shape(frame), px, margin)
        if not boxes:
            return first
        arr = first.emitters.as_array().reshape(-1, 4)
        redone = np.zeros(len(arr), bool)
        second = None
        kw = self.fit_kwargs() if kw is None else kw
        for box in boxes:
            mine = inside(arr, box, px)
            part = self.crop_fit(frame, background, box, arr[~mine], arr[mine], fixed_light, kw)
            if part is not None:
                redone |= mine
                second = part if second is None else joined(second, part)
        if second is None:
            return first
        second = joined(subset(first, ~redone), second)
        bg = np.broadcast_to(background, np.shape(frame))
        return likelier_per_region(
            frame, bg, first, second, self.model, **self.region_kwargs(kw, fixed_light)
        )

    def region_kwargs(self, kw: dict, fixed_light: NDArray | None) -> dict:
        """The keywords :func:`~sparseloc.solvers.frame_compose.likelier_per_region` and
        :func:`~sparseloc.solvers.frame_grow.grown_groups` share; ``kw``: :meth:`fit_kwargs`
        of the frame (or crop)."""
        keys = ("noise", "qe", *PIXEL_MAPS)
        return dict(
            pixel_size=self.p.pixel_size,
            group_distance=self.group_distance,
            pad=self.pad,
            penalty=addition_bar(self.p),
            fit_kwargs={k: v for k, v in kw.items() if k in keys},
            fixed_light=fixed_light,
        )

    def regrown(
        self,
        frame: NDArray,
        background: NDArray,
        fit: FrameFit,
        fixed_light: NDArray | None,
        kw: dict,
    ) -> FrameFit:
        """``fit`` with each region where its groups grown again from one emitter
        (:func:`~sparseloc.solvers.frame_grow.grown_groups`) are likelier replaced by them.
        ``kw``: :meth:`fit_kwargs` of the frame (or crop)."""
        common = self.region_kwargs(kw, fixed_light)
        bg = np.broadcast_to(background, np.shape(frame))
        grown = grown_groups(
            frame,
            bg,
            fit,
            self.model,
            reach=self.reach,
            max_emitters=self.p.max_emitters,
            **common,
        )
        if grown is None:
            return fit
        return likelier_per_region(frame, bg, fit, grown, self.model, **common)

    def crop_fit(
        self,
        frame: NDArray,
        background: NDArray,
        box: tuple,
        others: NDArray,
        mine: NDArray,
        fixed_light: NDArray | None,
        kw: dict,
    ) -> FrameFit | None:
        """The frame fit of the pixels ``box`` from the L1 deconvolution's peaks, with the
        light of ``others`` (K, 4) and ``fixed_light`` known; emitters in frame coordinates.
        None where the peaks are the first fit's emitters ``mine`` (one each, within a pixel
        laterally and one of the deconvolution's plane spacings axially): the fit from them
        would find the same. ``kw``: :meth:`fit_kwargs` of the frame."""
        p, px = self.p, self.p.pixel_size
        r0, r1, c0, c1 = box
        crop = np.asarray(frame)[r0:r1, c0:c1]
        bg = np.broadcast_to(background, np.shape(frame))[r0:r1, c0:c1]
        origin = (c0 * px, r0 * px)
        light = (
            self.model.render(*others.T, crop.shape, px, origin=origin)
            if len(others)
            else np.zeros(crop.shape)
        )
        if fixed_light is not None:
            light = light + fixed_light[r0:r1, c0:c1]
        kw = cropped_maps(kw, np.shape(frame), box)
        starts = tiled_l1_starts(
            crop - light,
            bg,
            self.l1,
            peak_radius=self.templates.typical_radius,
            min_snr=p.min_snr,
            noise_factor=_variance_factor(p),
            read_variance=kw.get("read_variance", 0.0),
        )
        shifted_starts = starts.as_array().reshape(-1, 4) + np.array([*origin, 0.0, 0.0])
        if len(shifted_starts) == len(mine) and np.all(
            same_as(shifted_starts, mine, px, self.l1_spacing)
        ):
            return None
        fit = frame_fit(crop, self.model, starts, background=bg, fixed_light=light, **kw)
        return shifted(fit, *origin)


def _frame_rows(fit: FrameFit, frame: int, id0: int) -> dict:
    e = fit.emitters
    k = len(e)
    return {
        "frame": np.full(k, frame, dtype=np.int64),
        "x_nm": e.x,
        "y_nm": e.y,
        "z_nm": e.z,
        "photons": e.photons,
        "background": fit.background,
        "sigma_x_nm": fit.sigma[:, 0],
        "sigma_y_nm": fit.sigma[:, 1],
        "sigma_z_nm": fit.sigma[:, 2],
        "sigma_photons": fit.sigma[:, 3],
        "gof": fit.gof,
        "flag": fit.flags.astype(object),
        "window_id": id0 + fit.group,
    }


def _rows(sol: WindowSolution, tile: Tile, frame: int, window_id: int, px: float) -> dict:
    e = sol.emitters
    k = len(e)
    x = e.x + tile.col0 * px
    y = e.y + tile.row0 * px
    keep = tile.owns(x, y, px)
    sig = sol.sigma if sol.sigma is not None else np.full((k, 4), np.nan)
    flags = sol.flags if sol.flags is not None else np.full(k, "ok")
    return {
        "frame": np.full(k, frame, dtype=np.int64)[keep],
        "x_nm": x[keep],
        "y_nm": y[keep],
        "z_nm": e.z[keep],
        "photons": e.photons[keep],
        "background": np.full(k, sol.background)[keep],
        "sigma_x_nm": sig[keep, 0],
        "sigma_y_nm": sig[keep, 1],
        "sigma_z_nm": sig[keep, 2],
        "sigma_photons": sig[keep, 3],
        "gof": np.full(k, np.nan if sol.gof is None else sol.gof)[keep],
        "flag": np.asarray(flags, dtype=object)[keep],
        "window_id": np.full(k, window_id, dtype=np.int64)[keep],
    }


def localize(
    frames: Any,
    model: PSFModel,
    params: LocalizeParams,
    *,
    start: int = 0,
    stop: int | None = None,
    block: int = 64,
    progress: Callable[[int], None] | None = None,
    workers: int = 1,
    read_variance: NDArray | None = None,
    check: bool = True,
    starts: pd.DataFrame | None = None,
) -> LocalizeResult:
    """Localize every frame of a movie (photons) and return the localization table.

    After the run the table's goodness of fit is checked (:func:`check_model`): the verdict
    goes to ``metadata["model_check"]``, and a warning with the likely causes is logged when
    the model or the noise model does not describe the data.

    Parameters
    ----------
    frames : Movie or ndarray, shape (n, rows, cols)
        Frames in photons (offset and gain removed), read ``block`` frames at a time (plus the
        background block around them).
    model : PSFModel
        PSF model.
    params : LocalizeParams
        Analysis parameters.
    start, stop : int
        Frame range (0-based, stop exclusive).
    block : int
        Frames read at once.
    progress : callable, optional
        Called with the number of frames just finished.
    workers : int
        Processes solving frames (1: this process). Frames are independent, so the table is
        the same whatever the number; the reading and the background stay here.
    read_variance : ndarray, shape (rows, cols), optional
        Per-pixel read-noise variance (photons^2) of an sCMOS camera, for ``noise="scmos"``
        (every solver: the windowed ones crop it to each window); replaces
        ``params.read_variance``.
    check : bool
        Run the model check (a chunk of a longer run leaves it to the whole run).
    starts : DataFrame, optional
        Emitters to start the frame solver from in place of its pursuit: columns ``frame``
        (0-based), ``x_nm``, ``y_nm``, ``z_nm`` and optionally ``photons`` (default
        :data:`START_PHOTONS`). Everything after the start (fits, count selection,
        relocation, the refit over a spatial background estimated again) is the same but the
        searches for more emitters; started from the true emitters, the result is the
        ceiling of what the fits can keep.

    Returns
    -------
    LocalizeResult
    """
    _check_pixel_size(model, params)
    n = len(frames)
    stop = n if stop is None else min(stop, n)
    if not 0 <= start < stop:
        raise ValueError(
            f"frame range {start}:{stop} (--frames) is empty (the movie has {n} frames)"
        )
    get = _getter(frames)
    shape = np.asarray(get(start, start + 1), dtype=np.float64).shape[-2:]
    # The frame solver needs no tiles but frames of at least one window all the same.
    tiles(shape, params.window, params.margin)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if read_variance is not None:
        read_variance = _checked_read_variance(read_variance, shape, params)
    t0 = time.perf_counter()
    inputs = _frames_and_backgrounds(get, n, start, stop, block, params, model, read_variance)
    if starts is not None:
        inputs = _with_starts(inputs, starts, params)
    work_args = (
        work_model_for(model, params),
        params,
        shape,
        read_variance,
        not _temporal(params, n),
    )
    parts: list[dict] = []
    early = _EarlyCheck(work_args[0], params, shape) if check and stop - start > 1 else None
    n_windows = _collect(
        _solve(inputs, work_args, workers), parts, params.method == "frame", progress, early
    )
    seconds = time.perf_counter() - t0
    meta = run_metadata(model, params, (start, stop), shape, read_variance)
    table = _table(parts)
    if check:
        meta.update(run_checks(table, model, work_args[0], params, shape, read_variance))
    return LocalizeResult(table, stop - start, n_windows, seconds, meta)


def run_checks(
    table: pd.DataFrame,
    model: PSFModel,
    work: PSFModel,
    params: LocalizeParams,
    shape: tuple[int, int],
    read_variance: NDArray | None = None,
) -> dict:
    """The run summary's checks of a finished table, as metadata entries: the model check
    (:func:`check_model`), the localizations too bright for a bead calibration's ROI
    (:func:`beyond_roi`) and those stopped at the ends of the z range (:func:`at_z_ends`;
    the fits' bound is ``work``'s range, the run's model ``model``'s may be wider), the last
    two only where they occur."""
    out = {"model_check": check_model(table, work, params, shape).to_dict()}
    bright = beyond_roi(table, work, params, read_variance)
    if bright:
        out["beyond_roi"] = bright
    ends = at_z_ends(table, work.z_range, model.z_range)
    if ends:
        out["at_z_ends"] = ends
    return out


#: The share of a table's localizations flagged "z_edge" from which the run summary notes
#: them: emitters within the range leave 0-4 % there (docs/benchmarks/z_ends.txt), a sample
#: deeper than the calibrated range some tens of per cent.
Z_ENDS_NOTE = 0.05


def at_z_ends(
    table: pd.DataFrame, z_range: tuple[float, float], model_range: tuple[float, float]
) -> dict | None:
    """Where at least :data:`Z_ENDS_NOTE` of the localizations are flagged "z_edge" (their
    fits stopped at an end of the fits' z range ``z_range`` (nm): emitters beyond it, whose
    z is not known), a dict with their ``count``, ``fraction``, the range (``z_min_nm``,
    ``z_max_nm``) and the model's own (``model_z_min_nm``, ``model_z_max_nm``: wider where
    the run narrowed it); else None."""
    if not len(table) or "flag" not in table:
        return None
    n = int((table["flag"] == "z_edge").sum())
    if n < Z_ENDS_NOTE * len(table):
        return None
    (lo, hi), (mlo, mhi) = ((float(a), float(b)) for a, b in (z_range, model_range))
    return {
        "count": n,
        "fraction": n / len(table),
        "z_min_nm": lo,
        "z_max_nm": hi,
        "model_z_min_nm": mlo,
        "model_z_max_nm": mhi,
    }


def beyond_roi(
    table: pd.DataFrame,
    work: PSFModel,
    params: LocalizeParams,
    read_variance: NDArray | None = None,
) -> dict | None:
    """Where the run's model is a table made from data (a bead calibration, which ends at
    its ROI: no halo is rendered beyond it), the localizations bright enough that their
    light just beyond the ROI would reach the detection's threshold
    (:meth:`~sparseloc.solvers.halo.Halo.at_roi_edge`, at each one's fitted background): a
    dict with their ``count`` and the ROI's half-width ``roi_half_nm``, or None."""
    if params.method != "frame" or not isinstance(work, SplinePSF) or not len(table):
        return None
    if getattr(work, "source", None) is not None:
        return None  # a table of a model: the solver renders its halo
    templates = run_templates(work, params)
    planes = detection_planes(templates)
    zr = params.z_range or work.z_range
    edge = Halo.at_roi_edge(work, params.pixel_size, planes, zr)
    noise = _background_noise(params, read_variance)
    noise["read_variance"] = float(np.median(noise["read_variance"]))
    bg = table["background"].to_numpy() if "background" in table else np.zeros(len(table))
    sigma = np.sqrt(_noise_variance(np.nan_to_num(bg), noise))
    z, photons = table["z_nm"].to_numpy(), table["photons"].to_numpy()
    ok = np.isfinite(z) & np.isfinite(photons)
    threshold = _detection_threshold(templates, planes, params)
    n = int(np.sum(edge.detectable(z[ok], photons[ok], sigma[ok], threshold)))
    return {"count": n, "roi_half_nm": work.roi_half(params.pixel_size)} if n else None


def _getter(frames: Any) -> Callable[[int, int], Any]:
    """``get(a, b)``: frames ``a`` to ``b - 1`` of a movie (its ``frames`` method) or array."""
    return frames.frames if hasattr(frames, "frames") else (lambda a, b: np.asarray(frames[a:b]))


def check_frame(
    frames: Any,
    index: int,
    table: pd.DataFrame,
    model: PSFModel,
    params: LocalizeParams,
    read_variance: NDArray | None = None,
) -> FrameResidual:
    """The frame check (:mod:`sparseloc.frame_residual`) of one frame of a run: what its
    localizations leave unexplained, and the support of each.

    Parameters
    ----------
    frames, model, params, read_variance
        As given to :func:`localize` for the run that made ``table``.
    index : int
        The frame (0-based).
    table : pandas.DataFrame
        The run's localizations (``frame``, ``x_nm``, ``y_nm``, ``z_nm``, ``photons`` and,
        where present, each window's fitted ``background``); rows with a non-finite position
        or photon count are left out.

    Returns
    -------
    FrameResidual
        Of that frame in photons over the run's background estimate of it (the rule of
        :func:`localize`; a spatial one estimated again without the localizations' light,
        as the frame solver does) and bright localizations' halos (as the frame solver knows
        them), the localizations rendered with the model the fits used, the
        unexplained light found with the run's detection planes
        (:func:`~sparseloc.solvers.two_tier.detection_planes`). Compare its support and
        signal-to-noise with :func:`addition_bar`.
    """
    n = len(frames)
    if not 0 <= index < n:
        raise ValueError(f"frame {index} is outside the movie, whose frames are 0 to {n - 1}")
    get = _getter(frames)
    shape = np.asarray(get(index, index + 1), dtype=np.float64).shape[-2:]
    if read_variance is not None:
        read_variance = _checked_read_variance(read_variance, shape, params)
    _, frame, bg = next(
        _frames_and_backgrounds(get, n, index, index + 1, 1, params, model, read_variance)
    )
    cols = ["x_nm", "y_nm", "z_nm", "photons"]
    missing = [c for c in ("frame", *cols) if c not in table]
    if missing:
        raise ValueError(f"the table has no {', '.join(missing)} column: the check needs them")
    rows = table[np.asarray(table["frame"]) == index]
    rows = rows[np.all(np.isfinite(rows[cols].to_numpy(dtype=np.float64)), axis=1)]
    fitted = rows["background"].to_numpy() if "background" in rows else None
    work = work_model_for(model, params)
    templates = run_templates(work, params)
    noise = _background_noise(params, read_variance)
    em = rows[cols].to_numpy()
    halo = counted = None
    if params.method == "frame":
        gate = _halo_gate(work, templates, params)
        halo = _halo_light(gate, work, em, bg, noise, params)
        # frame_residual counts each localization's light within a template's box
        box = templates.images.shape[-1] // 2
        counted = _halo_light(gate, work, em, bg, noise, params, box)
    if params.method == "frame" and not _temporal(params, n) and len(rows):
        cens = censored_pixels(frame, params.saturation)
        bg, _ = _residual_spatial_background(
            frame, em, work, params.pixel_size, _reach(templates), noise, halo,
            None if cens is None else (cens, bg),
        )  # fmt: skip
    return frame_residual(
        frame,
        bg,
        work,
        rows[cols].to_numpy(),
        params.pixel_size,
        noise=params.noise,
        qe=params.qe,
        read_variance=noise["read_variance"],
        min_snr=params.min_snr,
        window_background=fitted,
        known_light=counted,
        templates=detection_planes(templates),
    )


def check_model(
    table: pd.DataFrame,
    work_model: PSFModel,
    params: LocalizeParams,
    shape: tuple[int, int],
    *,
    warn: bool = True,
) -> ModelCheck:
    """The model check of a run (:func:`sparseloc.model_check.check_fit`) on its table.

    One ``gof`` per fitted window (its localizations share it), with the window's degrees of
    freedom: its pixels, as the solver cut it (:func:`window_box` of its localizations and the
    frame solver's pad, or the window of the window methods), less four parameters per
    localization and one for the background.

    Parameters
    ----------
    table : DataFrame
        A localization table of this run.
    work_model : PSFModel
        The model the solvers rendered (:func:`work_model_for`).
    params : LocalizeParams
        The run's parameters.
    shape : (int, int)
        Frame shape (rows, cols).
    warn : bool
        Log the verdict's message as a warning when the check fails.

    Returns
    -------
    ModelCheck
    """
    from .solvers.frame_windows import window_boxes

    wins = table.groupby(["frame", "window_id"], sort=False).agg(
        gof=("gof", "first"),
        k=("gof", "size"),
        x0=("x_nm", "min"),
        x1=("x_nm", "max"),
        y0=("y_nm", "min"),
        y1=("y_nm", "max"),
        background=("background", "median"),
    )
    px = params.pixel_size
    if params.method == "frame" and len(wins):
        pad = _FrameSolver(work_model, params, shape).pad
        x0, x1, y0, y1 = (wins[c].to_numpy() for c in ("x0", "x1", "y0", "y1"))
        r0, r1, c0, c1 = window_boxes(x0, x1, y0, y1, shape[0], shape[1], px, pad)
        pixels = (r1 - r0) * (c1 - c0)
    else:
        pixels = np.full(len(wins), float(params.window) ** 2)
    dof = pixels - (4 * wins["k"].to_numpy() + 1)
    area_um2 = shape[0] * shape[1] * (px * 1e-3) ** 2
    density = len(table) / (area_um2 * max(table["frame"].nunique(), 1))
    bg = params.qe * wins["background"].to_numpy()
    # the frame solver's addition threshold bounds what an unresolved emitter adds (the
    # windowed methods' count selection has its own; there crowding is named unbounded)
    ratio = add_threshold(None, params.qe) if params.method == "frame" else None
    allowance = _window_allowances(table, work_model, params, shape)
    res = check_fit(
        wins["gof"], dof, bg, wins["k"], density=density, unresolved_ratio=ratio,
        allowance=allowance,
    )  # fmt: skip
    if warn and not res.ok:
        log.warning("%s", res.message)
    return res


#: Windows whose model-error allowance the model check computes (a random sample of the run's,
#: fixed seed): it needs their median only.
ALLOWANCE_WINDOWS = 200


def _window_allowances(
    table: pd.DataFrame, work_model: PSFModel, params: LocalizeParams, shape: tuple[int, int]
) -> NDArray[np.float64] | None:
    """The model error's expected share of the deviance per degree of freedom (the count
    selection's allowance ``sum(E / V)`` over dof, :mod:`sparseloc.solvers.variance`) of a
    sample of the table's windows (each its localizations with the frame solver's pad);
    None for an exact model."""
    from .solvers.frame_windows import window_box
    from .solvers.mle import likelihood_weight
    from .solvers.variance import error_allowance, model_error_of, model_error_variance

    if getattr(work_model, "error_table", None) is None and model_error_of(work_model) <= 0:
        return None
    keys = table[["frame", "window_id"]].drop_duplicates()
    if not len(keys):
        return None
    # the sample's rows only (a long movie's table holds millions of windows), drawn at random
    # with a fixed seed: the same table gives the same verdict
    sample = keys.sample(n=min(ALLOWANCE_WINDOWS, len(keys)), random_state=0)
    rows = table.merge(sample, on=["frame", "window_id"])
    px = params.pixel_size
    pad = _FrameSolver(work_model, params, shape).pad if params.method == "frame" else 0
    w = likelihood_weight(params.noise, params.qe)
    rv = float(_noise_kwargs(params).get("read_variance", 0.0) or 0.0)
    out = []
    for _, g in rows.groupby(["frame", "window_id"], sort=False):
        em = g[["x_nm", "y_nm", "z_nm", "photons"]].to_numpy(np.float64)
        if params.method == "frame":
            r0, r1, c0, c1 = window_box(em, shape[0], shape[1], px, pad)
        else:
            half = params.window // 2
            r, c = int(em[:, 1].mean() / px), int(em[:, 0].mean() / px)
            r0, r1, c0, c1 = max(r - half, 0), r + half + 1, max(c - half, 0), c + half + 1
        size, origin = (r1 - r0, c1 - c0), (c0 * px, r0 * px)
        lo, hi = work_model.z_range
        z = np.clip(em[:, 2], lo, hi)
        signal = work_model.render(em[:, 0], em[:, 1], z, em[:, 3], size, px, origin=origin)
        mu = signal + float(g["background"].median())
        error_var = model_error_variance(work_model, em, signal, px, origin)
        dof = size[0] * size[1] - (4 * len(em) + 1)
        if error_var is not None and dof >= 1:
            out.append(error_allowance(mu / w + rv, error_var) / dof)
    return np.asarray(out) if out else None


def run_metadata(
    model: PSFModel,
    params: LocalizeParams,
    frames: tuple[int, int],
    shape: tuple[int, ...],
    read_variance: NDArray | None = None,
) -> dict[str, Any]:
    """The analysis metadata stored with a table: parameters, PSF and its hash, version,
    frame range (start, stop), frame shape and the digest of a read-variance map."""
    meta = {
        "params": asdict(params),
        "psf": getattr(model, "name", type(model).__name__),
        "psf_hash": psf_hash(model, params.pixel_size),
        "sparseloc_version": __version__,
        "frames": list(frames),
        "shape": list(shape),
    }
    if read_variance is not None:
        meta["read_variance_map_sha256"] = array_digest(read_variance)
    return meta


def _check_pixel_size(model: PSFModel, params: LocalizeParams) -> None:
    """A calibrated model must be used at the pixel size it was calibrated at."""
    cal_px = getattr(model, "pixel_size", None)
    if cal_px is not None and abs(float(cal_px) - params.pixel_size) > 1e-3 * float(cal_px):
        raise ValueError(
            f"the PSF calibration was made at {float(cal_px):g} nm pixels but the pixel size is "
            f"{params.pixel_size:g} nm; pass the matching --pixel-size or recalibrate"
        )


def _checked_read_variance(read_variance: Any, shape, p: LocalizeParams) -> NDArray:
    """The sCMOS read-variance map (photons^2) as float64, checked against the frames."""
    rv = np.asarray(read_variance, dtype=np.float64)
    if rv.shape != tuple(shape):
        raise ValueError(f"the read-variance map is {rv.shape}, the frames are {tuple(shape)}")
    if p.noise != "scmos":
        raise ValueError(
            "a per-pixel read-variance map (--variance-map) needs the sCMOS likelihood "
            "(noise 'scmos', --camera scmos)"
        )
    if not np.all(np.isfinite(rv)) or np.any(rv < 0):
        raise ValueError("the read-variance map must be finite and >= 0 photons^2")
    return rv


def _solve(inputs, work_args: tuple, workers: int):
    """Each frame's table parts and window count, in frame order: in this process, or in a
    pool of ``workers`` processes, each with its own :class:`_FrameWork` built from
    ``work_args``."""
    engine = work_args[1].engine
    if workers > 1:
        # Compile (or load) the engine's kernels here once: forked workers inherit them,
        # and spawned ones find numba's cache filled instead of all compiling at once.
        resolve_engine(engine)
        yield from in_processes(inputs, workers, (_FrameWork, work_args, engine))
        return
    from threadpoolctl import threadpool_limits

    # One BLAS thread, as in the worker processes: the matrices are small (no gain from
    # threads) and the same arithmetic gives the same table whatever ``workers``.
    with threadpool_limits(limits=1), use_engine(engine):
        work = _FrameWork(*work_args)
        for item in inputs:
            yield work(*item)


#: Photons of a given start without a ``photons`` column (the fits estimate them).
START_PHOTONS = 1000.0


def _with_starts(inputs, starts: pd.DataFrame, p: LocalizeParams):
    """``inputs`` (frame index, frame, background) with each frame's rows of ``starts`` as an
    array (K, 4) of x, y, z (nm) and photons."""
    if p.method != "frame":
        raise ValueError(f"starting emitters need method='frame', not {p.method!r}")
    missing = [c for c in ("frame", "x_nm", "y_nm", "z_nm") if c not in starts.columns]
    if missing:
        raise ValueError(f"the starting emitters have no column {', '.join(missing)}")
    photons = starts["photons"] if "photons" in starts.columns else START_PHOTONS
    arr = np.column_stack(
        [
            starts["x_nm"].to_numpy(float),
            starts["y_nm"].to_numpy(float),
            starts["z_nm"].to_numpy(float),
            np.broadcast_to(np.asarray(photons, dtype=float), len(starts)),
        ]
    )
    if p.z_range is not None:  # the fits stay in the run's range: so do their starts
        arr[:, 2] = np.clip(arr[:, 2], *p.z_range)
    frames = starts["frame"].to_numpy(np.int64)
    return ((f, frame, bg, arr[frames == f]) for f, frame, bg in inputs)


def _table(parts: list[dict]) -> pd.DataFrame:
    """The localization table of the frames' parts (the empty table without any)."""
    if not parts:
        return empty_locs()
    table = pd.DataFrame({c: np.concatenate([pt[c] for pt in parts]) for c in LOCS_COLUMNS})
    table["flag"] = table["flag"].astype(str)
    return table


def work_model_for(model: PSFModel, p: LocalizeParams) -> PSFModel:
    """The model the solvers render: ``model`` itself, or its spline table (``p.tabulate``),
    its valid range narrowed to the run's ``z_range`` where one is given, so that the fits stay
    in it, not only the dictionaries (:meth:`SplinePSF.within`; a model used untabulated
    keeps its own range as the fits' bound).

    Every window renders the model thousands of times; a spline table of it renders ~50x
    faster than a pupil model at the same precision (RMSE / CRLB 0.94-0.99, bias < 1 nm on
    isolated double-helix emitters; see :meth:`SplinePSF.from_model`). The frame solver's
    templates reach 20 px from the emitter (:func:`frame_templates`). Tabulate once and pass
    the result to :func:`localize` to share it between runs (it is not tabulated again).
    """
    if p.tabulate and not isinstance(model, SplinePSF):
        roi = 45 if p.method == "frame" else 2 * p.window + 3
        model = SplinePSF.from_model(model, p.pixel_size, roi=roi, z_step=10.0)
    return model.within(p.z_range) if isinstance(model, SplinePSF) else model


def _collect(results, parts: list[dict], renumber: bool, progress, early=None) -> int:
    """Gather each frame's table parts in order; with ``renumber`` the frame solver's group
    indices become window ids unique over the movie (a running count); ``early`` is called
    with the parts after each frame. Returns the number of windows."""
    n_windows = 0
    for rows, nw in results:
        if renumber:
            for r in rows:
                r["window_id"] = r["window_id"] + n_windows
        parts.extend(rows)
        n_windows += nw
        if progress is not None:
            progress(1)
        if early is not None:
            early(parts)
    return n_windows


class _EarlyCheck:
    """The model check on the first frame that has fits, said at once where it fails: a
    wrong PSF or camera setting shows after a frame, not at the end of an hours-long run.
    The run goes on; the check of the whole run at its end decides."""

    def __init__(self, work_model: PSFModel, params: LocalizeParams, shape: tuple[int, int]):
        self.args = (work_model, params, shape)
        self.frames = 0
        self.done = False

    def __call__(self, parts: list[dict]) -> None:
        self.frames += 1
        if self.done or not parts:
            return
        self.done = True
        res = check_model(_table(parts), *self.args, warn=False)
        if res.verdict in ("misfit", "too_little_noise"):
            log.warning(
                "after %d frame%s: %s; the run goes on (Ctrl-C stops it), and its check at the "
                "end decides",
                self.frames,
                "" if self.frames == 1 else "s",
                res.message,
            )


class _FrameWork:
    """Everything needed to solve one frame, built once (per process)."""

    def __init__(
        self,
        work_model: PSFModel,
        p: LocalizeParams,
        shape: tuple[int, int],
        read_variance: NDArray | None = None,
        spatial: bool = False,
    ) -> None:
        self.p = p
        self.tiling = tiles(shape, p.window, p.margin)
        if p.method == "frame":
            self.solver: Any = _FrameSolver(work_model, p, shape, read_variance, spatial)
        else:
            self.solver = _Solver(work_model, p)
            self.read_variance = read_variance
            zr = p.z_range or work_model.z_range
            tsize = min(2 * p.window + 1, 2 * (min(shape) // 2) - 1)
            self.template = z_averaged_psf(work_model, p.pixel_size, zr, tsize)

    def __call__(
        self, f: int, frame: NDArray, bg: NDArray, start: NDArray | None = None
    ) -> tuple[list[dict], int]:
        """Table parts and the number of windows of frame ``f`` (the frame solver starts from
        ``start`` (K, 4) when one is given)."""
        p = self.p
        if p.method == "frame":
            fit = self.solver(frame, bg, start, censored_pixels(frame, p.saturation))
            # window ids: the group index here; localize() makes them unique over the movie
            rows = _frame_rows(fit, f, 0)
            labels, rows["window_id"] = np.unique(rows["window_id"], return_inverse=True)
            return [rows], len(labels)
        parts = []
        rv = self.read_variance
        cand = detect_candidates(
            frame,
            bg,
            self.template,
            threshold=p.min_snr,
            **_background_noise(p, rv),
        )
        todo = _tiles_to_solve(self.tiling, cand, p.margin)
        for tile in todo:
            rows = slice(tile.row0, tile.row0 + p.window)
            cols = slice(tile.col0, tile.col0 + p.window)
            sol = self.solver(frame[rows, cols], None if rv is None else rv[rows, cols])
            window_id = f * len(self.tiling) + tile.index
            parts.append(_rows(sol, tile, f, window_id, p.pixel_size))
        return parts, len(todo)


#: A pixel within this fraction of the saturation level is at it: the level and the frames
#: are the same ADU converted to photons by the same arithmetic, and one ADU is a far larger
#: step than this.
SATURATION_TOLERANCE = 1e-9


def censored_pixels(frame: NDArray, saturation: float | None) -> NDArray[np.bool_] | None:
    """The pixels of ``frame`` (photons) at the camera's ``saturation`` (photons,
    :attr:`LocalizeParams.saturation`), or None where none is or no level is known."""
    if saturation is None:
        return None
    out = np.asarray(frame) >= saturation * (1.0 - SATURATION_TOLERANCE)
    return out if out.any() else None


def _frames_and_backgrounds(
    get,
    n: int,
    start: int,
    stop: int,
    block: int,
    p: LocalizeParams,
    model: PSFModel,
    read_variance: NDArray | None = None,
):
    """Yield (frame index, frame, background), reading ``block`` frames at a time. A temporal
    background has the bumps of molecules that stay on capped (:func:`capped_bumps`, blocks
    of one image's width: the diameter of the disc holding 90 % of ``model``'s light). Both
    estimates know the camera's noise (excess factor, read noise: ``read_variance``, a map,
    else the run's)."""
    noise = _background_noise(p, read_variance)
    half = p.background_frames // 2
    temporal = _temporal(p, n)
    if temporal:
        width = 2 * light_radius(model, p.pixel_size, p.z_range or model.z_range) + 1
    for b0 in range(start, stop, block):
        b1 = min(b0 + block, stop)
        lo, hi = max(b0 - half, 0), min(b1 + half, n)
        chunk = np.asarray(get(lo, hi), dtype=np.float64)
        if not np.all(np.isfinite(chunk)):
            raise ValueError(f"frames {lo}-{hi - 1} contain NaN or inf values")
        if temporal:
            centres = np.arange(b0, b1) - lo
            bgs = temporal_backgrounds(
                chunk, centres, half, percentile=p.background_percentile, **noise
            )
            bgs = capped_bumps(bgs, width)
        for f in range(b0, b1):
            i = f - lo
            bg = bgs[f - b0] if temporal else spatial_background(chunk[i], **noise)
            yield f, chunk[i], bg


def _tiles_to_solve(tiling: list[Tile], cand: NDArray, margin: int) -> list[Tile]:
    """Tiles whose core, grown by ``margin`` pixels, holds a candidate."""
    if len(cand) == 0:
        return []
    out = []
    r, c = cand[:, 0], cand[:, 1]
    for t in tiling:
        inside = (
            (r >= t.core_rows[0] - margin)
            & (r < t.core_rows[1] + margin)
            & (c >= t.core_cols[0] - margin)
            & (c < t.core_cols[1] + margin)
        )
        if inside.any():
            out.append(t)
    return out
