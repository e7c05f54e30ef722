"""Ground-truth scenes, noise-free rendering and noisy camera movies.

Truth tables are :class:`pandas.DataFrame` objects with one row per emitter per frame and the
columns ``frame`` (int, 0-based), ``x_nm``, ``y_nm``, ``z_nm``, ``photons`` (float) and optionally
``emitter_id`` (int; the same fluorophore across its blinks). Coordinates are native (design.md):
the outer corner of pixel (0, 0) is the origin, ``x`` runs along columns, ``y`` along rows, so the
field of view of a ``(rows, cols)`` frame with pixel size ``p`` is ``[0, cols*p] x [0, rows*p]``.

Every generator draws from a :class:`numpy.random.Generator`, so a seed fixes the result.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from tqdm import tqdm

from .camera import Camera, apply_noise
from .io.truth import TRUTH_COLUMNS, check_truth_table
from .psf.base import PSFModel, check_pixel_size, check_shape

__all__ = [
    "SCENES",
    "TRUTH_COLUMNS",
    "SimulatedMovie",
    "Simulation",
    "bead_scan_truth",
    "cluster_scene",
    "filament_scene",
    "render_movie",
    "simulate",
    "uniform_scene",
    "write_simulation",
]

#: Fraction of an emitter's energy (within 8 um) that its simulation patch holds.
PATCH_FRACTION = 0.995

log = logging.getLogger(__name__)

#: Scene names accepted by :func:`simulate` (the plurals "clusters" and "filaments" also work).
SCENES: tuple[str, ...] = ("uniform", "cluster", "filament")
_SCENE_ALIASES = {"clusters": "cluster", "filaments": "filament"}

PhotonSpec = float | tuple[float, float]

# Emitters rendered per call of ``model.images``: bounds the temporary arrays (~a few MB each).
_RENDER_CHUNK = 64


# -- helpers ---------------------------------------------------------------------------------
def _check_fov(fov_nm: ArrayLike) -> tuple[float, float]:
    try:
        w, h = (float(v) for v in fov_nm)  # type: ignore[union-attr]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"fov_nm must be (width_x, height_y) in nm, got {fov_nm!r}") from exc
    if not (np.isfinite(w) and np.isfinite(h) and w > 0 and h > 0):
        raise ValueError(f"fov_nm must be two positive numbers of nm, got {fov_nm!r}")
    return w, h


def _check_z_range(z_range: ArrayLike) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in z_range)  # type: ignore[union-attr]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"z_range must be (z_min, z_max) in nm, got {z_range!r}") from exc
    if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
        raise ValueError(f"z_range must be (z_min, z_max) with z_min <= z_max, got {z_range!r}")
    return lo, hi


def _check_n_frames(n_frames: int) -> int:
    n = int(n_frames)
    if n != n_frames or n < 1:
        raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
    return n


def _check_photons(photons: PhotonSpec) -> tuple[float, float]:
    """``(lo, hi)`` of a uniform photon draw; a scalar gives ``lo == hi``."""
    if np.ndim(photons) == 0:
        lo = hi = float(photons)  # type: ignore[arg-type]
    else:
        try:
            lo, hi = (float(v) for v in photons)  # type: ignore[union-attr]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"photons must be a number or (lo, hi), got {photons!r}") from exc
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 <= lo <= hi):
        raise ValueError(f"photons must be >= 0 with lo <= hi, got {photons!r}")
    return lo, hi


def _draw_photons(rng: np.random.Generator, photons: PhotonSpec, n: int) -> NDArray[np.float64]:
    lo, hi = _check_photons(photons)
    if lo == hi:
        return np.full(n, lo)
    return rng.uniform(lo, hi, size=n)


def _table(
    frame: ArrayLike,
    x: ArrayLike,
    y: ArrayLike,
    z: ArrayLike,
    photons: ArrayLike,
    emitter_id: ArrayLike | None = None,
) -> pd.DataFrame:
    data: dict[str, Any] = {
        "frame": np.asarray(frame, dtype=np.int64),
        "x_nm": np.asarray(x, dtype=np.float64),
        "y_nm": np.asarray(y, dtype=np.float64),
        "z_nm": np.asarray(z, dtype=np.float64),
        "photons": np.asarray(photons, dtype=np.float64),
    }
    if emitter_id is not None:
        data["emitter_id"] = np.asarray(emitter_id, dtype=np.int64)
    return pd.DataFrame(data)


# -- scenes ----------------------------------------------------------------------------------
def uniform_scene(
    rng: np.random.Generator,
    n_frames: int,
    fov_nm: tuple[float, float],
    density: float,
    z_range: tuple[float, float],
    photons: PhotonSpec = (1000.0, 5000.0),
    margin_nm: float = 0.0,
) -> pd.DataFrame:
    """Emitters scattered uniformly in a slab, independently in every frame.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    n_frames : int
        Number of frames.
    fov_nm : (float, float)
        Field of view ``(width_x, height_y)`` in nm.
    density : float
        Mean number of emitters per um^2 of the area inside the margin, per frame (>= 0).
    z_range : (float, float)
        Axial range ``(z_min, z_max)`` in nm; z is uniform in it.
    photons : float or (float, float)
        Photons per emitter: a fixed value or the bounds of a uniform draw.
    margin_nm : float
        Keep emitters this far (nm) from the edges of the field of view.

    Returns
    -------
    truth : DataFrame
        Columns ``frame, x_nm, y_nm, z_nm, photons``, sorted by frame. The count per frame is
        Poisson with mean ``density * area_um2``.
    """
    n_frames = _check_n_frames(n_frames)
    w, h = _check_fov(fov_nm)
    zlo, zhi = _check_z_range(z_range)
    _check_photons(photons)
    density = float(density)
    if not (np.isfinite(density) and density >= 0):
        raise ValueError(f"density must be >= 0 emitters per um^2, got {density!r}")
    m = float(margin_nm)
    if not (m >= 0 and 2 * m < w and 2 * m < h):
        raise ValueError(f"margin_nm must be >= 0 and less than half the field of view, got {m}")
    area_um2 = (w - 2 * m) * (h - 2 * m) / 1e6
    counts = rng.poisson(density * area_um2, size=n_frames)
    n = int(counts.sum())
    frame = np.repeat(np.arange(n_frames), counts)
    x = rng.uniform(m, w - m, size=n)
    y = rng.uniform(m, h - m, size=n)
    z = rng.uniform(zlo, zhi, size=n)
    ph = _draw_photons(rng, photons, n)
    log.debug("uniform scene: %d emitters in %d frames (%.2f per frame)", n, n_frames, n / n_frames)
    return _table(frame, x, y, z, ph)


def cluster_scene(
    rng: np.random.Generator,
    n_frames: int,
    fov_nm: tuple[float, float],
    k: int,
    box_nm: tuple[float, float, float] = (800.0, 800.0, 600.0),
    z_centre: float = 0.0,
    photons: PhotonSpec = (1000.0, 5000.0),
    z_range: tuple[float, float] | None = None,
) -> pd.DataFrame:
    """``k`` emitters packed into a small box placed at random in every frame.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    n_frames : int
        Number of frames.
    fov_nm : (float, float)
        Field of view ``(width_x, height_y)`` in nm.
    k : int
        Emitters per frame (>= 0).
    box_nm : (float, float, float)
        Box size ``(x, y, z)`` in nm. Its lateral position is uniform such that the box lies fully
        inside the field of view; axially it spans ``z_centre +- box_nm[2] / 2``.
    z_centre : float
        Axial centre of the box in nm.
    photons : float or (float, float)
        Photons per emitter: a fixed value or the bounds of a uniform draw.
    z_range : (float, float), optional
        The model's valid axial range; a ``ValueError`` is raised if the box leaves it.

    Returns
    -------
    truth : DataFrame
        Columns ``frame, x_nm, y_nm, z_nm, photons``; ``k`` rows per frame.
    """
    n_frames = _check_n_frames(n_frames)
    w, h = _check_fov(fov_nm)
    _check_photons(photons)
    k_int = int(k)
    if k_int != k or k_int < 0:
        raise ValueError(f"k must be a non-negative integer, got {k!r}")
    try:
        bx, by, bz = (float(v) for v in box_nm)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"box_nm must be (x, y, z) in nm, got {box_nm!r}") from exc
    if not (0 <= bx <= w and 0 <= by <= h and bz >= 0):
        raise ValueError(
            f"box_nm = {box_nm!r} must be non-negative and fit in the field of view {(w, h)} nm"
        )
    zc = float(z_centre)
    if z_range is not None:
        zlo, zhi = _check_z_range(z_range)
        if zc - bz / 2 < zlo or zc + bz / 2 > zhi:
            raise ValueError(
                f"the cluster box z_centre {zc:g} +- {bz / 2:g} nm leaves the z range "
                f"[{zlo:g}, {zhi:g}] nm"
            )
    x0 = rng.uniform(0.0, w - bx, size=n_frames)
    y0 = rng.uniform(0.0, h - by, size=n_frames)
    frame = np.repeat(np.arange(n_frames), k_int)
    n = frame.size
    x = np.repeat(x0, k_int) + rng.uniform(0.0, bx, size=n)
    y = np.repeat(y0, k_int) + rng.uniform(0.0, by, size=n)
    z = zc + rng.uniform(-bz / 2, bz / 2, size=n)
    ph = _draw_photons(rng, photons, n)
    return _table(frame, x, y, z, ph)


def _smooth_profile(rng: np.random.Generator, s: NDArray[np.float64], n_modes: int, wl: tuple):
    """Sum of ``n_modes`` random sinusoids of s (wavelengths in ``wl`` nm), zero mean, unit peak."""
    out = np.zeros_like(s)
    for _ in range(n_modes):
        lam = rng.uniform(*wl)
        amp = rng.uniform(0.5, 1.0)
        out += amp * np.sin(2 * np.pi * s / lam + rng.uniform(0, 2 * np.pi))
    out -= out.mean()
    peak = np.max(np.abs(out))
    return out / peak if peak > 0 else out


def filament_scene(
    rng: np.random.Generator,
    n_frames: int,
    fov_nm: tuple[float, float],
    n_filaments: int = 3,
    z_range: tuple[float, float] = (-500.0, 500.0),
    labels_per_um: float = 40.0,
    p_on: float = 0.025,
    p_off: float = 0.5,
    photons: PhotonSpec = (1000.0, 5000.0),
    *,
    photon_cv: float = 0.3,
    density: float | None = None,
    bend_nm: float = 600.0,
) -> pd.DataFrame:
    """Blinking fluorophores along smooth random 3D filaments crossing the field of view.

    Each filament is a smooth curve through a random point of the field of view at a random
    angle, bent laterally by a few random long-wavelength sinusoids (amplitude up to ``bend_nm``)
    and with ``z`` varying smoothly inside ``z_range``. Fluorophores sit at uniformly random arc
    positions (Poisson count, ``labels_per_um`` per um of 3D arc length inside the field of
    view). Each one blinks as a two-state Markov chain, started from its stationary distribution:
    every frame an off fluorophore switches on with probability ``p_on`` and an on one switches
    off with probability ``p_off``. The defaults give about one active emitter per um^2 in a
    64 x 64 frame of 100 nm pixels (3 filaments, ~20 um of filament inside the field of view,
    ~800 fluorophores, 4.8 % of them on, ~39 active per frame).

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    n_frames : int
        Number of frames.
    fov_nm : (float, float)
        Field of view ``(width_x, height_y)`` in nm.
    n_filaments : int
        Number of filaments.
    z_range : (float, float)
        Axial range in nm; each filament spans a random part of it.
    labels_per_um : float
        Mean fluorophores per um of filament.
    p_on, p_off : float
        Per-frame switching probabilities off->on and on->off, in [0, 1].
    photons : float or (float, float)
        Brightness of each fluorophore (photons per on-frame): fixed or uniform in (lo, hi).
    photon_cv : float
        Frame-to-frame coefficient of variation of the photons of an on-frame (gamma
        distributed around the fluorophore's brightness); 0 for a constant value.
    density : float, optional
        If given, overrides ``p_on`` so that the mean number of active emitters per frame is
        ``density`` (per um^2) times the field-of-view area (capped by the number of labels).
    bend_nm : float
        Largest lateral deviation (nm) of a filament from a straight line.

    Returns
    -------
    truth : DataFrame
        Columns ``frame, x_nm, y_nm, z_nm, photons, emitter_id`` (the fluorophore index), one row
        per fluorophore per on-frame, sorted by frame then ``emitter_id``.
    """
    n_frames = _check_n_frames(n_frames)
    w, h = _check_fov(fov_nm)
    zlo, zhi = _check_z_range(z_range)
    _check_photons(photons)
    if int(n_filaments) != n_filaments or n_filaments < 0:
        raise ValueError(f"n_filaments must be a non-negative integer, got {n_filaments!r}")
    if not labels_per_um >= 0:
        raise ValueError(f"labels_per_um must be >= 0, got {labels_per_um!r}")
    for name, p in (("p_on", p_on), ("p_off", p_off)):
        if not 0 <= p <= 1:
            raise ValueError(f"{name} must be a probability in [0, 1], got {p!r}")
    if not photon_cv >= 0:
        raise ValueError(f"photon_cv must be >= 0, got {photon_cv!r}")

    # -- geometry: dense samples of each curve ----------------------------------------------
    ds = 5.0  # nm between curve samples
    half_len = 0.5 * np.hypot(w, h) + 2 * bend_nm
    s = np.arange(-half_len, half_len + ds, ds)
    span = zhi - zlo
    xs, ys, zs, arc_fil = [], [], [], []
    for _ in range(int(n_filaments)):
        cx, cy = rng.uniform(0.2 * w, 0.8 * w), rng.uniform(0.2 * h, 0.8 * h)
        theta = rng.uniform(0, np.pi)
        t = np.array([np.cos(theta), np.sin(theta)])
        nrm = np.array([-t[1], t[0]])
        lateral = bend_nm * rng.uniform(0.3, 1.0) * _smooth_profile(rng, s, 3, (3000.0, 12000.0))
        px = cx + s * t[0] + lateral * nrm[0]
        py = cy + s * t[1] + lateral * nrm[1]
        # z: smooth, within a random sub-range of at least half of z_range.
        zspan = span * rng.uniform(0.5, 1.0)
        zmid = rng.uniform(zlo + zspan / 2, zhi - zspan / 2) if span > 0 else zlo
        pz = zmid + 0.5 * zspan * _smooth_profile(rng, s, 2, (4000.0, 16000.0))
        seg = np.sqrt(np.diff(px) ** 2 + np.diff(py) ** 2 + np.diff(pz) ** 2)
        arc = np.concatenate([[0.0], np.cumsum(seg)])  # 3D arc length, nm
        xs.append(px)
        ys.append(py)
        zs.append(pz)
        arc_fil.append(arc)

    # -- labels: uniform along the whole curve, kept where it is inside the field of view ------
    lx, ly, lz = [], [], []
    for px, py, pz, arc in zip(xs, ys, zs, arc_fil, strict=True):
        n_lab = rng.poisson(labels_per_um * arc[-1] / 1000.0)
        pos = np.sort(rng.uniform(0.0, arc[-1], size=n_lab))
        fx, fy = np.interp(pos, arc, px), np.interp(pos, arc, py)
        inside = (fx >= 0) & (fx < w) & (fy >= 0) & (fy < h)
        lx.append(fx[inside])
        ly.append(fy[inside])
        lz.append(np.clip(np.interp(pos, arc, pz)[inside], zlo, zhi))
    if lx:
        lx_a, ly_a, lz_a = np.concatenate(lx), np.concatenate(ly), np.concatenate(lz)
    else:
        lx_a = ly_a = lz_a = np.empty(0)
    n_lab = lx_a.size
    brightness = _draw_photons(rng, photons, n_lab)

    if density is not None:
        target = float(density) * w * h / 1e6
        if not (np.isfinite(target) and target >= 0):
            raise ValueError(f"density must be >= 0 emitters per um^2, got {density!r}")
        if n_lab == 0 or target <= 0:
            p_on = 0.0
        else:
            frac = min(target / n_lab, 0.999)
            # stationary on-fraction p_on / (p_on + p_off) = frac
            p_on = min(1.0, frac * p_off / (1.0 - frac)) if p_off > 0 else 1.0
        log.debug("filament scene: p_on = %.4g for %.3g active emitters per frame", p_on, target)

    # -- blinking: two-state Markov chain per fluorophore ----------------------------------
    p_stat = p_on / (p_on + p_off) if (p_on + p_off) > 0 else 0.0
    state = rng.random(n_lab) < p_stat
    frames_l, ids_l = [], []
    ids = np.arange(n_lab)
    for f in range(n_frames):
        if f > 0:
            u = rng.random(n_lab)
            state = np.where(state, u >= p_off, u < p_on)
        on = ids[state]
        frames_l.append(np.full(on.size, f, dtype=np.int64))
        ids_l.append(on)
    frame = np.concatenate(frames_l) if frames_l else np.empty(0, np.int64)
    eid = np.concatenate(ids_l) if ids_l else np.empty(0, np.int64)
    level = brightness[eid]
    if photon_cv > 0 and eid.size:
        shape = 1.0 / photon_cv**2
        ph = rng.gamma(shape, level / shape)
    else:
        ph = level.copy()
    log.debug(
        "filament scene: %d fluorophores, %d emitter-frames (%.2f per frame)",
        n_lab,
        eid.size,
        eid.size / n_frames,
    )
    return _table(frame, lx_a[eid], ly_a[eid], lz_a[eid], ph, eid)


# -- rendering -------------------------------------------------------------------------------
def bead_scan_truth(
    positions_nm: ArrayLike,
    z_planes: ArrayLike,
    photons: float = 20000.0,
    z_offsets: ArrayLike | None = None,
) -> pd.DataFrame:
    """Truth table of a bead z-scan: every bead in every frame, at z = plane + its offset.

    Parameters
    ----------
    positions_nm : array_like, shape (B, 2)
        Bead positions (x, y) in nm, native coordinates.
    z_planes : array_like, shape (Nz,)
        Focus position of each frame (nm): the emitter's z in frame k is ``z_planes[k]``
        plus the bead's offset.
    photons : float
        Photons per bead per frame.
    z_offsets : array_like, shape (B,), optional
        Each bead's height (nm) relative to the others (beads on a tilted coverslip).

    Returns
    -------
    DataFrame
        Columns ``frame, x_nm, y_nm, z_nm, photons`` (use with ``simulate(scene=...)``).
    """
    pos = np.asarray(positions_nm, dtype=np.float64).reshape(-1, 2)
    zp = np.asarray(z_planes, dtype=np.float64).ravel()
    dz = np.zeros(len(pos)) if z_offsets is None else np.asarray(z_offsets, float).ravel()
    if dz.size != len(pos):
        raise ValueError(f"z_offsets has {dz.size} values for {len(pos)} beads")
    nz, nb = zp.size, len(pos)
    return pd.DataFrame(
        {
            "frame": np.repeat(np.arange(nz), nb),
            "x_nm": np.tile(pos[:, 0], nz),
            "y_nm": np.tile(pos[:, 1], nz),
            "z_nm": (zp[:, None] + dz[None, :]).ravel(),
            "photons": np.full(nz * nb, float(photons)),
        }
    )


def _background_array(
    background: float | ArrayLike, n_frames: int, shape: tuple[int, int]
) -> NDArray[np.float64]:
    bg = np.asarray(background, dtype=np.float64)
    if bg.ndim not in (0, 2, 3):
        raise ValueError(
            "background must be a scalar, a (rows, cols) map or a (frames, rows, cols) array of "
            f"photons per pixel, got shape {bg.shape}"
        )
    try:
        out = np.array(np.broadcast_to(bg, (n_frames, *shape)), dtype=np.float64)
    except ValueError as exc:
        raise ValueError(
            f"background of shape {bg.shape} does not match the movie ({n_frames}, {shape[0]}, "
            f"{shape[1]})"
        ) from exc
    if not np.all(np.isfinite(out)) or np.any(out < 0):
        raise ValueError("background must be finite and >= 0 photons per pixel")
    return out


def render_movie(
    model: PSFModel,
    truth: pd.DataFrame,
    n_frames: int,
    shape: tuple[int, int],
    pixel_size: float,
    background: float | ArrayLike = 10.0,
    *,
    radius_nm: float | None = None,
    progress: bool = False,
) -> NDArray[np.float64]:
    """Noise-free movie: background plus the image of every emitter of the truth table.

    Each emitter is rendered in a square patch centred on its pixel, reaching at least
    ``radius_nm`` (default ``model.support_radius(pixel_size, PATCH_FRACTION)``) from it on every
    side, placed
    exactly with the model's
    ``origin`` argument and clipped to the frame (emitters near or outside the edges contribute
    only what falls inside). Emitters whose clipped patches coincide (same origin and shape, in
    any frame) are rendered in one batched ``model.images`` call.

    Parameters
    ----------
    model : PSFModel
        PSF model; every emitter's z must lie in ``model.z_range``.
    truth : DataFrame
        Truth table (columns ``frame, x_nm, y_nm, z_nm, photons``); frames in ``[0, n_frames)``.
    n_frames : int
        Number of frames of the movie.
    shape : (int, int)
        Frame shape ``(rows, cols)``.
    pixel_size : float
        Pixel size in nm.
    background : float or array_like
        Background in photons per pixel: a scalar, a ``(rows, cols)`` map or ``(frames, rows,
        cols)``.
    radius_nm : float, optional
        Patch half-width in nm; default
        ``model.support_radius(pixel_size, PATCH_FRACTION)``. Photons of an
        emitter's image beyond it are not rendered (a few per cent for a hard-edged pupil's
        halo), so pass a larger radius when photon totals must be exact.
    progress : bool
        Show a tqdm progress bar (only when stderr is a terminal).

    Returns
    -------
    expected : ndarray of float64, shape (frames, rows, cols)
        Expected photons per pixel.
    """
    n_frames = _check_n_frames(n_frames)
    rows, cols = check_shape(shape)
    px = check_pixel_size(pixel_size)
    truth = check_truth_table(truth)
    movie = _background_array(background, n_frames, (rows, cols))
    if len(truth) == 0:
        return movie

    frame = truth["frame"].to_numpy()
    if not np.all(np.isfinite(frame)) or np.any(frame != np.round(frame)):
        raise ValueError("truth column 'frame' must hold integers")
    frame = frame.astype(np.int64)
    if frame.min() < 0 or frame.max() >= n_frames:
        raise ValueError(
            f"truth frames must lie in [0, {n_frames - 1}], got {frame.min()}..{frame.max()}"
        )
    x = truth["x_nm"].to_numpy(dtype=np.float64)
    y = truth["y_nm"].to_numpy(dtype=np.float64)
    z = truth["z_nm"].to_numpy(dtype=np.float64)
    ph = truth["photons"].to_numpy(dtype=np.float64)
    for name, arr in (("x_nm", x), ("y_nm", y), ("z_nm", z), ("photons", ph)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"truth column {name!r} must be finite (no NaN or inf)")
    if np.any(ph < 0):
        raise ValueError("truth column 'photons' must be >= 0")
    zlo, zhi = model.z_range
    bad = (z < zlo) | (z > zhi)
    if np.any(bad):
        raise ValueError(
            f"truth z = {z[bad][0]:.1f} nm is outside the model's range [{zlo:g}, {zhi:g}] nm"
        )

    # 99.5 % of the energy within 8 um: a tighter patch cuts the PSF's tails and a fit with the
    # same model then sees a mismatch (a cut 3800-photon emitter was fitted as two)
    radius = model.support_radius(px, PATCH_FRACTION) if radius_nm is None else float(radius_nm)
    if not (np.isfinite(radius) and radius >= 0):
        raise ValueError(f"radius_nm must be a non-negative number of nm, got {radius_nm!r}")
    half = int(np.ceil(radius / px))
    ci = np.floor(x / px).astype(np.int64)
    ri = np.floor(y / px).astype(np.int64)
    c0 = np.clip(ci - half, 0, cols)
    c1 = np.clip(ci + half + 1, 0, cols)
    r0 = np.clip(ri - half, 0, rows)
    r1 = np.clip(ri + half + 1, 0, rows)
    keep = (c1 > c0) & (r1 > r0) & (ph > 0)
    idx = np.flatnonzero(keep)
    if idx.size < len(truth):
        log.debug(
            "render_movie: %d emitters contribute nothing to the frame", len(truth) - idx.size
        )
    # Group emitters by their clipped patch (r0, r1, c0, c1).
    keys = np.stack([r0[idx], r1[idx], c0[idx], c1[idx]], axis=1)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(uniq) + 1))
    log.info(
        "rendering %d emitters in %d frames (%d x %d px, patch half-width %d px, %d patch groups)",
        idx.size,
        n_frames,
        rows,
        cols,
        half,
        len(uniq),
    )
    disable = (not progress) or not sys.stderr.isatty()
    with tqdm(total=int(idx.size), desc="render", unit="emitter", disable=disable) as bar:
        for g, (a0, a1, b0, b1) in enumerate(uniq):
            members = idx[order[bounds[g] : bounds[g + 1]]]
            view = movie[:, a0:a1, b0:b1]
            origin = (float(b0) * px, float(a0) * px)
            for s in range(0, members.size, _RENDER_CHUNK):
                sel = members[s : s + _RENDER_CHUNK]
                imgs = model.images(
                    x[sel], y[sel], z[sel], (int(a1 - a0), int(b1 - b0)), px, origin=origin
                )
                np.add.at(view, frame[sel], imgs * ph[sel, None, None])
                bar.update(sel.size)
    return movie


# -- high level ------------------------------------------------------------------------------
@dataclass(eq=False)
class Simulation:
    """A simulated movie with its ground truth.

    Attributes
    ----------
    movie : ndarray of uint16, shape (frames, rows, cols)
        Noisy camera counts in ADU.
    expected : ndarray of float64, shape (frames, rows, cols)
        Expected photons per pixel (background included, before camera noise).
    truth : DataFrame
        Ground truth (``frame, x_nm, y_nm, z_nm, photons`` [, ``emitter_id``]).
    camera : Camera
        Camera used to make ``movie``.
    pixel_size : float
        Pixel size in nm.
    params : dict
        Parameters of the simulation (scene, seed, ...), for provenance.
    """

    movie: NDArray[np.uint16]
    expected: NDArray[np.float64]
    truth: pd.DataFrame
    camera: Camera
    pixel_size: float
    params: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        """Number of frames."""
        return int(self.movie.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        """Frame shape ``(rows, cols)``."""
        return int(self.movie.shape[1]), int(self.movie.shape[2])


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return f"array{value.shape}"
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return repr(value)


def simulate(
    model: PSFModel,
    *,
    scene: str | pd.DataFrame = "uniform",
    n_frames: int = 10,
    shape: tuple[int, int] = (64, 64),
    pixel_size: float = 100.0,
    density: float = 1.0,
    z_range: tuple[float, float] | None = None,
    photons: PhotonSpec = (1000.0, 5000.0),
    background: float | ArrayLike = 10.0,
    camera: Camera | None = None,
    seed: int = 0,
    progress: bool = False,
    patch_radius_nm: float | None = None,
    **scene_kwargs: Any,
) -> Simulation:
    """Simulate a noisy SMLM movie and its ground truth.

    Parameters
    ----------
    model : PSFModel
        PSF model used to render emitters.
    scene : {"uniform", "cluster", "filament"} or DataFrame
        Scene generator (:func:`uniform_scene`, :func:`cluster_scene`, :func:`filament_scene`),
        or a ready truth table to render as it is.
    n_frames : int
        Number of frames.
    shape : (int, int)
        Frame shape ``(rows, cols)``; the field of view is ``(cols * pixel_size, rows *
        pixel_size)`` nm.
    pixel_size : float
        Pixel size in nm.
    density : float
        Emitters per um^2 per frame: the mean of ``"uniform"``; the mean active density of
        ``"filament"`` (unless ``p_on`` is given); unused by ``"cluster"`` (use ``k``).
    z_range : (float, float), optional
        Axial range of the scene in nm; default ``model.z_range``.
    photons : float or (float, float)
        Photons per emitter per frame: fixed, or uniform in ``(lo, hi)``.
    background : float or array_like
        Background in photons per pixel (scalar, ``(rows, cols)`` or ``(frames, rows, cols)``).
    camera : Camera, optional
        Camera model; default ``Camera()`` (ideal, Poisson only, offset 100 ADU, gain 1).
    seed : int
        Seed; the same seed gives identical bytes.
    progress : bool
        Show a progress bar while rendering (only on a terminal).
    patch_radius_nm : float, optional
        Half-width (nm) of each emitter's rendered patch; default
        ``model.support_radius(pixel_size, PATCH_FRACTION)`` (see :func:`render_movie`).
    **scene_kwargs
        Passed to the scene generator (e.g. ``margin_nm``, ``k``, ``box_nm``, ``z_centre``,
        ``n_filaments``, ``labels_per_um``, ``p_on``, ``p_off``, ``photon_cv``).

    Returns
    -------
    Simulation
        Movie (uint16 ADU), expected photons, truth table, camera and parameters.
    """
    camera = Camera() if camera is None else camera
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
    n_frames = _check_n_frames(n_frames)
    rows, cols = check_shape(shape)
    px = check_pixel_size(pixel_size)
    zr = _check_z_range(model.z_range if z_range is None else z_range)
    fov = (cols * px, rows * px)
    # Independent streams for the scene and the camera noise.
    scene_ss, noise_ss = np.random.SeedSequence(seed).spawn(2)
    scene_rng = np.random.default_rng(scene_ss)
    noise_rng = np.random.default_rng(noise_ss)

    if isinstance(scene, pd.DataFrame):
        if scene_kwargs:
            raise ValueError("scene_kwargs are not used when scene is a truth table")
        truth = check_truth_table(scene)
        scene_name = "table"
    else:
        scene_name = _SCENE_ALIASES.get(scene, scene) if isinstance(scene, str) else scene
        kw = dict(scene_kwargs)
        if scene_name == "uniform":
            truth = uniform_scene(scene_rng, n_frames, fov, density, zr, photons, **kw)
        elif scene_name == "cluster":
            kw.setdefault("k", 5)
            kw.setdefault("box_nm", (800.0, 800.0, min(600.0, zr[1] - zr[0])))
            kw.setdefault("z_centre", 0.5 * (zr[0] + zr[1]))
            kw.setdefault("z_range", zr)
            truth = cluster_scene(scene_rng, n_frames, fov, photons=photons, **kw)
        elif scene_name == "filament":
            if "p_on" not in kw:
                kw.setdefault("density", density)
            truth = filament_scene(scene_rng, n_frames, fov, z_range=zr, photons=photons, **kw)
        else:
            allowed = ", ".join(repr(s) for s in SCENES)
            raise ValueError(f"scene must be one of {allowed} or a truth DataFrame, got {scene!r}")

    expected = render_movie(
        model,
        truth,
        n_frames,
        (rows, cols),
        px,
        background,
        radius_nm=patch_radius_nm,
        progress=progress,
    )
    movie = apply_noise(expected, camera, noise_rng)
    params = {
        "scene": scene_name,
        "n_frames": n_frames,
        "shape": [rows, cols],
        "pixel_size": px,
        "density": float(density),
        "z_range": list(zr),
        "photons": _jsonable(photons),
        "background": _jsonable(background),
        "seed": _jsonable(seed),
        "model": repr(model),
        "camera": camera.to_dict(),
        "patch_radius_nm": patch_radius_nm,
        "scene_kwargs": _jsonable(scene_kwargs),
    }
    log.info(
        "simulated %d frames of %d x %d px with %d emitters (scene %s, seed %s)",
        n_frames,
        rows,
        cols,
        len(truth),
        scene_name,
        seed,
    )
    return Simulation(movie, expected, truth.reset_index(drop=True), camera, px, params)


def write_simulation(sim: Simulation, path_tif: str | Path) -> tuple[Path, Path]:
    """Write a simulation as ``OUT.tif`` (uint16 movie) and ``OUT_truth.csv``.

    Parameters
    ----------
    sim : Simulation
        The simulation.
    path_tif : str or Path
        Movie path ending in ``.tif`` or ``.tiff``; its folder must exist.

    Returns
    -------
    (tif_path, truth_path) : (Path, Path)
        Paths written. Both files are written atomically.
    """
    from .io.tiff import write_tiff
    from .io.truth import write_truth_csv

    p = Path(path_tif)
    if p.suffix.lower() not in (".tif", ".tiff"):
        raise ValueError(f"the movie path must end with .tif or .tiff, got {str(p)!r}")
    truth_path = p.with_name(p.stem + "_truth.csv")
    check_truth_table(sim.truth)  # fail before writing anything
    meta = {"sparseloc_" + k: v for k, v in sim.params.items() if k in ("scene", "seed")}
    meta["camera_offset_adu"] = sim.camera.offset
    meta["camera_gain_e_per_adu"] = sim.camera.gain
    meta["camera_em_gain"] = sim.camera.em_gain
    meta["camera_qe"] = sim.camera.qe
    write_tiff(p, sim.movie, pixel_size=sim.pixel_size, metadata=meta)
    write_truth_csv(truth_path, sim.truth)
    log.info("wrote %s and %s", p, truth_path)
    return p, truth_path


class SimulatedMovie:
    """A long uniform-scene movie made frame by frame on demand, never stored.

    Frame ``f`` holds emitters drawn by :func:`uniform_scene` from a generator seeded with
    ``(seed, f)``, rendered and given Poisson noise from the same generator, so every frame is
    the same whichever frames are asked for together and in whichever process: a worker can
    make its own chunk of a 20,000-frame movie. Frames are in photons (no camera), so the
    object can be given straight to :func:`sparseloc.pipeline.localize` or
    :func:`sparseloc.distributed.localize_chunked`.

    Parameters
    ----------
    model : PSFModel
        PSF model (z of the emitters: ``z_range`` or the model's range).
    n_frames : int
    shape : (int, int)
        Frame shape (rows, cols).
    pixel_size : float
        nm.
    density : float
        Emitters per um^2 per frame.
    photons : float or (float, float)
    background : float
        Photons per pixel.
    z_range : (float, float), optional
    seed : int
    """

    def __init__(
        self,
        model: PSFModel,
        n_frames: int,
        shape: tuple[int, int],
        pixel_size: float,
        *,
        density: float = 0.5,
        photons: PhotonSpec = (1000.0, 5000.0),
        background: float = 10.0,
        z_range: tuple[float, float] | None = None,
        seed: int = 0,
    ) -> None:
        self.model = model
        self.n_frames = _check_n_frames(n_frames)
        self.shape = (int(shape[0]), int(shape[1]))
        self.pixel_size = float(pixel_size)
        self.density = float(density)
        self.photons = photons
        self.background = float(background)
        self.z_range = tuple(model.z_range if z_range is None else z_range)
        self.seed = int(seed)

    def __len__(self) -> int:
        return self.n_frames

    def identity(self) -> dict:
        """What makes the movie (for resuming runs): its parameters and the model's images."""
        from .pipeline import psf_hash

        return {
            "simulated": {
                "psf_hash": psf_hash(self.model, self.pixel_size),
                "n_frames": self.n_frames,
                "shape": list(self.shape),
                "pixel_size": self.pixel_size,
                "density": self.density,
                "photons": np.atleast_1d(np.asarray(self.photons, dtype=float)).tolist(),
                "background": self.background,
                "z_range": [float(v) for v in self.z_range],
                "seed": self.seed,
            }
        }

    def truth(self, start: int = 0, stop: int | None = None) -> pd.DataFrame:
        """Ground truth of frames ``start..stop-1`` (columns frame, x_nm, y_nm, z_nm, photons)."""
        stop = self.n_frames if stop is None else stop
        return self.truth_of(range(start, stop))

    def truth_of(self, frames: Any) -> pd.DataFrame:
        """Ground truth of the frames listed (0-based indices)."""
        parts = []
        for f in frames:
            f = int(f)
            t = self._scene(f)[0]
            t["frame"] = f
            parts.append(t)
        return pd.concat(parts, ignore_index=True)

    def frames(self, start: int, stop: int) -> NDArray[np.float64]:
        """Noisy frames ``start..stop-1`` in photons, shape (stop - start, rows, cols)."""
        if not 0 <= start <= stop <= self.n_frames:
            raise ValueError(f"frames {start}:{stop} outside 0:{self.n_frames}")
        out = np.empty((stop - start, *self.shape))
        for i, f in enumerate(range(start, stop)):
            out[i] = self._frame(f)[1]
        return out

    def _scene(self, f: int) -> tuple[pd.DataFrame, np.random.Generator]:
        rng = np.random.default_rng([self.seed, f])
        fov = (self.shape[1] * self.pixel_size, self.shape[0] * self.pixel_size)
        t = uniform_scene(rng, 1, fov, self.density, self.z_range, self.photons)
        return t, rng

    def _frame(self, f: int) -> tuple[pd.DataFrame, NDArray[np.float64]]:
        t, rng = self._scene(f)
        mu = render_movie(self.model, t, 1, self.shape, self.pixel_size, self.background)[0]
        t["frame"] = f
        return t, rng.poisson(mu).astype(np.float64)
