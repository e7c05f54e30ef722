"""Readers and writers: camera movies (TIFF) and ground-truth tables (CSV).

I/O happens only at the ends of the pipeline; every writer is atomic (a temporary file in the
destination folder, then a rename), so a failure never leaves a half-written output.
"""

from .tiff import read_tiff, read_tiff_metadata, write_tiff
from .truth import TRUTH_COLUMNS, check_truth_table, read_truth_csv, write_truth_csv

__all__ = [
    "TRUTH_COLUMNS",
    "check_truth_table",
    "read_tiff",
    "read_tiff_metadata",
    "read_truth_csv",
    "write_tiff",
    "write_truth_csv",
]
