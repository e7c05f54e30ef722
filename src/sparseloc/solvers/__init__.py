"""Window solvers: matching pursuit, convex L1 recovery and their hybrid.

Every solver takes one window (photons) and returns a :class:`WindowSolution`.
"""

from .convex import ConvexResult, noise_epsilon, solve_constrained, solve_penalized
from .emitters import Emitters, WindowSolution, group_by_boxes, group_coefficients
from .fast_mp import matching_pursuit_batch
from .hybrid import convex_solve, hybrid_solve
from .mp import estimate_background, matching_pursuit

__all__ = [
    "ConvexResult",
    "Emitters",
    "WindowSolution",
    "convex_solve",
    "estimate_background",
    "group_by_boxes",
    "group_coefficients",
    "hybrid_solve",
    "matching_pursuit",
    "matching_pursuit_batch",
    "noise_epsilon",
    "solve_constrained",
    "solve_penalized",
]
