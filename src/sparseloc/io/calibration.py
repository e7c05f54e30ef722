"""PSF calibration files (HDF5): write a :class:`~sparseloc.calibrate.Calibration`, read a model.

Layout (all lengths in nm; read with h5py, never pickle)::

    /                 attrs: format="sparseloc-psf", format_version, model ("spline" | "pupil"),
                      name, pixel_size_nm, z_step_nm, z_min_nm, z_max_nm, content_hash,
                      sparseloc_version, created, params (JSON)
    /spline/stack     (Nz, R, C) float64, each plane sums to one photon
    /spline/z         (Nz,) plane positions
                      attrs: centre_row, centre_col (px, pixel-centre coordinates)
    /beads/<column>   one dataset per column of the bead table (reason as UTF-8 strings)
    /pupil            (only when a pupil was fitted) attrs: na, wavelength_nm, n_immersion,
                      z_min_nm, z_max_nm (the calibration's frame), offset_{x,y,z}_nm (the
                      pupil model is read as ``ShiftedPSF(pupil, dx, dy, dz)``: the same
                      coordinate frame as the spline), residual_rms; datasets phase (N, N)
                      radians of the whole pupil phase sampled over the unit disc (centre
                      (N-1)/2, radius (N-1)/2 samples), zernike (M, 3) rows (n, m, waves RMS)

``content_hash`` identifies the model: the spline's data (see
:attr:`sparseloc.psf.spline.SplinePSF.content_hash`) or, for a pupil model, its phase and optics.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import atomic_path

__all__ = [
    "FORMAT",
    "load_calibration",
    "read_calibration_beads",
    "read_calibration_info",
    "save_calibration",
]

FORMAT = "sparseloc-psf"
FORMAT_VERSION = 1
_PHASE_SAMPLES = 129


def _pupil_phase(psf: Any, n: int = _PHASE_SAMPLES) -> np.ndarray:
    c = (n - 1) / 2.0
    yy, xx = np.mgrid[0:n, 0:n]
    kx, ky = (xx - c) / c, (yy - c) / c
    rho = np.hypot(kx, ky)
    phi = np.arctan2(ky, kx)
    inside = rho <= 1.0
    phase = np.zeros((n, n))
    if psf.mask is not None:
        phase[inside] = np.asarray(psf.mask(rho[inside], phi[inside]), dtype=np.float64)
    return phase


def _pupil_hash(phase: np.ndarray, optics: dict[str, float]) -> str:
    h = hashlib.sha256(np.ascontiguousarray(phase, "<f8").tobytes())
    h.update(json.dumps(optics, sort_keys=True).encode())
    return h.hexdigest()[:16]


def save_calibration(cal: Any, path: str | Path, *, model: str = "spline") -> Path:
    """Write a calibration to HDF5 atomically.

    Parameters
    ----------
    cal : Calibration
        From :func:`sparseloc.calibrate.calibrate_beads`.
    path : str or Path
        Output ``.h5`` file; its folder must exist.
    model : {"spline", "pupil"}
        Which model :func:`load_calibration` returns by default (``"pupil"`` needs a fitted
        pupil).
    """
    import h5py

    from .. import __version__

    if model not in ("spline", "pupil"):
        raise ValueError(f"model must be 'spline' or 'pupil', got {model!r}")
    if model == "pupil" and cal.pupil is None:
        raise ValueError("no pupil was fitted; calibrate with the pupil fit to save a pupil model")
    psf = cal.psf
    dest = Path(path)
    with atomic_path(dest) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["model"] = model
        f.attrs["name"] = psf.name
        f.attrs["pixel_size_nm"] = float(psf.pixel_size)
        f.attrs["z_step_nm"] = float(psf.z_step)
        f.attrs["z_min_nm"] = float(psf.z_range[0])
        f.attrs["z_max_nm"] = float(psf.z_range[1])
        f.attrs["sparseloc_version"] = __version__
        f.attrs["created"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        f.attrs["params"] = json.dumps(cal.params, default=str)
        # The beads' departure from the model (relative, per pixel): the solvers' tests add it
        # to the camera's variance.
        f.attrs["model_error"] = float(cal.params.get("model_error", 0.0))
        g = f.create_group("spline")
        g.create_dataset("stack", data=psf.stack, compression="gzip")
        g.create_dataset("z", data=psf.z)
        g.attrs["centre_row"], g.attrs["centre_col"] = psf.centre
        g.attrs["oversample"] = int(getattr(psf, "oversample", 1))
        _write_error_table(f, getattr(psf, "error_table", None))
        b = f.create_group("beads")
        for col in cal.beads.columns:
            values = cal.beads[col].to_numpy()
            if values.dtype == object:
                b.create_dataset(col, data=[str(v) for v in values], dtype=h5py.string_dtype())
            else:
                b.create_dataset(col, data=values)
        content_hash = psf.content_hash
        if cal.pupil is not None:
            pp = cal.pupil.psf
            phase = _pupil_phase(pp)
            optics = {
                "na": float(pp.na),
                "wavelength_nm": float(pp.wavelength),
                "n_immersion": float(pp.n_immersion),
            }
            g = f.create_group("pupil")
            for k, v in optics.items():
                g.attrs[k] = v
            fm = getattr(cal.pupil, "frame_model", None)
            off = fm.offset if fm is not None else (0.0, 0.0, 0.0)
            zr = fm.z_range if fm is not None else pp.z_range
            g.attrs["offset_x_nm"], g.attrs["offset_y_nm"], g.attrs["offset_z_nm"] = off
            g.attrs["z_min_nm"], g.attrs["z_max_nm"] = (float(v) for v in zr)
            g.attrs["residual_rms"] = float(getattr(cal.pupil, "residual_rms", np.nan))
            # the pupil's own error on the beads, where measured (else the spline's serves)
            error = getattr(cal.pupil, "model_error", None)
            if error is not None:
                g.attrs["model_error"] = float(error)
                _write_error_table(g, getattr(cal.pupil, "error_table", None))
            g.create_dataset("phase", data=phase, compression="gzip")
            coefs = getattr(cal.pupil, "coefficients", {}) or {}
            g.create_dataset(
                "zernike",
                data=np.array([[n, m, a] for (n, m), a in sorted(coefs.items())], float).reshape(
                    -1, 3
                ),
            )
            if model == "pupil":
                content_hash = _pupil_hash(phase, optics)
        f.attrs["content_hash"] = content_hash
    return dest


def _write_error_table(group, table) -> None:
    """The model error pixel by pixel (:attr:`sparseloc.calibrate_error.ModelError.table`)
    as ``group``'s "error_table" (nothing for None)."""
    if table is None:
        return
    t = group.create_group("error_table")
    t.create_dataset("stack", data=table.stack, compression="gzip")
    t.create_dataset("z", data=table.z)
    t.attrs["centre_row"], t.attrs["centre_col"] = table.centre


