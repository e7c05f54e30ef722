"""Configuration of a localization run: every default, unit conversion and check, in one place.

- :class:`LocalizeParams`: the analysis parameters, frozen and stored with every table.
- :data:`LOCALIZE_DEFAULTS` and :func:`check_options`: the options of ``sparseloc localize``,
  which are also the keys of a TOML file's ``[localize]`` table, with their defaults and types.
- :func:`build_job`: from those options and the movie, the PSF model, the camera, the
  parameters, the frame range and the sCMOS read-variance map of one run (:class:`LocalizeJob`).

The command line only parses flags into options, calls :func:`build_job` and the pipeline, and
writes; the Python API builds :class:`LocalizeParams` directly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .camera import (
    Camera,
    camera_from_options,
    clipping,
    noise_variance,
    saturation_level,
    type_saturation,
)
from .engine import check_engine
from .options import LOCALIZE_DEFAULTS, check_options
from .psf import make_psf
from .psf.base import PSFModel, light_radius
from .solvers.frame import RELOCATE
from .solvers.mle import check_qe
from .units import WAVELENGTH_RANGE_NM, check_length_nm, check_pixel_size, check_z_limits

log = logging.getLogger(__name__)

__all__ = [
    "LOCALIZE_DEFAULTS",
    "METHODS",
    "LocalizeJob",
    "LocalizeParams",
    "build_job",
    "check_options",
    "frame_range",
    "noise_model",
    "read_variance_photons",
    "saturation_adu",
    "window_for",
]

METHODS = ("frame", "hybrid", "mp", "co")
#: How the frame solver spends its work (see ``LocalizeParams.frame_schedule``).
SCHEDULES = ("auto", "two-tier", "whole-frame")


@dataclass(frozen=True)
class LocalizeParams:
    """Analysis parameters (all stored with the results).

    Parameters
    ----------
    pixel_size : float
        Pixel size in sample space (nm).
    method : {"frame", "hybrid", "mp", "co"}
        ``frame``: pursuit over the whole frame, then maximum-likelihood fits of groups of
        overlapping emitters with their neighbours' light held fixed
        (:mod:`sparseloc.solvers.frame`). The others solve fixed windows (tiles) with the
        paper's hybrid MP+CO, matching pursuit or convex recovery.
    refine : bool
        Maximum-likelihood stage with count selection (part of ``hybrid``; applied after
        ``mp`` and ``co`` too). The ``frame`` solver always fits by maximum likelihood;
        ``refine=False`` only turns its count selection off.
    window, margin : int
        Window size and the margin (pixels) outside each window's owned core.
    z_range : (float, float), optional
        Axial range (nm) of the dictionaries and, for a tabulated model (``tabulate``, the
        default, or a calibration), of the fits; within the model's; default the model's.
        Where the sample is thinner than the model's range, giving its depth keeps fits from
        reading crowded neighbours' light as emitters at depths where there are none
        (``docs/benchmarks/sample_z_range.txt``).
    coarse, fine : (dxy, dz)
        Grid steps (nm) of the coarse and fine dictionaries. The lateral step must divide
        the pixel; by default the largest such step up to 80 nm (coarse) and, for the fine
        grid, 20 nm with ``refine`` (the fit goes beyond the grid) or the paper's 10 nm
        without; axial steps 120 and 30 (or 15) nm. The frame solver's pursuit uses the
        coarse steps, with 60 nm planes by default.
    min_snr : float
        Detection significance: a candidate (``frame``: a new emitter of the pursuit) must
        carry at least this many standard errors of the noise.
    background_frames : int
        Frames in the sliding block of the temporal background.
    background_percentile : float
        Percentile of that block.
    tabulate : bool
        Work with a spline table of the model (:meth:`SplinePSF.from_model`, 10 nm planes)
        instead of the model itself: much faster for pupil models, same precision.
    background : {"auto", "temporal", "spatial"}
        Temporal: a per-pixel percentile over a sliding block of frames (blinking
        molecules). Spatial: a per-frame estimate from each frame's darker pixels (snapshots,
        short movies, molecules that stay on); the frame solver estimates it once more from
        the frame less its fitted emitters' light (in a crowd their images fill the darker
        pixels too), searches what that background leaves and refits. Auto: temporal for
        movies of at least ``min_temporal_frames`` frames.
    min_temporal_frames : int
        See ``background``.
    noise : {"poisson", "emccd", "scmos"}
        Likelihood of the maximum-likelihood stage.
    read_variance : float
        Read-noise variance per pixel in photons^2 (``noise="scmos"``, or an EMCCD's read
        noise behind its EM gain): enters the detection threshold and the likelihood (Huang
        et al. 2013).
    qe : float
        The camera's quantum efficiency in (0, 1]: frames converted to photons hold
        photoelectrons divided by it, so their shot noise is ``mu / qe``. It weights the
        likelihood (uncertainties and goodness of fit on the photoelectrons' scale; the
        windowed solvers' chi-square count selection too), while the detection and the frame
        solver's empirical add threshold stay on the photon-counting scale they were measured
        on; 1 treats the frames as photon counts.
    max_emitters : int
        Cap per window.
    engine : {"auto", "numpy", "numba"}
        Which engine computes the solvers' arithmetic (:mod:`sparseloc.engine`): ``"auto"``
        runs the compiled numba kernels where numba works, else NumPy; ``"numpy"`` the plain
        reference. Both give the same table to rounding (a crowded region whose two fits
        are about equally likely may go either way in the frame solver's second start).
    relocate : int
        Relocation passes of the frame solver (:func:`~sparseloc.solvers.frame.frame_fit`):
        each emitter in turn replaced by the best PSF position of what its neighbours leave
        unexplained, kept where the likelihood rises; each pass costs time and finds emitters
        that crowds hide. 0 disables.
    frame_schedule : {"auto", "whole-frame", "two-tier"}
        How the ``frame`` solver spends its work. ``whole-frame``: the pursuit and the fits
        over every emitter of the frame. ``two-tier``: emitters whose images overlap no
        other's are fitted alone, and the fits with count selection (from the pursuit on a
        crop where a crowd is large) run only where the light crowds or one emitter does not
        explain it (:mod:`sparseloc.solvers.two_tier`). ``auto`` (default): two tiers, but a
        frame whose crowds hold more emitters than its singles where most emitters' images
        overlap another's is solved whole (:func:`~sparseloc.solvers.two_tier.crowded`), and
        a large crowd by the whole-frame solver on a crop around it: faster where most
        emitters are alone, the whole-frame solver's tables where they crowd (measurements:
        ``docs/benchmarks/auto_schedule.txt``).
    second_start : bool
        The whole-frame solver also fits the frame from a second start, the peaks of its
        non-negative L1 deconvolution (:mod:`sparseloc.solvers.frame_l1`), and keeps, region
        by region, the likelier of the two fits (:mod:`sparseloc.solvers.frame_compose`):
        more emitters found right in crowds, at the cost of the second fit where the two
        starts differ (``docs/benchmarks/second_start.txt``). False: the pursuit's start alone.
    regrow : bool
        The whole-frame solver also solves each group of two or more emitters of its fit
        once more from one emitter, adding one at a time with joint refits
        (:mod:`sparseloc.solvers.frame_grow`), and keeps, region by region, the likelier
        arrangement: where images overlap, the pursuit's first emitter can land between two
        of them and the fits keep that arrangement. Costs about 1.1-1.2x the time where
        frames are solved whole (``docs/benchmarks/regrow.txt``). False: the fits from the
        pursuit and the second start alone. Needs ``refine`` (its growth is the count
        selection's).
    haze : bool
        The sample adds a haze (autofluorescence, out-of-focus light) broader than one
        emitter's image: each window fit of the frame solver scales the background
        estimate's shape (smoothed at the PSF's core radius) where that makes the window
        clearly likelier than a constant (:data:`~sparseloc.solvers.mle.SHAPE_MARGIN`), so the
        haze's slope across a window is not explained by false emitters, and keeps the
        constant elsewhere. Off by default: where the estimate's shape holds light the model
        lacks (a calibration's halo in dense frames) the data choose it too, which costs up
        to 1.5 points of Jaccard on some dense sets and gains on others, and each window with a
        slope along the shape is fitted twice (``docs/benchmarks/haze.txt``).
    saturation : float or None
        Photons at which a pixel reaches the camera's saturation (the largest over the
        pixels where an sCMOS camera's gain and offset maps give each its own; the frames'
        reader lifts every saturated pixel to it, :meth:`LocalizeJob.frames`): a pixel of a
        frame at or above it says only that its light reached that level, and the frame
        solver's fits leave it out of their likelihood (a clipped peak would otherwise
        flatten the fitted image and move its z). None: no pixel is taken as saturated. The
        windowed methods do not use it.
    """

    pixel_size: float
    method: str = "frame"
    refine: bool = True
    window: int = 11
    margin: int = 3
    z_range: tuple[float, float] | None = None
    coarse: tuple[float, float] | None = None
    fine: tuple[float, float] | None = None
    min_snr: float = 5.0
    background_frames: int = 21
    background_percentile: float = 30.0
    background: str = "auto"
    tabulate: bool = True
    min_temporal_frames: int = 50
    noise: str = "poisson"
    max_emitters: int = 10
    read_variance: float = 0.0
    engine: str = "auto"
    qe: float = 1.0
    relocate: int = RELOCATE
    frame_schedule: str = "auto"
    second_start: bool = True
    regrow: bool = True
    haze: bool = False
    saturation: float | None = None

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}; got {self.method!r}")
        if not self.pixel_size > 0:
            raise ValueError(f"pixel_size must be > 0 nm, got {self.pixel_size}")
        r = self.relocate
        if (
            isinstance(r, bool)
            or not isinstance(r, int | float | np.integer | np.floating)
            or not np.isfinite(r)
            or r < 0
            or int(r) != r
        ):
            raise ValueError(f"relocate must be a whole number >= 0, got {r!r}")
        object.__setattr__(self, "relocate", int(r))  # frozen: as an int
        if self.window < 5 or self.margin < 0 or self.window - 2 * self.margin < 1:
            raise ValueError(
                f"window {self.window} px and margin {self.margin} px leave no core (--window "
                "must be at least 5 px and more than twice --margin, which must be >= 0)"
            )
        if self.frame_schedule not in SCHEDULES:
            raise ValueError(
                f"frame_schedule must be one of {', '.join(SCHEDULES)}; got {self.frame_schedule!r}"
            )
        if self.background_frames < 1:
            raise ValueError("background_frames must be >= 1")
        if self.noise not in ("poisson", "emccd", "scmos"):
            raise ValueError(f"noise must be poisson, emccd or scmos; got {self.noise!r}")
        if not (np.isfinite(self.read_variance) and self.read_variance >= 0):
            raise ValueError(f"read_variance must be >= 0 photons^2, got {self.read_variance}")
        object.__setattr__(self, "qe", check_qe(self.qe))  # frozen: as a float
        if self.saturation is not None and not (
            np.isfinite(self.saturation) and self.saturation > 0
        ):
            raise ValueError(f"saturation must be > 0 photons, got {self.saturation}")
        if self.read_variance > 0 and self.noise == "poisson":
            raise ValueError(
                "read_variance applies to noise='scmos' or 'emccd', not 'poisson' (a "
                "photon-counting camera has no read noise)"
            )
        check_engine(self.engine)
        if not (np.isfinite(self.min_snr) and self.min_snr > 0):
            raise ValueError(f"min_snr must be a number > 0, got {self.min_snr!r}")
        if self.background not in ("auto", "temporal", "spatial"):
            raise ValueError(
                f"background must be auto, temporal or spatial; got {self.background!r}"
            )
        px = float(self.pixel_size)
        if self.coarse is None:
            # The frame solver's pursuit uses 60 nm planes: its starts then need fewer
            # corrections from the fits, whose errors they bias on dense frames.
            dz = 60.0 if self.method == "frame" else 120.0
            object.__setattr__(self, "coarse", (px / np.ceil(px / 80.0 - 1e-9), dz))
        if self.fine is None:
            # With the maximum-likelihood stage the fine grid only seeds the fit, so it can be
            # coarser than the paper's 10/15 nm.
            dxy, dz = (20.0, 30.0) if self.refine else (10.0, 15.0)
            object.__setattr__(self, "fine", (px / np.ceil(px / dxy - 1e-9), dz))


def window_for(
    model: PSFModel, pixel_size: float, window: int | None, margin: int | None
) -> tuple[int, int]:
    """Window and margin (px) of the window methods: the user's, else sized from a measured
    PSF, else 11 and 3.

    A measured (spline) PSF holds its light in its ROI, so the radius holding 90 % of it is a
    fair margin: windows then see all of every emitter they keep. Pupil models keep a halo of
    a few per cent far out, so their radius says little: they get the paper's 11 px window.
    """
    from .psf.spline import SplinePSF

    if margin is None:
        if isinstance(model, SplinePSF):
            margin = light_radius(model, pixel_size)
        else:
            margin = 3
        if window is not None:  # a window the user chose keeps a core of at least 1 px
            margin = min(margin, (int(window) - 1) // 2)
    if window is None:
        window = max(11, 2 * margin + 9) if isinstance(model, SplinePSF) else 11
    return int(window), int(margin)


def noise_model(camera: Camera) -> str:
    """The likelihood of a camera's data: ``"emccd"`` (shot noise doubled) behind an EM gain
    above 1; ``"scmos"`` for an sCMOS camera, or an EMCCD run without EM gain but with read
    noise; else ``"poisson"`` (as :func:`sparseloc.camera.noise_variance` describes them)."""
    if camera.kind == "emccd":
        if camera.em_gain > 1.0:
            return "emccd"
        return "scmos" if camera.read_noise > 0 else "poisson"
    return "scmos" if camera.kind == "scmos" else "poisson"


def read_variance_photons(camera: Camera, shape: tuple[int, int]) -> NDArray[np.float64]:
    """The camera's read-noise variance in photons^2 for the likelihood and the detection: 0
    for an ideal camera; a scalar array unless an sCMOS camera has maps that vary over
    ``shape`` (rows, cols)."""
    if camera.kind == "ideal":
        return np.asarray(0.0)
    var = np.asarray(noise_variance(np.zeros(shape), camera))
    if var.ndim == 2 and np.ptp(var) == 0:
        var = np.asarray(var.flat[0])
    return var


def frame_range(frames: str | None, n: int) -> tuple[int, int]:
    """``START:STOP`` (0-based, either may be left out) as ``(start, stop)`` of an ``n``-frame
    movie; ValueError in one sentence otherwise."""
    if not frames:
        return 0, n
    try:
        a, b = str(frames).split(":")
        start, stop = int(a or 0), int(b) if b else n
    except ValueError:
        raise ValueError(
            f"--frames takes START:STOP (0-based, STOP excluded: 0:5 for the first five "
            f"frames, 5:6 for frame 5), got {frames!r}"
        ) from None
    if start < 0 or stop < 0:
        raise ValueError(
            f"--frames takes 0-based frame numbers >= 0 (START:STOP, STOP excluded); got {frames!r}"
        )
    if stop > n:
        raise ValueError(f"--frames {frames} goes past the movie's {n} frames (0:{n})")
    if stop <= start:
        raise ValueError(f"--frames {frames} holds no frame")
    return start, stop


@dataclass
class LocalizeJob:
    """Everything one run of :func:`sparseloc.pipeline.localize` needs beside the frames."""

    model: PSFModel
    camera: Camera
    params: LocalizeParams
    start: int
    stop: int
    #: sCMOS read variance (photons^2) per pixel, or None where it is one number (in params).
    read_variance_map: NDArray[np.float64] | None
    #: Defective (hot or stuck) pixels, replaced by their neighbours in every frame
    #: (:func:`find_defects`), or None where the movie shows none.
    defects: NDArray[np.bool_] | None = None
    #: (ADU, values) where the movie's largest value looks clipped below its type's maximum
    #: (:func:`~sparseloc.camera.clipping`), else None.
    clipped: tuple[float, int] | None = None
    #: ADU at which the camera saturates (``params.saturation`` is that level in photons),
    #: or None.
    saturation_adu: float | None = None

    def frames(self, movie: Any) -> Any:
        """The movie's frames in photons as this run reads them
        (:class:`~sparseloc.distributed.CameraFrames`: the camera, the defective pixels
        replaced, saturated pixels at the run's level)."""
        from .distributed import CameraFrames

        return CameraFrames(movie, self.camera, self.defects, self.saturation_adu)


#: Built-in pupil models (:data:`sparseloc.psf.PSF_NAMES`), which take the pupil's optics.
_PUPIL_NAMES = ("dh", "astig", "clear")
#: The pupil optics options (:data:`LOCALIZE_DEFAULTS`) and the :func:`make_psf` argument of
#: each: NA, emission wavelength (nm) and Gaussian blur sigma (nm) of a pupil model; the
#: pupil disc's radius (mask pixels) in a mask file.
OPTICS_OPTIONS: dict[str, str] = {
    "na": "na",
    "wavelength": "wavelength",
    "blur": "blur",
    "mask_radius": "radius",
}


def psf_option(spec: str, **kwargs: Any) -> PSFModel:
    """:func:`~sparseloc.psf.make_psf` of the ``--psf`` option, its refusals naming it."""
    try:
        return make_psf(spec, **kwargs)
    except ValueError as exc:
        if "--psf" in str(exc):
            raise
        raise ValueError(f"--psf: {exc}") from exc


#: The refusal of a run without a PSF.
PSF_NEEDED = (
    "--psf is needed: the PSF.h5 that 'sparseloc calibrate' made from a bead z-stack of this "
    "microscope, a phase-mask file with its optics, or a built-in pupil model (dh, astig, "
    "clear) for simulated data"
)


def build_model(options: dict[str, Any]) -> PSFModel:
    """The PSF model of ``options["psf"]``, with the sample's optics, the pupil's optics
    (``na``, ``wavelength``, ``blur``; ``mask_radius`` for mask files) and the user's z range
    where it is a pupil model (which renders any depth)."""
    from .psf.masks import MASK_SUFFIXES
    from .psf.pupil import PupilPSF

    spec = options["psf"]
    if spec is None:
        raise ValueError(PSF_NEEDED)
    optics = {k: float(options[k]) for k in ("n_sample", "focal_depth") if options[k] is not None}
    pupil = {
        arg: float(options[key])
        for key, arg in OPTICS_OPTIONS.items()
        if options.get(key) is not None
    }
    mask_file = Path(str(spec)).suffix.lower() in MASK_SUFFIXES
    if "radius" in pupil and not mask_file:
        raise ValueError(
            f"--mask-radius applies to phase-mask files ({', '.join(MASK_SUFFIXES)}), not {spec!r}"
        )
    if pupil and not (mask_file or str(spec).lower() in _PUPIL_NAMES):
        given = [k for k in OPTICS_OPTIONS if options.get(k) is not None]
        flags = ", ".join("--" + k.replace("_", "-") for k in given)
        raise ValueError(
            f"{flags} {'applies' if len(given) == 1 else 'apply'} to pupil models (dh, astig, "
            f"clear, mask files), not {spec!r}"
        )
    if "wavelength" in pupil:
        check_length_nm(pupil["wavelength"], "--wavelength", WAVELENGTH_RANGE_NM)
    model = psf_option(spec, **pupil)
    if optics and not isinstance(model, PupilPSF):
        raise ValueError(
            "--n-sample and --focal-depth apply to pupil models (built-in names, mask files)"
        )
    if "focal_depth" in optics and "n_sample" not in optics:
        raise ValueError("--focal-depth needs --n-sample (the sample's refractive index)")
    zmin, zmax = options["z_min"], options["z_max"]
    check_z_limits(zmin, zmax)
    if isinstance(model, PupilPSF) and (optics or zmin is not None or zmax is not None):
        lo, hi = model.z_range
        z_range = (lo if zmin is None else float(zmin), hi if zmax is None else float(zmax))
        model = psf_option(spec, z_range=z_range, **optics, **pupil)
    return model


#: Most frames of the run's range whose pixel medians the camera offset is checked against.
OFFSET_CHECK_FRAMES = 8
#: Most frames, spread over the movie, whose median finds its defective pixels; fewer where
#: they would hold more than :data:`DEFECT_PIXELS` pixels in all.
DEFECT_FRAMES = 50
DEFECT_PIXELS = 20_000_000


def _spread_frames(movie: Any) -> NDArray:
    """Up to :data:`DEFECT_FRAMES` frames (ADU) spread over the whole movie, whatever the
    run's range: what the movie's checks read (a run of one frame finds what the whole
    does)."""
    n = len(movie)
    per_frame = int(np.prod(movie.frames(0, 1).shape[-2:]))
    count = max(1, min(DEFECT_FRAMES, n, DEFECT_PIXELS // per_frame))
    picks = np.unique(np.linspace(0, n - 1, count).astype(int))
    return np.concatenate([movie.frames(int(i), int(i) + 1) for i in picks])


def find_defects(
    movie: Any, camera: Camera, pixel_size: float, frames: NDArray | None = None
) -> NDArray[np.bool_] | None:
    """The movie's defective (hot or stuck) pixels (:func:`~sparseloc.defects.defective_pixels`
    of its :func:`_spread_frames`, or of ``frames`` where already read), or None where there
    are none."""
    from .camera import photon_noise, to_photons
    from .defects import defective_pixels

    raw = _spread_frames(movie) if frames is None else frames
    photons = np.concatenate([to_photons(f[None], camera) for f in raw])
    factor, _ = photon_noise(camera)
    read_var = read_variance_photons(camera, raw.shape[-2:])
    mask = defective_pixels(photons, pixel_size, factor, read_var)
    return mask if mask.any() else None


def build_camera(
    options: dict[str, Any], movie: Any, start: int = 0, stop: int | None = None
) -> Camera:
    """The camera of ``options`` (:func:`~sparseloc.camera.camera_from_options`), checked
    against the movie's frames ``start:stop`` (ADU): its maps against their shape, its
    offset against the median pixel value of up to :data:`OFFSET_CHECK_FRAMES` of them,
    spread over the range (the offset lies below it in at least one; a blank frame, dropped
    or taken with the shutter closed, says nothing about it)."""
    cam = camera_from_options(options)
    stop = len(movie) if stop is None else stop
    first = movie.frames(start, start + 1)
    if cam.map_shape is not None and cam.map_shape != first.shape[-2:]:
        raise ValueError(
            f"the camera maps are {cam.map_shape[0]}x{cam.map_shape[1]} pixels but the "
            f"frames are {first.shape[-2]}x{first.shape[-1]}"
        )
    if cam.offset_map is None:
        picks = np.unique(np.linspace(start, stop - 1, min(OFFSET_CHECK_FRAMES, stop - start)))
        level = max(float(np.median(movie.frames(int(i), int(i) + 1))) for i in picks)
        if cam.offset >= level:
            raise ValueError(
                f"the offset ({cam.offset:g} ADU) is not below the median pixel value of any "
                f"of {len(picks)} frame(s) spread over the run (at most {level:g} ADU); check "
                "--offset"
            )
    return cam


#: Two pixel sizes that differ by more than this fraction describe different images.
PIXEL_SIZE_TOLERANCE = 0.01


def pixel_sizes_differ(given: float, recorded: float) -> bool:
    """Whether ``recorded`` (nm; a file's metadata) contradicts ``given`` (nm)."""
    return abs(recorded - given) > PIXEL_SIZE_TOLERANCE * given


def resolve_pixel_size(options: dict[str, Any], model: PSFModel, movie_pixel: float | None):
    """The pixel size (nm): the option, else the calibration's, else the movie's metadata
    (``movie_pixel``, nm or None), which also checks the other two."""
    px = options["pixel_size"]
    cal_px = getattr(model, "pixel_size", None)
    if px is None and cal_px is not None:
        px = float(cal_px)
    if px is None and movie_pixel:
        # a movie that records its pixel size (sparseloc's simulate, OME, ImageJ metadata)
        px = float(movie_pixel)
        log.warning("pixel size %g nm, from the movie's metadata (--pixel-size overrides it)", px)
    if px is None:
        raise ValueError(
            "give the pixel size in sample space with --pixel-size NM: the PSF "
            f"{str(options.get('psf'))!r} does not carry one (a calibration from "
            "sparseloc calibrate does), nor does the movie's metadata"
        )
    source = "the calibration's pixel size" if cal_px is not None else "the movie's pixel size"
    px = check_pixel_size(px, "--pixel-size" if options["pixel_size"] is not None else source)
    if movie_pixel and pixel_sizes_differ(px, movie_pixel):
        if options["pixel_size"] is not None:
            raise ValueError(
                f"--pixel-size {px:g} nm differs from the movie's metadata ({movie_pixel:g} nm)"
            )
        raise ValueError(
            f"the calibration {str(options.get('psf'))!r} was made at {px:g} nm pixels but the "
            f"movie's metadata says {movie_pixel:g} nm: calibrate beads imaged at the movie's "
            "pixel size"
        )
    return float(px)


def _check_frames_hold_a_window(shape: tuple[int, int], window: int, given: bool) -> None:
    """ValueError, with the fix, where the frames are smaller than one window."""
    rows, cols = (int(v) for v in shape)
    if rows >= window and cols >= window:
        return
    fix = (
        "crop a larger region"
        if given
        else f"pass --window {min(rows, cols)} or less (the default is sized to hold the "
        "PSF's light; a smaller window holds less of it), or crop a larger region"
    )
    raise ValueError(
        f"the frames ({rows}x{cols} px) are smaller than one window ({window}x{window} px): {fix}"
    )


def build_job(
    options: dict[str, Any],
    movie: Any,
    defects: NDArray[np.bool_] | str | None = "find",
    clipped: tuple[float, int] | None = None,
) -> LocalizeJob:
    """The run that ``options`` (:data:`LOCALIZE_DEFAULTS` keys) describe on ``movie`` (an
    object with ``len()``, ``frames(start, stop)`` in ADU and ``pixel_size``, nm or None).
    ``defects``: the movie's defective pixels where already found (:func:`find_defects` with
    the same camera and pixel size: a viewer's previews of one movie), else "find";
    ``clipped``: where they were given, the :attr:`LocalizeJob.clipped` found with them.

    Raises ValueError in one sentence for options that do not fit the movie or each other.
    """
    opts = {**LOCALIZE_DEFAULTS, **check_options(options)}
    model = build_model(opts)
    px = resolve_pixel_size(opts, model, getattr(movie, "pixel_size", None))
    start, stop = frame_range(opts["frames"], len(movie))
    cam = build_camera(opts, movie, start, stop)
    shape = movie.frames(start, start + 1).shape[-2:]
    window, margin = window_for(model, px, opts["window"], opts["margin"])
    _check_frames_hold_a_window(shape, window, opts["window"] is not None)
    read_var = read_variance_photons(cam, shape)
    lo, hi = model.z_range
    z_range = (
        lo if opts["z_min"] is None else opts["z_min"],
        hi if opts["z_max"] is None else opts["z_max"],
    )
    params = LocalizeParams(
        pixel_size=px,
        method=opts["method"],
        refine=opts["refine"],
        window=window,
        margin=margin,
        z_range=z_range,
        min_snr=opts["min_snr"],
        background=opts["background"],
        noise=noise_model(cam),
        read_variance=float(read_var) if read_var.ndim == 0 else 0.0,
        engine=opts["engine"],
        qe=cam.qe,
        **({} if opts["relocate"] is None else {"relocate": opts["relocate"]}),
        **({} if opts["frame_schedule"] is None else {"frame_schedule": opts["frame_schedule"]}),
        second_start=opts["second_start"],
        regrow=opts["regrow"],
        haze=opts["haze"],
    )
    if isinstance(defects, str):
        sample = _spread_frames(movie)
        defects = find_defects(movie, cam, px, sample)
        clipped = clipping(sample, ignore=defects)
    first = movie.frames(start, start + 1)
    adu = saturation_adu(opts["saturation"], clipped, first, start, defects)
    sat = None if adu is None else saturation_level(adu, cam, shape)
    if sat is not None and sat <= 0:
        raise ValueError(
            f"the saturation, {adu:g} ADU, lies at or below the camera's offset: no pixel "
            "could reach it; check --offset and --saturation"
        )
    params = replace(params, saturation=sat)
    read_map = read_var if read_var.ndim == 2 else None
    # the windowed methods take clipped pixels at face value: their frames are not lifted
    lifted = adu if params.method == "frame" else None
    return LocalizeJob(model, cam, params, start, stop, read_map, defects, clipped, lifted)


def saturation_adu(
    given: float | None,
    clipped: tuple[float, int] | None,
    raw: NDArray,
    index: int = 0,
    defects: NDArray[np.bool_] | None = None,
) -> float | None:
    """The ADU at which the movie's camera saturates: ``given``, else the level the movie
    looks clipped at (``clipped``, :func:`~sparseloc.camera.clipping`), else its integer
    type's largest value (``raw``: frame ``index`` in ADU, its ``defects`` left out of the
    check that ``given`` is no lower than its pixels); None for floating-point frames without
    a level given."""
    if given is not None and not (np.isfinite(given) and given > 0):
        raise ValueError(f"--saturation must be a positive number of ADU, got {given:g}")
    values = np.asarray(raw).reshape(-1, *np.shape(raw)[-2:])
    if defects is not None:
        values = values[:, ~np.asarray(defects, dtype=bool)]
    top = float(np.max(values)) if values.size else -np.inf
    if given is not None and given < top:
        raise ValueError(
            f"--saturation {given:g} ADU lies below frame {index}'s largest value, {top:g} "
            "ADU: no pixel reads above its camera's saturation"
        )
    return given if given is not None else clipped[0] if clipped else type_saturation(raw)
