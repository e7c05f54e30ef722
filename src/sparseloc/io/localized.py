"""The table of a ``localize`` run, written with the run's metadata.

One writer for the command line and the napari widget, so that both give the same file for
the same run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["localized_metadata", "write_localized"]


def localized_metadata(result: Any, movie: Any, job: Any) -> dict[str, Any]:
    """The metadata stored with a run's table: the analysis (``result.metadata``), the movie's
    files, the camera, the defective pixels replaced (row, col) and the PSF's width by depth
    (for the ``sx``, ``sy`` of Picasso exports).

    Parameters
    ----------
    result : LocalizeResult
        From :func:`sparseloc.pipeline.localize` (or the chunked run).
    movie : Movie or object with ``paths``
        The movie localized; ``paths`` may be empty (frames held in memory).
    job : LocalizeJob
        From :func:`sparseloc.config.build_job`.
    """
    from .picasso import psf_width_table

    paths = [str(p) for p in getattr(movie, "paths", ())]
    meta = {**result.metadata, "movie": paths, "camera": job.camera.to_dict()}
    defects = getattr(job, "defects", None)
    meta["defective_pixels"] = [] if defects is None else np.argwhere(defects).tolist()
    meta["psf_width"] = psf_width_table(job.model, job.params.pixel_size)
    return meta


def write_localized(
    result: Any, out: str | Path, *, format: str | None, movie: Any, job: Any
) -> Path:
    """Write ``localize``'s table to ``out`` (atomically, :func:`sparseloc.io.tables.write_table`)
    with :func:`localized_metadata`.

    Parameters
    ----------
    result : LocalizeResult
        The run's result.
    out : str or Path
        Output table; the format from ``format`` or the suffix.
    format : str or None
        ``parquet``, ``thunderstorm``, ``picasso`` or ``smlm``; None: from the suffix.
    movie : Movie or object with ``paths``, ``shape`` (rows, cols) and ``len()``
        The movie localized.
    job : LocalizeJob
        The run's model, camera and parameters.

    Returns
    -------
    Path
        The table written.
    """
    from .tables import write_table

    return write_table(
        result.table,
        out,
        format=format,
        pixel_size=job.params.pixel_size,
        shape=tuple(movie.shape),
        n_frames=len(movie),
        metadata=localized_metadata(result, movie, job),
    )