def _open(path: str | Path):
    import h5py

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"calibration file {str(p)!r} does not exist")
    try:
        f = h5py.File(p, "r")
    except Exception as exc:  # h5py raises OSError, RuntimeError, ... for a damaged file
        raise ValueError(f"{p.name} is not a readable HDF5 file ({exc})") from exc
    try:
        fmt = f.attrs.get("format")
    except Exception as exc:  # a damaged attribute table
        f.close()
        raise ValueError(f"{p.name} is a damaged HDF5 file ({type(exc).__name__}: {exc})") from exc
    if fmt != FORMAT:
        f.close()
        raise ValueError(f"{p.name} is not a sparseloc PSF calibration (no format={FORMAT!r})")
    return f


def read_calibration_info(path: str | Path) -> dict[str, Any]:
    """The file's attributes (pixel size, z range, hash, parameters, ...) as a dict."""
    with _open(path) as f:
        info = {k: (v.item() if hasattr(v, "item") else v) for k, v in f.attrs.items()}
        info["params"] = json.loads(info.get("params", "{}"))
        info["has_pupil"] = "pupil" in f
        if "beads" in f:
            info["n_beads_used"] = int(np.sum(f["beads/used"][()])) if "used" in f["beads"] else 0
    return info


def read_calibration_beads(path: str | Path):
    """The bead table stored in a calibration file (one row per bead found: ``x_nm``,
    ``y_nm`` in the bead stack's native coordinates, ``used``, ``reason``, ``photons``, ...;
    see :data:`sparseloc.calibrate.BEAD_COLUMNS`); empty when the file holds none."""
    import pandas as pd

    with _open(path) as f:
        if "beads" not in f:
            return pd.DataFrame({"x_nm": [], "y_nm": [], "used": []})
        g = f["beads"]
        cols = {}
        for k in g:
            v = g[k][()]
            if v.dtype == object:  # h5py returns variable-length strings as bytes
                v = [x.decode() if isinstance(x, bytes) else x for x in v]
            cols[k] = v
        return pd.DataFrame(cols)


def load_calibration(path: str | Path, model: str | None = None):
    """Read the PSF model from a calibration file.

    Parameters
    ----------
    path : str or Path
        A file written by :func:`save_calibration` (``sparseloc calibrate``).
    model : {"spline", "pupil"}, optional
        Which model to build; default the one the file names.

    Returns
    -------
    SplinePSF or ShiftedPSF (a PupilPSF in the calibration's frame)
        With attributes ``pixel_size`` (nm) and ``content_hash``.
    """

    p = Path(path)
    try:
        return _load(p, model)
    except KeyError as exc:
        raise ValueError(f"{p.name} is an incomplete calibration file (missing {exc})") from exc


def _model_error(group) -> float:
    """The model error of the file's or pupil group's model (0 where not measured)."""
    e = float(group.attrs.get("model_error", 0.0))
    return e if np.isfinite(e) and e > 0 else 0.0


