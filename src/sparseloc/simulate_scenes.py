"""Ground-truth scenes: emitters scattered uniformly, packed in clusters, or blinking along
filaments, and the truth table of a bead z-scan.

Truth tables are :class:`pandas.DataFrame` objects with one row per emitter per frame and the
columns ``frame`` (int, 0-based), ``x_nm``, ``y_nm``, ``z_nm``, ``photons`` (float) and optionally
``emitter_id`` (int; the same fluorophore across its blinks), in native coordinates (see
:mod:`sparseloc.simulate`). Every generator draws from a :class:`numpy.random.Generator`, so a
seed fixes the result. :mod:`sparseloc.simulate` re-exports all public names.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from .psf.base import parse_pair

__all__ = [
    "PhotonSpec",
    "bead_scan_truth",
    "check_n_frames",
    "check_z_range",
    "cluster_scene",
    "filament_scene",
    "uniform_scene",
]

# The scenes log as part of the simulator.
log = logging.getLogger("sparseloc.simulate")

PhotonSpec = float | tuple[float, float]


# -- helpers ---------------------------------------------------------------------------------
def _check_fov(fov_nm: ArrayLike) -> tuple[float, float]:
    w, h = parse_pair(fov_nm, float, f"fov_nm must be (width_x, height_y) in nm, got {fov_nm!r}")
    if not (np.isfinite(w) and np.isfinite(h) and w > 0 and h > 0):
        raise ValueError(f"fov_nm must be two positive numbers of nm, got {fov_nm!r}")
    return w, h


def check_z_range(z_range: ArrayLike) -> tuple[float, float]:
    lo, hi = parse_pair(z_range, float, f"z_range must be (z_min, z_max) in nm, got {z_range!r}")
    if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
        raise ValueError(f"z_range must be (z_min, z_max) with z_min <= z_max, got {z_range!r}")
    return lo, hi


def check_n_frames(n_frames: int) -> int:
    n = int(n_frames)
    if n != n_frames or n < 1:
        raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
    return n


def _check_photons(photons: PhotonSpec) -> tuple[float, float]:
    """``(lo, hi)`` of a uniform photon draw; a scalar gives ``lo == hi``."""
    if np.ndim(photons) == 0:
        lo = hi = float(photons)  # type: ignore[arg-type]
    else:
        error = f"photons must be a number or (lo, hi), got {photons!r}"
        lo, hi = parse_pair(photons, float, error)
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 <= lo <= hi):
        raise ValueError(f"photons must be >= 0 with lo <= hi, got {photons!r}")
    return lo, hi


def _check_scene(
    n_frames: int,
    fov_nm: ArrayLike,
    photons: PhotonSpec,
    z_range: ArrayLike | None = None,
) -> tuple[int, float, float, tuple[float, float] | None]:
    """The arguments every scene takes, checked in this order: ``(n_frames, w, h, z_range)``."""
    n = check_n_frames(n_frames)
    w, h = _check_fov(fov_nm)
    zr = None if z_range is None else check_z_range(z_range)
    _check_photons(photons)
    return n, w, h, zr


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
    n_frames, w, h, (zlo, zhi) = _check_scene(n_frames, fov_nm, photons, z_range)
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
    n_frames, w, h, _ = _check_scene(n_frames, fov_nm, photons)
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
        zlo, zhi = check_z_range(z_range)
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
    64 x 64 frame of 100 nm pixels.

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
    n_frames, w, h, zr = _check_scene(n_frames, fov_nm, photons, z_range)
    _check_filament_args(n_filaments, labels_per_um, p_on, p_off, photon_cv)
    curves = _filament_curves(rng, int(n_filaments), w, h, zr, bend_nm)
    lx, ly, lz = _filament_labels(rng, curves, labels_per_um, w, h, zr)
    n_lab = lx.size
    brightness = _draw_photons(rng, photons, n_lab)
    if density is not None:
        p_on = _p_on_for_density(density, w, h, n_lab, p_on, p_off)
    frame, eid = _blink(rng, n_lab, n_frames, p_on, p_off)
    ph = _on_frame_photons(rng, brightness[eid], photon_cv)
    log.debug(
        "filament scene: %d fluorophores, %d emitter-frames (%.2f per frame)",
        n_lab,
        eid.size,
        eid.size / n_frames,
    )
    return _table(frame, lx[eid], ly[eid], lz[eid], ph, eid)


def _check_filament_args(
    n_filaments: int, labels_per_um: float, p_on: float, p_off: float, photon_cv: float
) -> None:
    if int(n_filaments) != n_filaments or n_filaments < 0:
        raise ValueError(f"n_filaments must be a non-negative integer, got {n_filaments!r}")
    if not labels_per_um >= 0:
        raise ValueError(f"labels_per_um must be >= 0, got {labels_per_um!r}")
    for name, p in (("p_on", p_on), ("p_off", p_off)):
        if not 0 <= p <= 1:
            raise ValueError(f"{name} must be a probability in [0, 1], got {p!r}")
    if not photon_cv >= 0:
        raise ValueError(f"photon_cv must be >= 0, got {photon_cv!r}")


Curve = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


def _filament_curves(
    rng: np.random.Generator,
    n_filaments: int,
    w: float,
    h: float,
    z_range: tuple[float, float],
    bend_nm: float,
) -> list[Curve]:
    """Dense samples ``(x, y, z, arc length)`` (nm) of each filament's curve."""
    zlo, zhi = z_range
    ds = 5.0  # nm between curve samples
    half_len = 0.5 * np.hypot(w, h) + 2 * bend_nm
    s = np.arange(-half_len, half_len + ds, ds)
    span = zhi - zlo
    curves = []
    for _ in range(n_filaments):
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
        curves.append((px, py, pz, arc))
    return curves


