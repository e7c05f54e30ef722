"""Which engine computes the solvers' arithmetic: one setting, decided in one place.

The solvers' rules (the pursuit's selection, the Levenberg-Marquardt step and its convergence
test, the count selection, the sweeps) are written once; the numbers they ask for come from an
engine:

- ``"numpy"``: the plain NumPy reference, for any :class:`~sparseloc.psf.base.PSFModel`;
- ``"numba"``: compiled kernels for spline tables (their images and derivatives, the fit's
  model, likelihood and Fisher matrix, the frame pursuit's template selection) and the
  temporal background's sliding percentile; other models still use NumPy.

The setting is ``"auto"`` (numba where it imports and its kernels compile, else NumPy with a
logged warning), ``"numpy"`` or ``"numba"``; it comes from ``LocalizeParams.engine`` /
``--engine`` (the pipeline applies it with :func:`use_engine`). The environment variable
``SPARSELOC_ENGINE`` (``numpy`` or ``numba``) says what ``"auto"`` means, for a whole test run
or a machine where numba misbehaves. This module is the only code that
looks at numba, PyTorch, CUDA or an environment variable to choose a code path.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

__all__ = [
    "ENGINES",
    "Kernels",
    "active_engine",
    "check_engine",
    "kernels",
    "resolve_engine",
    "torch_device",
    "use_engine",
]

ENGINES = ("auto", "numpy", "numba")
#: The environment variable that says what the setting ``"auto"`` means.
ENV_VAR = "SPARSELOC_ENGINE"


@dataclass(frozen=True)
class Kernels:
    """The compiled functions of the numba engine (see :mod:`sparseloc.solvers._fit_numba`,
    :mod:`sparseloc.psf._spline_numba`, :mod:`sparseloc.solvers._pursuit_numba`,
    :mod:`sparseloc._percentile_numba`)."""

    spline: Any
    fit: Any
    select_best: Any
    percentiles: Any


_setting: str | None = None  # set by use_engine; None: the default
_chosen: str | None = None  # the engine _setting resolves to, once asked for
_compiled: list = []  # [Kernels] once compiled, [None] when numba failed
_logged: set = set()


def check_engine(name: Any) -> str:
    """``name`` if it is one of :data:`ENGINES`; ValueError naming the choices otherwise."""
    if name not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}; got {name!r}")
    return name


def _auto() -> str:
    """What ``"auto"`` means: ``SPARSELOC_ENGINE`` where it is set, else ``"auto"``."""
    env = os.environ.get(ENV_VAR, "")
    if env == "":
        return "auto"
    if env not in ENGINES:
        raise ValueError(f"{ENV_VAR} must be one of {', '.join(ENGINES)}; got {env!r}")
    return env


def _compile() -> Kernels | None:
    """Import numba and run each kernel once on tiny inputs (compiling it, or loading it from
    numba's cache), so that a failure means NumPy rather than an error in the middle of a fit."""
    if not _compiled:
        try:
            from ._percentile_numba import sliding_percentiles
            from .psf._spline_numba import spline_kernel
            from .solvers._fit_numba import warm_up
            from .solvers._pursuit_numba import select_best

            coef = np.zeros((6, 6, 6))
            one = np.ones(1)
            out = np.empty((1, 2, 2))
            spline_kernel(coef, one, one, one, 2, 2, 1, out, np.empty((1, 3, 2, 2)), True)
            fit = warm_up()
            grid = np.zeros((1, 1, 1), np.float32)
            best = np.zeros((1, 1), np.float32)
            select_best(grid, 0, grid, 0, best, np.zeros((1, 1), np.int32), best.copy())
            sliding_percentiles(np.zeros((2, 1, 1)), np.zeros(1, np.int64), 1, 30.0, out)
            _compiled.append(Kernels(spline_kernel, fit, select_best, sliding_percentiles))
        except Exception as exc:  # any failure of numba (import, compilation) means NumPy
            log.warning("numba kernels unavailable (%s): using the NumPy engine", exc)
            _compiled.append(None)
    return _compiled[0]


def resolve_engine(name: str | None = None) -> str:
    """The engine that runs for setting ``name`` (``None``: the active setting): ``"numpy"``
    or ``"numba"``. ``"auto"`` falls back to NumPy, with a warning, where numba fails;
    ``"numba"`` raises then. The choice is logged once per setting."""
    setting = check_engine(active_setting() if name is None else name)
    if setting == "auto":
        setting = _auto()
    if setting == "numpy":
        chosen = "numpy"
    elif _compile() is not None:
        chosen = "numba"
    elif setting == "numba":
        raise ValueError("engine 'numba' was asked for but numba is unavailable here")
    else:
        chosen = "numpy"
    if (setting, chosen) not in _logged:
        _logged.add((setting, chosen))
        log.info("engine %r: %s", setting, chosen)
    return chosen


def active_setting() -> str:
    """The setting in force: the innermost :func:`use_engine`, else ``"auto"``."""
    return "auto" if _setting is None else _setting


def active_engine() -> str:
    """The engine that runs now: ``"numpy"`` or ``"numba"`` (resolved once per setting, as
    the hot paths ask for it on every call)."""
    global _chosen
    if _chosen is None:
        _chosen = resolve_engine(None)
    return _chosen


def kernels() -> Kernels | None:
    """The compiled kernels when the active engine is numba, else ``None`` (use NumPy)."""
    return _compiled[0] if active_engine() == "numba" else None


@contextlib.contextmanager
def use_engine(name: str | None) -> Iterator[str]:
    """Run the enclosed code with engine setting ``name`` (``None``: leave it as it is);
    yields the engine that runs."""
    global _setting, _chosen
    previous = (_setting, _chosen)
    if name is not None:
        _setting, _chosen = check_engine(name), None
    try:
        yield active_engine()
    finally:
        _setting, _chosen = previous


def set_engine(name: str | None) -> str:
    """Set the engine for the rest of the process (worker processes use it); returns the
    engine that runs."""
    global _setting, _chosen
    _setting, _chosen = (None if name is None else check_engine(name)), None
    return active_engine()


def torch_device(device: str) -> tuple[Any, Any]:
    """PyTorch and its device ``device`` (``"cpu"``, ``"cuda"``, ``"cuda:N"``), or a
    ValueError in one sentence where PyTorch or that device is missing."""
    try:
        import torch
    except ImportError:
        raise ValueError(
            f"device {device!r} needs PyTorch: pip install 'sparseloc[cpu]' (CPU build) or a "
            "CUDA build of torch"
        ) from None
    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"device {device!r}: PyTorch sees no CUDA GPU on this machine")
        index = int(device.partition(":")[2] or 0)
        if index >= torch.cuda.device_count():
            raise ValueError(
                f"device {device!r}: PyTorch sees {torch.cuda.device_count()} CUDA GPU(s), "
                "numbered from 0"
            )
    elif device != "cpu":
        raise ValueError(f"device must be cpu, cuda or cuda:N; got {device!r}")
    return torch, torch.device(device)
