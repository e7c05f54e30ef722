"""Picasso HDF5 localization tables with their YAML sidecar (re-exported by
:mod:`sparseloc.io.tables`).

Dataset ``/locs`` (structured array, Picasso's field names and dtypes), ``x`` and ``y`` in
camera pixels with the centre of the first pixel at 0, ``z`` and ``lpz`` in nm, plus the YAML
sidecar whose first document holds ``Width``, ``Height``, ``Frames`` and ``Pixelsize``. Values
are float32.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pandas as pd
import yaml

from .. import __version__
from .atomic import atomic_path
from .locs import check_locs
from .table_files import (
    decode_flags,
    dest_path,
    encode_flags,
    flag_mapping,
    plain_metadata,
    source_path,
)

__all__ = ["PICASSO_DTYPE", "psf_width_table", "read_picasso_hdf5", "write_picasso_hdf5"]

# Messages keep the logger of sparseloc.io.tables, where the table formats have always logged.
log = logging.getLogger("sparseloc.io.tables")

#: Fields of Picasso's ``/locs`` dataset written by sparseloc (Picasso names and dtypes first,
#: then sparseloc's ``gof``, ``flag`` code and ``window_id``).
PICASSO_DTYPE = np.dtype(
    [
        ("frame", "<u4"),
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("photons", "<f4"),
        ("bg", "<f4"),
        ("lpx", "<f4"),
        ("lpy", "<f4"),
        ("lpz", "<f4"),
        ("photons_unc", "<f4"),
        ("gof", "<f4"),
        ("flag", "<i2"),
        ("window_id", "<i8"),
    ]
)


#: ``/locs`` fields when the PSF widths are known: Picasso's ``sx``, ``sy`` after ``photons``.
_DTYPE_WITH_WIDTH = np.dtype(
    [
        *[(n, PICASSO_DTYPE[n]) for n in PICASSO_DTYPE.names[:5]],
        ("sx", "<f4"),
        ("sy", "<f4"),
        *[(n, PICASSO_DTYPE[n]) for n in PICASSO_DTYPE.names[5:]],
    ]
)

#: Side (camera pixels) of the window over which :func:`psf_width_table` takes moments.
_WIDTH_WINDOW = 15


def psf_width_table(model: Any, pixel_size: float, n_planes: int = 25) -> dict[str, list[float]]:
    """The PSF's width along x and y at ``n_planes`` depths over its axial range, for the
    ``sx``, ``sy`` fields of a Picasso table.

    Picasso's ``sx``, ``sy`` are the standard deviations of the Gaussian fitted to each spot.
    sparseloc fits no Gaussian, so the width written is the model's: the RMS extent of its
    unit-photon image at the row's depth (second moments over a 15 px window, negative values
    clipped, less the ``pixel^2 / 12`` that pixelation adds). For a Gaussian PSF this is the
    Gaussian's sigma; for a double helix it grows with the lobes' separation along each axis.

    Parameters
    ----------
    model : PSFModel
        The PSF model the table was localized with (anything with ``images`` and ``z_range``).
    pixel_size : float
        Camera pixel size (nm).
    n_planes : int
        Depths sampled (evenly over ``model.z_range``).

    Returns
    -------
    dict
        ``z_nm``, ``sx_nm``, ``sy_nm``: lists of ``n_planes`` floats (JSON-ready, for a
        table's metadata under ``psf_width``).
    """
    px = _positive_number(pixel_size, "pixel_size")
    z = np.linspace(*(float(v) for v in model.z_range), int(n_planes))
    c = np.full(z.size, _WIDTH_WINDOW * px / 2)
    img = np.clip(np.asarray(model.images(c, c, z, (_WIDTH_WINDOW,) * 2, px)), 0.0, None)
    pos = (np.arange(_WIDTH_WINDOW) + 0.5) * px
    total = img.sum(axis=(1, 2))
    widths = []
    for axis in (2, 1):  # x runs along columns, y along rows
        w = img.sum(axis=3 - axis) / total[:, None]
        mean = w @ pos
        var = w @ pos**2 - mean**2 - px**2 / 12.0
        widths.append(np.sqrt(np.clip(var, (0.05 * px) ** 2, None)))
    return {"z_nm": z.tolist(), "sx_nm": widths[0].tolist(), "sy_nm": widths[1].tolist()}


def _width_columns(
    table: Mapping[str, Any] | None, z_nm: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """``sx``, ``sy`` (nm) of rows at depths ``z_nm``, interpolated in a :func:`psf_width_table`
    (values beyond its range take its end values); ``None`` when ``table`` is ``None``."""
    if table is None:
        return None
    try:
        z, sx, sy = (np.asarray(table[k], dtype=np.float64) for k in ("z_nm", "sx_nm", "sy_nm"))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(
            "psf_width must hold z_nm, sx_nm and sy_nm lists of numbers (see psf_width_table)"
        ) from exc
    ok = z.ndim == 1 and z.size >= 1 and z.shape == sx.shape == sy.shape
    ok = ok and bool(np.all(np.isfinite(z)) and np.all(np.diff(z) > 0))
    if not ok or not (np.all(sx > 0) and np.all(sy > 0)):
        raise ValueError(
            "psf_width must hold z_nm (increasing), sx_nm and sy_nm (> 0) of one length"
        )
    zq = np.nan_to_num(z_nm, nan=float(z[z.size // 2]))
    return np.interp(zq, z, sx), np.interp(zq, z, sy)


def _positive_number(value: Any, name: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = math.nan
    if not math.isfinite(out) or out <= 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return out


def _positive_int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _image_shape(shape: Any) -> tuple[int, int]:
    try:
        dims = tuple(shape)
    except TypeError:
        dims = ()
    if len(dims) != 2:
        raise ValueError(f"shape must be (rows, cols) of the camera image, got {shape!r}")
    return _positive_int(dims[0], "shape[0] (rows)"), _positive_int(dims[1], "shape[1] (cols)")


def _from_info(info: list[dict[str, Any]], key: str) -> Any:
    """Look ``key`` up from the last YAML document to the first, as Picasso does."""
    for doc in reversed(info):
        if isinstance(doc, dict) and doc.get(key) is not None:
            return doc[key]
    return None


def write_picasso_hdf5(
    df: pd.DataFrame,
    path: str | Path,
    *,
    pixel_size: float,
    shape: tuple[int, int],
    n_frames: int,
    metadata: Mapping[str, Any] | None = None,
    psf_width: Mapping[str, Any] | None = None,
) -> Path:
    """Write a localization table as Picasso HDF5 plus its YAML sidecar, atomically.

    ``/locs`` is a structured array with the fields of :data:`PICASSO_DTYPE`: ``frame``
    (uint32, 0-based), ``x``, ``y`` in camera pixels with the centre of the first pixel at 0
    (``x = x_nm / pixel_size - 0.5``), ``z`` in nm, ``photons``, ``bg`` (photons/pixel),
    ``lpx``, ``lpy`` (localization precision, pixels), ``lpz`` (nm), ``photons_unc``
    (Picasso's name for the photon uncertainty), then sparseloc's ``gof``, ``flag`` (int16
    code; the code table is in the YAML) and ``window_id`` (int64), all float32 unless noted.
    Picasso reads extra fields as extra columns and saves them again; the flag is numeric so
    that Picasso Filter can histogram it and keep ``flag == 0`` ("ok"), which a text field
    would not allow. ``sx`` and ``sy`` (Picasso's Gaussian PSF widths, camera pixels) follow
    ``photons`` when the PSF's widths are known (``psf_width``, or the ``psf_width`` entry of
    ``metadata`` that ``sparseloc localize`` records): sparseloc fits no Gaussian, so they are
    the model's width at each row's depth (:func:`psf_width_table`), not a per-spot fit.
    Without a width table they are left out (Picasso treats them as optional), never written
    as NaN, which Picasso's loader would drop every row for.

    An existing ``.yaml`` sidecar is replaced only together with its own table: one beside a
    missing ``.hdf5`` belongs to something else and is refused.

    The sidecar ``path.with_suffix(".yaml")`` holds two YAML documents: first ``Width``,
    ``Height``, ``Frames``, ``Pixelsize`` (nm); then ``Generated by`` and a ``sparseloc``
    mapping (``metadata``, the flag codes, the coordinate convention). The same list is also
    embedded as JSON in the ``/metadata`` dataset, as Picasso >= 0.11 does.

    Note that Picasso's loader drops rows with any NaN, with ``x < 0`` or ``y < 0`` (the
    outer half of the first pixel), ``x >= Width`` or ``y >= Height``, or negative ``lpx``,
    ``lpy``, ``lpz`` or ``photons``; :func:`read_picasso_hdf5` keeps every row.

    Parameters
    ----------
    df : DataFrame
        Localization table (:func:`check_locs`); extra columns are not written.
    path : str or Path
        Destination ``.hdf5`` file; its folder must exist.
    pixel_size : float
        Camera pixel size (nm).
    shape : tuple of int
        Camera image ``(rows, cols)``: ``Height``, ``Width`` (pixels).
    n_frames : int
        Number of frames in the movie (``Frames``); every ``frame`` must be below it.
    metadata : dict, optional
        Analysis metadata for the second YAML document (JSON-serialisable).
    psf_width : dict, optional
        :func:`psf_width_table` of the PSF the table was localized with; default
        ``metadata["psf_width"]`` when present.

    Returns
    -------
    Path
        The HDF5 path written.

    Raises
    ------
    ValueError
        If the folder does not exist, the table is invalid, ``pixel_size``, ``shape`` or
        ``n_frames`` are not positive, a frame is ``>= n_frames``, the width table is
        malformed, or the sidecar exists without the table.
    """
    t = check_locs(df)
    pixel = _positive_number(pixel_size, "pixel_size")
    rows, cols = _image_shape(shape)
    frames = _positive_int(n_frames, "n_frames")
    if len(t) and int(t["frame"].max()) >= frames:
        raise ValueError(
            f"frame {int(t['frame'].max())} is outside a movie of n_frames={frames} frames"
        )
    meta = plain_metadata(metadata)
    dest = dest_path(path)
    sidecar = dest.with_suffix(".yaml")
    if sidecar.exists() and not dest.exists():
        raise ValueError(
            f"{str(sidecar)!r} exists without the table {dest.name!r}, so it is not that "
            "table's sidecar; move it or choose another output name"
        )
    if psf_width is None and isinstance(meta.get("psf_width"), dict):
        psf_width = meta["psf_width"]
    mapping = flag_mapping(t["flag"])
    locs = _picasso_locs(t, pixel, mapping, _width_columns(psf_width, t["z_nm"].to_numpy()))
    info = _picasso_documents(rows, cols, frames, pixel, meta, mapping)
    yaml_text = yaml.safe_dump_all(info, default_flow_style=False, sort_keys=False)
    with atomic_path(dest) as tmp_h5, atomic_path(sidecar) as tmp_yaml:
        with h5py.File(tmp_h5, "w") as fh:
            fh.create_dataset("locs", data=locs)
            fh.create_dataset("metadata", data=json.dumps(info))
        tmp_yaml.write_text(yaml_text, encoding="utf-8")
    log.info("wrote %d localizations to %s (Picasso HDF5)", len(t), dest)
    return dest


def _picasso_locs(
    t: pd.DataFrame,
    pixel: float,
    mapping: Mapping[str, int],
    widths: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """The ``/locs`` structured array of the checked table ``t`` (pixel size ``pixel`` nm),
    with ``sx``, ``sy`` when the rows' PSF ``widths`` (nm) are given."""
    locs = np.zeros(len(t), dtype=PICASSO_DTYPE if widths is None else _DTYPE_WITH_WIDTH)
    if widths is not None:
        locs["sx"], locs["sy"] = widths[0] / pixel, widths[1] / pixel
    locs["frame"] = t["frame"].to_numpy()
    locs["x"] = t["x_nm"].to_numpy() / pixel - 0.5
    locs["y"] = t["y_nm"].to_numpy() / pixel - 0.5
    locs["z"] = t["z_nm"].to_numpy()
    locs["photons"] = t["photons"].to_numpy()
    locs["bg"] = t["background"].to_numpy()
    locs["lpx"] = t["sigma_x_nm"].to_numpy() / pixel
    locs["lpy"] = t["sigma_y_nm"].to_numpy() / pixel
    locs["lpz"] = t["sigma_z_nm"].to_numpy()
    locs["photons_unc"] = t["sigma_photons"].to_numpy()
    locs["gof"] = t["gof"].to_numpy()
    locs["flag"] = encode_flags(t["flag"], mapping)
    locs["window_id"] = t["window_id"].to_numpy()
    return locs


def _picasso_documents(
    rows: int,
    cols: int,
    frames: int,
    pixel: float,
    meta: dict[str, Any],
    mapping: Mapping[str, int],
) -> list[dict[str, Any]]:
    """The two YAML documents: Picasso's image description, then sparseloc's own."""
    return [
        {"Width": cols, "Height": rows, "Frames": frames, "Pixelsize": pixel},
        {
            "Generated by": f"sparseloc {__version__}",
            "sparseloc": {
                "metadata": meta,
                "flag_codes": mapping,
                "coordinates": (
                    "x, y, lpx, lpy, sx, sy in camera pixels with the centre of the first "
                    "pixel at 0; sx, sy the PSF model's width at the row's z, not a fit; "
                    "z, lpz in nm; photons, bg (per pixel) in photons; frame 0-based"
                ),
            },
        },
    ]


def _picasso_info(src: Path, fh: h5py.File) -> list[dict[str, Any]]:
    sidecar = src.with_suffix(".yaml")
    if sidecar.is_file():
        try:
            docs = list(yaml.safe_load_all(sidecar.read_text(encoding="utf-8")))
        except yaml.YAMLError as exc:
            raise ValueError(f"the Picasso metadata {sidecar.name!r} is not plain YAML") from exc
        return [d for d in docs if isinstance(d, dict)]
    if "metadata" in fh:
        raw = fh["metadata"][()]
        if isinstance(raw, bytes):
            raw = raw.decode("utf-8")
        try:
            return [d for d in json.loads(raw) if isinstance(d, dict)]
        except (ValueError, TypeError) as exc:
            raise ValueError(f"the metadata embedded in {src.name!r} is not JSON") from exc
    raise ValueError(f"found neither {sidecar.name!r} nor metadata embedded in {src.name!r}")


def read_picasso_hdf5(path: str | Path) -> tuple[pd.DataFrame, list[dict[str, Any]]]:
    """Read a Picasso HDF5 localization file (Picasso's own or :func:`write_picasso_hdf5`'s).

    Parameters
    ----------
    path : str or Path
        HDF5 file with a structured ``/locs`` dataset, beside its ``.yaml`` sidecar (or with
        the metadata embedded in ``/metadata``).

    Returns
    -------
    df : DataFrame
        Localization table (:func:`check_locs` form) in native coordinates:
        ``x_nm = (x + 0.5) * Pixelsize``, ``sigma_x_nm = lpx * Pixelsize``... A missing ``z``
        is 0 nm; missing ``lpz``, ``photons_unc``, ``gof`` are NaN; a missing ``flag`` is
        "ok" and ``window_id`` -1.
    info : list of dict
        The YAML documents (Picasso's metadata list).

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If it is not HDF5, has no structured ``/locs``, or its metadata lacks ``Pixelsize``.
    """
    src = source_path(path)
    try:
        fh = h5py.File(src, "r")
    except OSError as exc:
        raise ValueError(f"{str(src)!r} is not a readable HDF5 file ({exc})") from exc
    with fh:
        ds = fh.get("locs")
        if not isinstance(ds, h5py.Dataset) or ds.dtype.names is None:
            raise ValueError(f"{str(src)!r} has no Picasso '/locs' table")
        locs = ds[()]
        info = _picasso_info(src, fh)
    names = set(locs.dtype.names)
    missing = [f for f in ("frame", "x", "y") if f not in names]
    if missing:
        raise ValueError(f"the Picasso table {src.name} lacks the field(s) {', '.join(missing)}")
    pixel_raw = _from_info(info, "Pixelsize")
    if pixel_raw is None:
        raise ValueError(f"the metadata of {src.name} has no Pixelsize (nm)")
    pixel = _positive_number(pixel_raw, "Pixelsize")
    n = len(locs)

    def field(name: str, scale: float = 1.0, default: float = np.nan) -> np.ndarray:
        if name in names:
            return locs[name].astype(np.float64) * scale
        return np.full(n, default)

    out = pd.DataFrame(
        {
            "frame": locs["frame"].astype(np.int64),
            "x_nm": (locs["x"].astype(np.float64) + 0.5) * pixel,
            "y_nm": (locs["y"].astype(np.float64) + 0.5) * pixel,
            "z_nm": field("z", default=0.0),
            "photons": field("photons"),
            "background": field("bg"),
            "sigma_x_nm": field("lpx", pixel),
            "sigma_y_nm": field("lpy", pixel),
            "sigma_z_nm": field("lpz"),
            "sigma_photons": field("photons_unc"),
            "gof": field("gof"),
        }
    )
    if "flag" in names:
        own = _from_info(info, "sparseloc")
        mapping = own.get("flag_codes") if isinstance(own, dict) else None
        out["flag"] = decode_flags(locs["flag"], mapping)
    else:
        out["flag"] = "ok"
    out["window_id"] = field("window_id", default=-1.0)
    return check_locs(out, what=f"the Picasso table {src.name}"), info
