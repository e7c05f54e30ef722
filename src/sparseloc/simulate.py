"""Noise-free rendering and noisy camera movies of ground-truth scenes.

Truth tables are :class:`pandas.DataFrame` objects with one row per emitter per frame and the
columns ``frame`` (int, 0-based), ``x_nm``, ``y_nm``, ``z_nm``, ``photons`` (float) and optionally
``emitter_id`` (int; the same fluorophore across its blinks). Coordinates are native (design.md):
the outer corner of pixel (0, 0) is the origin, ``x`` runs along columns, ``y`` along rows, so the
field of view of a ``(rows, cols)`` frame with pixel size ``p`` is ``[0, cols*p] x [0, rows*p]``.

The scene generators live in :mod:`sparseloc.simulate_scenes` and are re-exported here. Every
generator draws from a :class:`numpy.random.Generator`, so a seed fixes the result.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from tqdm import tqdm

from .camera import Camera, apply_noise, check_camera
from .io.truth import TRUTH_COLUMNS, check_truth_table
from .psf.base import PSFModel, check_pixel_size, check_shape
from .simulate_scenes import (
    PhotonSpec,
    bead_scan_truth,
    check_n_frames,
    check_z_range,
    cluster_scene,
    filament_scene,
    uniform_scene,
)

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
    "truth_path_for",
    "uniform_scene",
    "write_simulation",
]

#: Fraction of an emitter's energy (within 8 um) that its simulation patch holds.
PATCH_FRACTION = 0.995

log = logging.getLogger(__name__)

#: Scene names accepted by :func:`simulate` (the plurals "clusters" and "filaments" also work).
SCENES: tuple[str, ...] = ("uniform", "cluster", "filament")
_SCENE_ALIASES = {"clusters": "cluster", "filaments": "filament"}

# Emitters rendered per call of ``model.images``: bounds the temporary arrays (~a few MB each).
_RENDER_CHUNK = 64


# -- rendering -------------------------------------------------------------------------------
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
    side, placed exactly with the model's ``origin`` argument and clipped to the frame (emitters
    near or outside the edges contribute only what falls inside). Emitters whose clipped patches
    coincide (same origin and shape, in any frame) are rendered in one batched ``model.images``
    call.

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
        Patch half-width in nm; default ``model.support_radius(pixel_size, PATCH_FRACTION)``.
        Photons of an emitter's image beyond it are not rendered (a few per cent for a
        hard-edged pupil's halo), so pass a larger radius when photon totals must be exact.
    progress : bool
        Show a tqdm progress bar (only when stderr is a terminal).

    Returns
    -------
    expected : ndarray of float64, shape (frames, rows, cols)
        Expected photons per pixel.
    """
    n_frames = check_n_frames(n_frames)
    rows, cols = check_shape(shape)
    px = check_pixel_size(pixel_size)
    truth = check_truth_table(truth)
    movie = _background_array(background, n_frames, (rows, cols))
    if len(truth) == 0:
        return movie
    frame, x, y, z, ph = _truth_arrays(truth, n_frames, model.z_range)
    # 99.5 % of the energy within 8 um: a tighter patch cuts the PSF's tails, and a fit with the
    # same model then sees a mismatch.
    radius = model.support_radius(px, PATCH_FRACTION) if radius_nm is None else float(radius_nm)
    if not (np.isfinite(radius) and radius >= 0):
        raise ValueError(f"radius_nm must be a non-negative number of nm, got {radius_nm!r}")
    half = int(np.ceil(radius / px))
    idx, groups = _patch_groups(x, y, ph, px, half, (rows, cols))
    log.info(
        "rendering %d emitters in %d frames (%d x %d px, patch half-width %d px, %d patch groups)",
        idx.size,
        n_frames,
        rows,
        cols,
        half,
        len(groups),
    )
    disable = (not progress) or not sys.stderr.isatty()
    with tqdm(total=int(idx.size), desc="render", unit="emitter", disable=disable) as bar:
        for patch, members in groups:
            _add_patch(movie, model, patch, members, (frame, x, y, z, ph), px, bar)
    return movie


def _add_patch(
    movie: NDArray[np.float64],
    model: PSFModel,
    patch: NDArray[np.int64],
    members: NDArray[np.intp],
    emitters: tuple[NDArray, ...],
    px: float,
    bar: tqdm,
) -> None:
    """Add the images of the emitters ``members`` (of ``frame, x, y, z, photons``) that share the
    clipped patch ``(r0, r1, c0, c1)`` to ``movie``, in chunks of :data:`_RENDER_CHUNK`; count
    them on the progress ``bar``."""
    frame, x, y, z, ph = emitters
    a0, a1, b0, b1 = patch
    view = movie[:, a0:a1, b0:b1]
    origin = (float(b0) * px, float(a0) * px)
    for s in range(0, members.size, _RENDER_CHUNK):
        sel = members[s : s + _RENDER_CHUNK]
        imgs = model.images(x[sel], y[sel], z[sel], (int(a1 - a0), int(b1 - b0)), px, origin=origin)
        np.add.at(view, frame[sel], imgs * ph[sel, None, None])
        bar.update(sel.size)


