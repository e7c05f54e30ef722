"""sparseloc: sparse recovery of overlapping 3D single-molecule PSFs."""

__version__ = "0.1.0"