def _filament_labels(
    rng: np.random.Generator,
    curves: list[Curve],
    labels_per_um: float,
    w: float,
    h: float,
    z_range: tuple[float, float],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Fluorophore positions (nm): uniform along each whole curve, kept inside the field of view."""
    zlo, zhi = z_range
    lx, ly, lz = [], [], []
    for px, py, pz, arc in curves:
        n_lab = rng.poisson(labels_per_um * arc[-1] / 1000.0)
        pos = np.sort(rng.uniform(0.0, arc[-1], size=n_lab))
        fx, fy = np.interp(pos, arc, px), np.interp(pos, arc, py)
        inside = (fx >= 0) & (fx < w) & (fy >= 0) & (fy < h)
        lx.append(fx[inside])
        ly.append(fy[inside])
        lz.append(np.clip(np.interp(pos, arc, pz)[inside], zlo, zhi))
    if not lx:
        empty = np.empty(0)
        return empty, empty, empty
    return np.concatenate(lx), np.concatenate(ly), np.concatenate(lz)


def _p_on_for_density(
    density: float, w: float, h: float, n_lab: int, p_on: float, p_off: float
) -> float:
    """The switch-on probability whose stationary on-fraction gives ``density`` (per um^2) in
    the ``w x h`` nm field of view."""
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
    return p_on


def _blink(
    rng: np.random.Generator, n_lab: int, n_frames: int, p_on: float, p_off: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Two-state Markov chain per fluorophore, started from its stationary distribution.

    Returns the frame and the fluorophore index of every on-frame, sorted by frame.
    """
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
    return frame, eid


def _on_frame_photons(
    rng: np.random.Generator, level: NDArray[np.float64], photon_cv: float
) -> NDArray[np.float64]:
    """Photons of each on-frame: gamma distributed around ``level`` with CV ``photon_cv``."""
    if photon_cv > 0 and level.size:
        shape = 1.0 / photon_cv**2
        return rng.gamma(shape, level / shape)
    return level.copy()


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