def _truth_arrays(
    truth: pd.DataFrame, n_frames: int, z_range: tuple[float, float]
) -> tuple[NDArray[np.int64], ...]:
    """``frame, x, y, z, photons`` of a truth table, checked against the movie and the model."""
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
    zlo, zhi = z_range
    bad = (z < zlo) | (z > zhi)
    if np.any(bad):
        raise ValueError(
            f"truth z = {z[bad][0]:.1f} nm is outside the model's range [{zlo:g}, {zhi:g}] nm"
        )
    return frame, x, y, z, ph


def _patch_groups(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    ph: NDArray[np.float64],
    px: float,
    half: int,
    shape: tuple[int, int],
) -> tuple[NDArray[np.intp], list[tuple[NDArray[np.int64], NDArray[np.intp]]]]:
    """Each emitter's patch, ``half`` pixels around its pixel, clipped to the frame.

    Returns the emitters that contribute (inside the frame, photons > 0) and their groups by
    clipped patch: ``((r0, r1, c0, c1), member indices)`` per distinct patch, in sorted order.
    """
    rows, cols = shape
    ci = np.floor(x / px).astype(np.int64)
    ri = np.floor(y / px).astype(np.int64)
    c0 = np.clip(ci - half, 0, cols)
    c1 = np.clip(ci + half + 1, 0, cols)
    r0 = np.clip(ri - half, 0, rows)
    r1 = np.clip(ri + half + 1, 0, rows)
    keep = (c1 > c0) & (r1 > r0) & (ph > 0)
    idx = np.flatnonzero(keep)
    if idx.size < x.size:
        log.debug("render_movie: %d emitters contribute nothing to the frame", x.size - idx.size)
    keys = np.stack([r0[idx], r1[idx], c0[idx], c1[idx]], axis=1)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(uniq) + 1))
    groups = [(key, idx[order[bounds[g] : bounds[g + 1]]]) for g, key in enumerate(uniq)]
    return idx, groups


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
    c = _check_simulation(model, camera, n_frames, shape, pixel_size, z_range, seed)
    if not isinstance(scene, pd.DataFrame):
        _check_memory(c, density)
    truth, scene_name = _scene_truth(scene, c, density, photons, scene_kwargs)
    expected = render_movie(
        model,
        truth,
        c.n_frames,
        c.shape,
        c.pixel_size,
        background,
        radius_nm=patch_radius_nm,
        progress=progress,
    )
    movie = apply_noise(expected, c.camera, c.noise_rng)
    params = c.params(
        scene_name, model, density, photons, background, seed, patch_radius_nm, scene_kwargs
    )
    c.log_done(len(truth), scene_name, seed)
    return Simulation(movie, expected, truth.reset_index(drop=True), c.camera, c.pixel_size, params)


class _Checked(NamedTuple):
    """The checked arguments of :func:`simulate` and its two random streams."""

    camera: Camera
    n_frames: int
    shape: tuple[int, int]
    pixel_size: float
    z_range: tuple[float, float]
    scene_rng: np.random.Generator
    noise_rng: np.random.Generator

    @property
    def fov(self) -> tuple[float, float]:
        """Field of view ``(width_x, height_y)`` in nm."""
        rows, cols = self.shape
        return (cols * self.pixel_size, rows * self.pixel_size)

    def params(
        self,
        scene_name: str,
        model: PSFModel,
        density: float,
        photons: PhotonSpec,
        background: float | ArrayLike,
        seed: int,
        patch_radius_nm: float | None,
        scene_kwargs: dict[str, Any],
    ) -> dict[str, Any]:
        """The simulation's parameters as plain JSON values, for provenance."""
        rows, cols = self.shape
        return {
            "scene": scene_name,
            "n_frames": self.n_frames,
            "shape": [rows, cols],
            "pixel_size": self.pixel_size,
            "density": float(density),
            "z_range": list(self.z_range),
            "photons": _jsonable(photons),
            "background": _jsonable(background),
            "seed": _jsonable(seed),
            "model": repr(model),
            "camera": self.camera.to_dict(),
            "patch_radius_nm": patch_radius_nm,
            "scene_kwargs": _jsonable(scene_kwargs),
        }

    def log_done(self, n_emitters: int, scene_name: str, seed: int) -> None:
        rows, cols = self.shape
        log.info(
            "simulated %d frames of %d x %d px with %d emitters (scene %s, seed %s)",
            self.n_frames,
            rows,
            cols,
            n_emitters,
            scene_name,
            seed,
        )


