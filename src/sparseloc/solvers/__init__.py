"""Solvers: the frame solver (the default) and the paper's window solvers.

- :func:`frame_fit` (:mod:`sparseloc.solvers.frame`) is the default: the pipeline
  (:func:`sparseloc.pipeline.localize`) fits a frame's lone emitters singly and its small
  crowds with :func:`frame_fit` (:mod:`sparseloc.solvers.two_tier`), and where the frame is
  crowded runs :func:`frame_pursuit` on it (through :func:`tiled_pursuit`) and hands its
  emitters to :func:`frame_fit`, which fits groups of overlapping emitters by maximum
  likelihood with their neighbours' light held fixed.
- Window solvers (``method`` ``hybrid``, ``mp``, ``co``): :func:`matching_pursuit`,
  :func:`convex_solve` and :func:`hybrid_solve` take one window (photons) and return a
  :class:`WindowSolution`; :func:`refine_solution` adds the maximum-likelihood stage.
- The maximum-likelihood fit (:func:`fit_emitters`, with :func:`fit_with_count_selection`) is
  shared by both; its arithmetic runs on the engine :mod:`sparseloc.engine` chooses.
"""

from .convex import ConvexResult, noise_epsilon, solve_constrained, solve_penalized
from .emitters import Emitters, WindowSolution, group_by_boxes, group_coefficients
from .fast_mp import matching_pursuit_batch
from .frame import FrameFit, frame_fit, frame_pursuit, tiled_pursuit
from .hybrid import convex_solve, hybrid_solve
from .mp import estimate_background, matching_pursuit
from .refine import FitResult, fit_emitters, fit_with_count_selection, refine_solution

__all__ = [
    "ConvexResult",
    "Emitters",
    "FitResult",
    "FrameFit",
    "WindowSolution",
    "convex_solve",
    "estimate_background",
    "fit_emitters",
    "fit_with_count_selection",
    "frame_fit",
    "frame_pursuit",
    "group_by_boxes",
    "group_coefficients",
    "hybrid_solve",
    "matching_pursuit",
    "matching_pursuit_batch",
    "noise_epsilon",
    "refine_solution",
    "solve_constrained",
    "solve_penalized",
    "tiled_pursuit",
]
