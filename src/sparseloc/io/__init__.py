"""Readers and writers: camera movies (lazy TIFF / OME-TIFF series), ground-truth tables
(CSV) and localization tables (Parquet, ThunderSTORM CSV, Picasso HDF5 + YAML, SMLM-challenge CSV).

I/O happens only at the ends of the pipeline; every writer is atomic (a temporary file in the
destination folder, then a rename), so a failure never leaves a half-written output.
"""

from .movie import Movie, check_camera_for_movie, photon_frames
from .tables import LOCS_COLUMNS, check_locs, empty_locs, read_table, write_table
from .tiff import read_tiff, read_tiff_metadata, write_tiff
from .truth import TRUTH_COLUMNS, check_truth_table, read_truth_csv, write_truth_csv

__all__ = [
    "LOCS_COLUMNS",
    "TRUTH_COLUMNS",
    "Movie",
    "check_camera_for_movie",
    "check_locs",
    "check_truth_table",
    "empty_locs",
    "photon_frames",
    "read_table",
    "read_tiff",
    "read_tiff_metadata",
    "read_truth_csv",
    "write_table",
    "write_tiff",
    "write_truth_csv",
]