def _check_simulation(
    model: PSFModel,
    camera: Camera | None,
    n_frames: int,
    shape: tuple[int, int],
    pixel_size: float,
    z_range: tuple[float, float] | None,
    seed: int,
) -> _Checked:
    camera = Camera() if camera is None else camera
    check_camera(camera)
    n_frames = check_n_frames(n_frames)
    rows, cols = check_shape(shape)
    px = check_pixel_size(pixel_size)
    zr = check_z_range(model.z_range if z_range is None else z_range)
    # Independent streams for the scene and the camera noise.
    scene_ss, noise_ss = np.random.SeedSequence(seed).spawn(2)
    scene_rng = np.random.default_rng(scene_ss)
    noise_rng = np.random.default_rng(noise_ss)
    return _Checked(camera, n_frames, (rows, cols), px, zr, scene_rng, noise_rng)


#: Bytes a simulation holds per pixel of its movie (the expected photons in float64 and the
#: uint16 movie) and per emitter of its truth table.
_BYTES_PER_PIXEL = 10
_BYTES_PER_EMITTER = 100


def _available_memory() -> int | None:
    """Bytes of memory this machine has free now, or None where the system does not say."""
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def _check_memory(c: _Checked, density: float) -> None:
    """Refuse a simulation that cannot fit in the free memory (the movie is held whole)."""
    rows, cols = c.shape
    pixels = float(c.n_frames) * rows * cols
    area_um2 = c.fov[0] * c.fov[1] * 1e-6
    emitters = max(float(density), 0.0) * area_um2 * c.n_frames
    need = pixels * _BYTES_PER_PIXEL + emitters * _BYTES_PER_EMITTER
    free = _available_memory()
    if free is not None and need > free:
        raise ValueError(
            f"a simulation of {c.n_frames} frame{'s' if c.n_frames != 1 else ''} of "
            f"{rows}x{cols} px with about "
            f"{emitters:.3g} emitters needs about {need / 2**30:.3g} GiB of memory but "
            f"{free / 2**30:.3g} GiB is free; simulate fewer frames or a smaller frame"
        )


def _scene_truth(
    scene: str | pd.DataFrame,
    c: _Checked,
    density: float,
    photons: PhotonSpec,
    scene_kwargs: dict[str, Any],
) -> tuple[pd.DataFrame, str]:
    """The truth table of :func:`simulate`'s ``scene`` and the scene's name for ``params``."""
    if isinstance(scene, pd.DataFrame):
        if scene_kwargs:
            raise ValueError("scene_kwargs are not used when scene is a truth table")
        return check_truth_table(scene), "table"
    rng, n_frames, fov, zr = c.scene_rng, c.n_frames, c.fov, c.z_range
    scene_name = _SCENE_ALIASES.get(scene, scene) if isinstance(scene, str) else scene
    kw = dict(scene_kwargs)
    if scene_name == "uniform":
        truth = uniform_scene(rng, n_frames, fov, density, zr, photons, **kw)
    elif scene_name == "cluster":
        kw.setdefault("k", 5)
        kw.setdefault("box_nm", (800.0, 800.0, min(600.0, zr[1] - zr[0])))
        kw.setdefault("z_centre", 0.5 * (zr[0] + zr[1]))
        kw.setdefault("z_range", zr)
        truth = cluster_scene(rng, n_frames, fov, photons=photons, **kw)
    elif scene_name == "filament":
        if "p_on" not in kw:
            kw.setdefault("density", density)
        truth = filament_scene(rng, n_frames, fov, z_range=zr, photons=photons, **kw)
    else:
        allowed = ", ".join(repr(s) for s in SCENES)
        raise ValueError(f"scene must be one of {allowed} or a truth DataFrame, got {scene!r}")
    return truth, scene_name


def truth_path_for(path_tif: str | Path) -> Path:
    """The ground-truth CSV written beside the movie ``path_tif``: ``OUT_truth.csv``."""
    p = Path(path_tif)
    return p.with_name(p.stem + "_truth.csv")


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
        Paths written. Both files are written to temporary names and renamed only when both
        are complete, so a failure leaves neither (no movie without its truth).
    """
    from .io.atomic import atomic_path
    from .io.table_files import dest_path
    from .io.tiff import write_tiff
    from .io.truth import write_truth_csv

    p = Path(path_tif)
    if p.suffix.lower() not in (".tif", ".tiff"):
        raise ValueError(f"the movie path must end with .tif or .tiff, got {str(p)!r}")
    truth_path = truth_path_for(p)
    for dest in (p, truth_path):
        dest_path(dest)  # a folder in the way is refused before anything is written
    check_truth_table(sim.truth)  # fail before writing anything
    meta = {"sparseloc_" + k: v for k, v in sim.params.items() if k in ("scene", "seed")}
    meta["camera_offset_adu"] = sim.camera.offset
    meta["camera_gain_e_per_adu"] = sim.camera.gain
    meta["camera_em_gain"] = sim.camera.em_gain
    meta["camera_qe"] = sim.camera.qe
    with atomic_path(p) as tmp_tif, atomic_path(truth_path) as tmp_truth:
        write_tiff(tmp_tif, sim.movie, pixel_size=sim.pixel_size, metadata=meta)
        write_truth_csv(tmp_truth, sim.truth)
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
        self.n_frames = check_n_frames(n_frames)
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
        from .digest import psf_hash

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