def _error_table(group, px: float, name: str):
    """The model-error table of the file's or pupil group's model (None where not kept)."""
    from ..psf.spline import SplinePSF

    if "error_table" not in group:
        return None
    t = group["error_table"]
    centre = (float(t.attrs["centre_row"]), float(t.attrs["centre_col"]))
    return SplinePSF(
        t["stack"][()], px, t["z"][()], centre=centre, normalise=False, name=f"{name} error"
    )


def _load(p: Path, model: str | None):
    """The model of the calibration file ``p``; every failure of a damaged file (h5py's
    OSError, KeyError, RuntimeError, TypeError, zlib errors, a model refusing its data ...)
    as a ValueError in one sentence naming the file."""
    try:
        return _read_model(p, model)
    except KeyError as exc:
        raise ValueError(f"{p.name} is an incomplete calibration file (missing {exc})") from exc
    except ValueError as exc:
        if p.name in str(exc):
            raise
        raise ValueError(f"{p.name} is not a usable calibration file: {exc}") from exc
    except Exception as exc:
        raise ValueError(
            f"{p.name} is a damaged calibration file ({type(exc).__name__}: {exc})"
        ) from exc


#: How far a stored plane's sum may stray from one photon (float rounding and the clipping
#: of negative voxels stay far below it; a rescaled or foreign stack does not).
PLANE_SUM_TOLERANCE = 0.01


def _check_plane_sums(p: Path, stack: np.ndarray, oversample: int = 1) -> None:
    """Refuse a spline stack whose planes do not each hold one photon (``oversample``^2 for
    a table sampled that much finer than the camera): its photon counts would be wrong by
    that factor, silently."""
    sums = np.asarray(stack, dtype=np.float64).reshape(len(stack), -1).sum(axis=1)
    sums = sums / max(oversample, 1) ** 2
    bad = ~(np.abs(sums - 1.0) <= PLANE_SUM_TOLERANCE)
    if np.any(bad):
        raise ValueError(
            f"{p.name} is not a usable calibration file: its model's planes must each sum to "
            f"one photon, but {int(bad.sum())} of {len(sums)} sum to "
            f"{np.nanmin(sums):.4g}-{np.nanmax(sums):.4g}"
        )


def _read_model(p: Path, model: str | None):
    from ..psf.base import ShiftedPSF
    from ..psf.masks import ArrayMask
    from ..psf.pupil import PupilPSF
    from ..psf.spline import SplinePSF

    with _open(p) as f:
        version = int(f.attrs.get("format_version", 0))
        if version > FORMAT_VERSION:
            raise ValueError(
                f"{p.name} was written by a newer sparseloc (format {version}); upgrade sparseloc"
            )
        kind = model or str(f.attrs.get("model", "spline"))
        name = str(f.attrs.get("name", p.stem))
        px = float(f.attrs["pixel_size_nm"])
        if kind == "spline":
            g = f["spline"]
            stack = g["stack"][()]
            _check_plane_sums(p, stack, int(g.attrs.get("oversample", 1)))
            out = SplinePSF(
                stack,
                px,
                g["z"][()],
                centre=(float(g.attrs["centre_row"]), float(g.attrs["centre_col"])),
                z_range=(float(f.attrs["z_min_nm"]), float(f.attrs["z_max_nm"])),
                name=name,
                normalise=False,
                oversample=int(g.attrs.get("oversample", 1)),
            )
            out.model_error = _model_error(f)
            out.error_table = _error_table(f, px, name)
            return out
        if kind == "pupil":
            if "pupil" not in f:
                raise ValueError(f"{p.name} holds no fitted pupil; use the spline model")
            g = f["pupil"]
            phase = g["phase"][()]
            c = (phase.shape[0] - 1) / 2.0
            mask = ArrayMask(phase, centre=(c, c), radius=c)
            dx, dy, dz = (float(g.attrs.get(f"offset_{k}_nm", 0.0)) for k in "xyz")
            zr = (float(g.attrs["z_min_nm"]), float(g.attrs["z_max_nm"]))
            pupil = PupilPSF(
                mask,
                na=float(g.attrs["na"]),
                wavelength=float(g.attrs["wavelength_nm"]),
                n_immersion=float(g.attrs["n_immersion"]),
                z_range=(zr[0] + dz, zr[1] + dz),
                name=name,
            )
            out = ShiftedPSF(pupil, dx, dy, dz, z_range=zr)
            out.pixel_size = px
            out.content_hash = str(f.attrs["content_hash"])
            # the pupil's own error where the file has it (files before it: the spline's)
            own = "model_error" in g.attrs
            out.model_error = _model_error(g if own else f)
            out.error_table = _error_table(g, px, name) if own else None
            return out
        raise ValueError(f"model must be 'spline' or 'pupil', got {kind!r}")
