"""A disk cache of spline tables (:meth:`SplinePSF.from_model`).

Tabulating a pupil model takes seconds; the table depends only on the model's images and the
table's parameters, so it is kept on disk under a key made of both and read back on
later runs. Files are plain ``.npz`` arrays (read without pickle), written under a temporary
name and renamed, so a reader never sees half a file; a damaged file is ignored and written
again.

The folder is ``$SPARSELOC_CACHE_DIR`` if set, else the user's cache folder
(``$XDG_CACHE_HOME/sparseloc`` or ``~/.cache/sparseloc`` on Linux, ``~/Library/Caches/sparseloc``
on macOS, ``%LOCALAPPDATA%\\sparseloc`` on Windows). Deleting it is always safe.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["cache_dir", "load_table", "save_table", "table_key", "table_path"]

log = logging.getLogger(__name__)

#: Bump when the stored arrays or their meaning change: older files are then not read.
FORMAT = 1


def cache_dir() -> Path:
    """The folder of cached spline tables (see the module notes)."""
    env = os.environ.get("SPARSELOC_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "sparseloc"


def table_key(model, pixel_size: float, planes: NDArray, roi: int, oversample: int) -> str:
    """The cache key (SHA-256, hex) of a table of ``model``: the model's content hash
    (:func:`sparseloc.digest.psf_hash`), its kind and name, the package version, and the
    table's pixel size, planes (nm), ROI (px) and oversampling."""
    from .. import __version__
    from ..digest import psf_hash

    desc = {
        "format": FORMAT,
        "version": __version__,
        "model": f"{type(model).__module__}.{type(model).__qualname__}",
        "name": str(getattr(model, "name", "")),
        "psf_hash": psf_hash(model, pixel_size),
        "z_range": [float(v) for v in model.z_range],
        "pixel_size": float(pixel_size),
        "roi": int(roi),
        "oversample": int(oversample),
    }
    h = hashlib.sha256(json.dumps(desc, sort_keys=True).encode())
    h.update(np.ascontiguousarray(planes, dtype="<f8").tobytes())
    return h.hexdigest()


def table_path(key: str, name: str = "psf") -> Path:
    """The cache file of ``key`` (the model's name in it, for people looking at the folder)."""
    label = re.sub(r"[^A-Za-z0-9_.-]+", "_", name)[:40] or "psf"
    return cache_dir() / f"spline-{label}-{key[:32]}.npz"


def load_table(path: Path, key: str, planes: NDArray, shape: tuple[int, ...]) -> NDArray | None:
    """The cached stack at ``path`` if it is there, whole and made for ``key``; else None
    (a damaged file is reported and left to be written again)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            stored_key = str(f["key"])
            stored_planes = np.asarray(f["planes"], dtype=np.float64)
            stack = np.asarray(f["stack"], dtype=np.float64)
        if stored_key != key or not np.array_equal(stored_planes, planes):
            raise ValueError("it was made for another table")
        if stack.shape != tuple(shape) or not np.all(np.isfinite(stack)):
            raise ValueError(f"its stack is {stack.shape} or not finite")
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        log.warning("the cached spline table %s is damaged (%s); tabulating it again", path, exc)
        return None
    return stack


def save_table(path: Path, key: str, planes: NDArray, stack: NDArray) -> bool:
    """Write the table atomically (temporary file, then rename); True when it was saved. A
    cache that cannot be written is reported and otherwise ignored."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".npz")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, key=np.str_(key), planes=planes, stack=stack)
        os.chmod(tmp, 0o644)  # mkstemp's 0600 would hide a shared cache from the group
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        log.warning(
            "could not save the spline table to the cache (%s: %s); it will be tabulated "
            "again next time (set SPARSELOC_CACHE_DIR to a writable folder)",
            path,
            exc,
        )
        return False
    finally:
        if tmp is not None:  # failed or interrupted: no half-written file stays behind
            Path(tmp).unlink(missing_ok=True)
    return True
