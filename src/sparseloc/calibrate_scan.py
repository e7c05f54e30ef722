"""Bead z-scans for PSF calibration (:mod:`sparseloc.calibrate`): the z of each plane (from a
stage step or a z file), the conversion from ADU to photons and the per-frame background.

Coordinates (design.md): ``z = (slice - z0_slice) * z_step`` with ``z0_slice`` the middle slice
by default, or the z of each frame from a file. :mod:`sparseloc.calibrate` re-exports
:func:`read_z_file`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from .camera import Camera, camera_from_options, clipping, to_photons, type_saturation
from .defects import defective_pixels, replace_defects
from .detect import background_trend
from .units import check_pixel_size, check_z_step

__all__ = [
    "BeadScan",
    "frame_background",
    "read_bead_positions",
    "read_scan",
    "read_z_file",
    "scan_conversion",
]

# Messages keep the logger of sparseloc.calibrate, where the calibration has always logged.
log = logging.getLogger("sparseloc.calibrate")


def scan_conversion(camera: Camera | dict[str, Any]) -> tuple[float, float]:
    """The offset (ADU) and photons per ADU (``gain / em_gain / qe``, gain in e-/ADU) that
    convert a bead scan to photons, as :func:`sparseloc.camera.to_photons` converts a movie.

    Parameters
    ----------
    camera : Camera or dict
        The camera, or its options (:func:`sparseloc.camera.camera_from_options`).

    Returns
    -------
    offset, photons_per_adu : float
        The ``offset`` and ``gain`` arguments of :func:`sparseloc.calibrate.calibrate_beads`:
        for an sCMOS camera with per-pixel maps, the maps' medians (the conversion itself
        then takes the maps, see :func:`read_scan`'s ``camera``).

    Raises
    ------
    ValueError
        For invalid camera settings.
    """
    if isinstance(camera, dict):
        camera = camera_from_options(camera)
    if camera.map_shape is None:
        return camera.offset, camera.photons_per_adu
    offset, gain = camera._pixel_params(camera.map_shape)
    return float(np.median(offset)), float(np.median(gain)) / (camera.em_gain * camera.qe)


def _adu_to_photons(
    raw: NDArray, offset: float, photons_per_adu: float, camera: Camera | None = None
) -> NDArray[np.float64]:
    """``(ADU - offset) * photons_per_adu``: :func:`~sparseloc.camera.to_photons` of a camera
    whose gain is ``photons_per_adu`` (its EM gain and QE folded in by
    :func:`scan_conversion`); with the per-pixel maps of ``camera`` where it has them."""
    if camera is not None and camera.map_shape is not None:
        if tuple(raw.shape[-2:]) != camera.map_shape:
            rows, cols = camera.map_shape
            raise ValueError(
                f"the camera maps are {rows}x{cols} pixels but the bead stack's frames are "
                f"{raw.shape[-2]}x{raw.shape[-1]}"
            )
        return to_photons(raw, camera)
    return to_photons(raw, Camera(offset=offset, gain=photons_per_adu))


def read_bead_positions(path: str | Path, pixel_size: float) -> NDArray[np.float64]:
    """The beads' known lateral positions from a CSV, as (B, 2) x, y in nm.

    Columns ``x_nm, y_nm`` (nm, origin at the outer corner of pixel (0, 0), x along columns:
    the project's convention) or ``x_px, y_px`` (pixels, 0.0 at the centre of the first
    pixel, as storm-analysis writes them). Rows repeating a position (one row per frame, as in
    the SMLM challenge's ``beads_gt.csv``) count once.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"bead file {str(p)!r} does not exist")
    try:
        df = pd.read_csv(p, skipinitialspace=True)
    except (ValueError, OSError, pd.errors.ParserError) as exc:
        raise ValueError(f"cannot read bead file {p.name}: {exc}") from exc
    cols = {str(c).strip().lower(): c for c in df.columns}
    if "x_nm" in cols and "y_nm" in cols:
        xy = df[[cols["x_nm"], cols["y_nm"]]].apply(pd.to_numeric, errors="coerce").to_numpy()
    elif "x_px" in cols and "y_px" in cols:
        px = df[[cols["x_px"], cols["y_px"]]].apply(pd.to_numeric, errors="coerce").to_numpy()
        xy = (px + 0.5) * float(pixel_size)
    else:
        raise ValueError(
            f"bead file {p.name} needs columns x_nm, y_nm (nm, origin at the outer corner of "
            "pixel (0, 0)) or x_px, y_px (pixels, 0.0 at the centre of the first pixel)"
        )
    if len(xy) == 0 or not np.all(np.isfinite(xy)):
        raise ValueError(f"bead file {p.name} holds no positions or non-numeric ones")
    return np.unique(np.round(xy, 3), axis=0)


def read_z_file(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Read per-frame z positions from a CSV (storm-analysis style or one column).

    Accepted columns: ``z_um`` or ``z_nm`` (or a single unnamed column in nm), optional
    ``valid`` (0/1) and ``frame_0based``/``frame``. Returns z in nm and the valid flags, in
    frame order.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"z file {str(p)!r} does not exist")
    try:
        df = pd.read_csv(p)
    except (ValueError, OSError, pd.errors.ParserError) as exc:
        raise ValueError(f"cannot read z file {p.name}: {exc}") from exc
    cols = {c.strip().lower(): c for c in df.columns}
    if "z_um" in cols:
        z = df[cols["z_um"]].to_numpy(dtype=float) * 1000.0
    elif "z_nm" in cols:
        z = df[cols["z_nm"]].to_numpy(dtype=float)
    elif "z" in cols:
        z = df[cols["z"]].to_numpy(dtype=float)
    else:
        try:
            z = np.loadtxt(p, delimiter=",", ndmin=1).astype(float)
        except ValueError as exc:
            raise ValueError(
                f"z file {p.name} needs a z_um or z_nm column (or one column of nm)"
            ) from exc
        if z.ndim != 1:
            raise ValueError(
                f"z file {p.name} has {z.shape[1]} columns but no header; name them "
                "(z_um or z_nm, and valid)"
            )
        if not np.all(np.isfinite(z)):
            raise ValueError(f"z file {p.name} holds non-numeric or missing z values")
        return z, np.ones(z.size, bool)
    if "valid" in cols:
        flags = pd.to_numeric(df[cols["valid"]], errors="coerce").to_numpy(dtype=float)
        valid = np.nan_to_num(flags, nan=0.0) != 0  # missing or unreadable: not valid
    else:
        valid = np.ones(z.size, dtype=bool)
    for key in ("frame_0based", "frame"):
        if key in cols:
            order = np.argsort(df[cols[key]].to_numpy(), kind="stable")
            z, valid = z[order], valid[order]
            break
    if not np.all(np.isfinite(z[valid])):
        raise ValueError(f"z file {p.name} holds non-numeric or missing z values")
    return z, valid


@dataclass
class BeadScan:
    """A bead z-stack in photons, ready for calibration."""

    data: NDArray[np.float64]  # (Nz, H, W) photons less each frame's background
    projection: NDArray[np.float64]  # (H, W) z-average of ``data``
    zplanes: NDArray[np.float64]  # (Nz,) plane positions (nm)
    step: float  # z step between planes (nm)
    pixel_size: float  # nm
    saturation: float | None  # ADU at which the camera saturates
    sat_frames: NDArray  # the ADU frames the saturation test looks at
    offset: float  # ADU
    gain: float  # photons per ADU: the camera's gain (e-/ADU) / EM gain / QE (scan_conversion)
    background: NDArray[np.float64] | None = None  # (Nz,) each frame's background (photons/px)
    defects: int = 0  # defective (hot or stuck) pixels replaced by their neighbours
    trend: float = 0.0  # photons/px: the range across the field of the trend subtracted
    clipped: tuple[float, int] | None = None  # (ADU, values) where the stack's top is clipped


def read_scan(
    stack: ArrayLike,
    pixel_size: float,
    z_step: float | None,
    z: ArrayLike | None,
    valid: ArrayLike | None,
    z0_slice: float | None,
    offset: float,
    gain: float,
    saturation: float | None,
    camera: Camera | None = None,
    noise: tuple[float, float] = (1.0, 0.0),
) -> BeadScan:
    """Check the stack, place its planes in z, convert it to photons, replace defective
    (hot or stuck) pixels by their neighbours (:mod:`sparseloc.defects`; ``noise``: the
    camera's variance per photon and read variance, photons^2) and subtract each frame's
    background: its smooth change across the field
    (:func:`~sparseloc.detect.background_trend`), then its median level (beads cover a small
    fraction of the field). Where ``camera`` has
    sCMOS maps, they convert the stack (``offset`` and ``gain`` are then their medians,
    :func:`scan_conversion`)."""
    if z is not None and z0_slice is not None:
        raise ValueError(
            "--z0-slice places z = 0 in an even scan (--z-step); with each frame's z given "
            "(--z-file) leave it out"
        )
    raw, p, saturation = _checked_stack(stack, pixel_size, gain, saturation)
    if z is not None:
        photons, sat_frames, zplanes, step = _planes_from_z(
            raw, z, valid, z_step, offset, gain, camera
        )
    else:
        photons, sat_frames, zplanes, step = _even_planes(
            raw, z_step, z0_slice, offset, gain, camera
        )
    if photons.shape[0] < 4:
        raise ValueError(f"a calibration needs at least 4 z planes, got {photons.shape[0]}")
    defects = defective_pixels(photons, p, *noise)
    if defects.any():
        log.info("%d defective (hot or stuck) pixel(s) replaced by their neighbours", defects.sum())
        photons = replace_defects(photons, defects)
        # a pixel stuck at the camera's maximum is no bead's saturation
        sat_frames = np.where(defects, 0, sat_frames)
    # a background that changes across the field (illumination) would leave a ramp in every
    # bead's image, moving its light's centroid: each frame's trend is subtracted first
    trend = background_trend(photons, noise_factor=noise[0], read_variance=noise[1])
    photons = photons - trend
    bg = frame_background(photons)
    if np.median(bg) < 0 and offset > 0:
        raise ValueError(f"the offset {offset:g} ADU is above most pixel values; check --offset")
    data = photons - bg[:, None, None]
    clipped = clipping(sat_frames, saturation, defects)
    return BeadScan(
        data, data.mean(axis=0), zplanes, step, p, saturation, sat_frames, offset, gain, bg,
        int(defects.sum()), float(np.ptp(trend.mean(axis=0))), clipped,
    )  # fmt: skip


def _checked_stack(
    stack: ArrayLike, pixel_size: float, gain: float, saturation: float | None
) -> tuple[NDArray, float, float | None]:
    """The stack as an array, the pixel size (nm) and the saturation (ADU; by default the
    integer type's maximum); ``ValueError`` saying what to fix."""
    raw = np.asarray(stack)
    if raw.ndim != 3:
        raise ValueError(
            f"a bead z-stack must be 3-D (frames, rows, cols), got shape {raw.shape}; "
            "save the scan as a multi-frame TIFF"
        )
    if raw.shape[0] < 2:
        raise ValueError(
            "the bead stack has only one frame; a calibration needs a z-scan through focus "
            "(typically 50-200 frames)"
        )
    if not np.all(np.isfinite(raw)):
        raise ValueError("the bead stack contains NaN or inf values")
    p = check_pixel_size(pixel_size)
    if gain <= 0:
        raise ValueError(f"gain must be > 0 photons per ADU, got {gain}")
    if saturation is None:
        saturation = type_saturation(raw)
    return raw, p, saturation


def _planes_from_z(
    raw: NDArray,
    z: ArrayLike,
    valid: ArrayLike | None,
    z_step: float | None,
    offset: float,
    gain: float,
    camera: Camera | None = None,
) -> tuple[NDArray[np.float64], NDArray, NDArray[np.float64], float]:
    """Photons, the ADU frames used, plane z (nm) and step of a scan with the z of each
    frame: valid frames sorted by z, resampled onto an even grid when the steps are uneven
    or ``z_step`` is given."""
    n = raw.shape[0]
    zf = np.asarray(z, dtype=np.float64).ravel()
    vf = np.ones(zf.size, bool) if valid is None else np.asarray(valid, bool).ravel()
    if zf.size != n or vf.size != n:
        raise ValueError(f"the z file lists {zf.size} frames but the stack has {n}")
    keep = np.nonzero(vf)[0]
    if not np.all(np.isfinite(zf[keep])):
        raise ValueError("the z file holds missing or non-finite z for frames marked valid")
    if keep.size < 4:
        raise ValueError("fewer than 4 frames are marked valid in the z file")
    zk = zf[keep]
    order = np.argsort(zk, kind="stable")
    keep, zk = keep[order], zk[order]
    steps = np.diff(zk)
    if np.any(steps <= 0):
        raise ValueError("the z file repeats a z value; each frame needs its own z")
    if z_step:
        step = check_z_step(z_step)
    else:
        step = check_z_step(float(np.median(steps)), "the z file's median step")
    photons = _adu_to_photons(raw[keep], offset, gain, camera)
    sat_frames = raw[keep]
    if np.ptp(steps) > 1e-3 * step or z_step:
        grid = np.arange(zk[0], zk[-1] + 1e-6 * step, step)
        from scipy.interpolate import interp1d

        photons = interp1d(zk, photons, axis=0, assume_sorted=True)(grid)
        log.info(
            "resampled %d uneven planes onto %d planes %.1f nm apart", zk.size, grid.size, step
        )
        zk = grid
    return photons, sat_frames, zk, step


def _even_planes(
    raw: NDArray,
    z_step: float | None,
    z0_slice: float | None,
    offset: float,
    gain: float,
    camera: Camera | None = None,
) -> tuple[NDArray[np.float64], NDArray, NDArray[np.float64], float]:
    """Photons, the ADU frames, plane z (nm) and step of a scan in even steps, z = 0 at
    ``z0_slice`` (default the middle slice)."""
    n = raw.shape[0]
    if z_step is None:
        raise ValueError("give the stage step with --z-step NM, or each frame's z with a z file")
    step = check_z_step(z_step)
    z0 = (n - 1) / 2.0 if z0_slice is None else float(z0_slice)
    if not 0 <= z0 <= n - 1:
        raise ValueError(f"--z0-slice {z0_slice} is outside the stack's 0..{n - 1} slices")
    zplanes = (np.arange(n) - z0) * step
    photons = _adu_to_photons(raw, offset, gain, camera)
    return photons, raw, zplanes, step


def frame_background(photons: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each frame's background (photons/px, (Nz,)): the median of ``photons`` (Nz, H, W) over
    the frame, where beads cover a small fraction of the field or their light is removed."""
    return np.median(photons.reshape(photons.shape[0], -1), axis=1)
