"""Batched maximum-likelihood fits: many independent windows in one call, on NumPy or PyTorch.

:func:`fit_batch` solves, for every window of a batch, the problem :func:`~sparseloc.solvers.
refine.fit_emitters` solves for one: K emitters (x, y, z in nm, photons) plus a constant (or
tilted-plane) background, with a known ``offset`` image of neighbours' light, by
Levenberg-Marquardt with Fisher scoring on the Poisson, EMCCD or sCMOS likelihood (see
:mod:`sparseloc.solvers.refine` for the model, the noise models and the clamping rules). The
iterations are the same, window by window: each window keeps its own damping ``lam``, accepts
or rejects its own steps and stops on its own; the batch only shares the array operations.
Windows that have stopped drop out of the work, and the damping trials of one iteration run as
a vectorised inner loop over the windows still looking for a better step.

Shapes: ``B`` windows, all padded to ``(R, C)`` pixels (a ``mask`` says which pixels are
real), and up to ``Kmax`` emitters per window (``n_emitters`` says how many are real; the first
``n_emitters[b]`` rows of ``starts[b]``). Padded pixels and padded emitters take no part in the
fit. A window's extent, for the clamping of x and y (``xy_margin`` pixels beyond it), the
``"outside"`` flag and the plane background's coordinates, is the bounding box of its real
pixels; a window padded at its bottom and right therefore behaves exactly as the unpadded window
does in :func:`fit_emitters`.

The PSF is a :class:`~sparseloc.psf.spline.SplinePSF`; :func:`spline_images` renders it and its
x/y/z derivatives for many emitters at once, each on its own window, with the same arithmetic as
``SplinePSF._images`` (a sub-block of the coefficient table is gathered per emitter, then
contracted along z, x and y with the cubic B-spline weights).

Backends: ``device=None`` (or ``"numpy"``) runs on NumPy; ``"cpu"``, ``"cuda"``,
``"cuda:1"`` or a :class:`torch.device` run the same code on PyTorch (imported only then; it
is an optional dependency, ``pip install sparseloc[cpu]``). float64 throughout by default;
``precision="float32"`` renders the PSF in single precision (the likelihood, the linear algebra
and the uncertainties stay in float64).
"""

from __future__ import annotations

import logging
import time
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..psf.spline import SplinePSF, table_coords
from .emitters import Emitters
from .refine import _MIN_BG, _MIN_PHOTONS, NOISE_MODELS, FitResult, check_qe, likelihood_weight

log = logging.getLogger(__name__)

__all__ = ["BatchFitResult", "fit_batch", "spline_images"]

#: Damping trials per iteration (as in :func:`fit_emitters`).
_TRIALS = 12
#: Elements of the gathered coefficient block rendered at once (per chunk of emitters).
_CHUNK_ELEMENTS = {"numpy": 1 << 18, "cpu": 1 << 18, "cuda": 1 << 26}


# ---------------------------------------------------------------------------------------------
# Array backends: the few operations whose spelling differs between NumPy and PyTorch.
# ---------------------------------------------------------------------------------------------
class _NumpyOps:
    """NumPy spelling of the operations the renderer and the fitter need."""

    kind = "numpy"
    device_name = "numpy"

    def __init__(self) -> None:
        self.float = np.float64

    def asarray(self, a: Any, dtype: Any = None) -> NDArray:
        return np.asarray(a, dtype=self.float if dtype is None else dtype)

    def float_dtype(self, precision: str) -> Any:
        return np.float32 if precision == "float32" else np.float64

    def cast(self, a: NDArray, dtype: Any) -> NDArray:
        return a.astype(dtype, copy=False)

    def index(self, a: Any) -> NDArray:
        return np.asarray(a, dtype=np.int64)

    def to_numpy(self, a: Any) -> NDArray:
        return np.asarray(a)

    def zeros(self, shape: tuple[int, ...], dtype: Any = None) -> NDArray:
        return np.zeros(shape, dtype=self.float if dtype is None else dtype)

    def arange(self, n: int) -> NDArray:
        return np.arange(n, dtype=np.int64)

    def floor_int(self, a: NDArray) -> tuple[NDArray, NDArray]:
        f = np.floor(a)
        return f, f.astype(np.int64)

    def nonzero(self, mask: NDArray) -> NDArray:
        return np.flatnonzero(mask)

    def sum(self, a: NDArray, axis: int | tuple[int, ...]) -> NDArray:
        return a.sum(axis=axis)

    def all(self, a: NDArray, axis: int | tuple[int, ...]) -> NDArray:
        return a.all(axis=axis)

    def stack(self, arrays: list, axis: int) -> NDArray:
        return np.stack(arrays, axis=axis)

    def cat(self, arrays: list, axis: int) -> NDArray:
        return np.concatenate(arrays, axis=axis)

    def copy(self, a: NDArray) -> NDArray:
        return a.copy()

    def diagonal(self, a: NDArray) -> NDArray:
        return np.diagonal(a, axis1=-2, axis2=-1).copy()

    def transpose(self, a: NDArray) -> NDArray:
        return np.swapaxes(a, -1, -2)

    def contiguous(self, a: NDArray) -> NDArray:
        return np.ascontiguousarray(a)

    def isfinite(self, a: NDArray) -> NDArray:
        return np.isfinite(a)

    def log(self, a: NDArray) -> NDArray:
        return np.log(a)

    def where(self, cond: NDArray, a: Any, b: Any) -> NDArray:
        return np.where(cond, a, b)

    def full(self, shape: tuple[int, ...], value: Any, dtype: Any = None) -> NDArray:
        return np.full(shape, value, dtype=self.float if dtype is None else dtype)

    @property
    def bool(self) -> Any:
        return np.bool_

    def contract_rows(self, s: NDArray, w: NDArray, n: int, os_: int) -> NDArray:
        """``out[:, :, i] = sum_b w[:, b] * s[:, :, os_ * i + b]``: (N, a, L, M) with
        weights (N, 4) -> (N, a, n, M)."""
        from numpy.lib.stride_tricks import sliding_window_view

        v = sliding_window_view(s, 4, axis=2)[:, :, : os_ * (n - 1) + 1 : os_]
        return np.einsum("nalmb,nb->nalm", v, w)

    def diag_embed(self, d: NDArray) -> NDArray:
        n = d.shape[-1]
        out = np.zeros((*d.shape, n), dtype=d.dtype)
        i = np.arange(n)
        out[..., i, i] = d
        return out

    def solve(self, a: NDArray, b: NDArray) -> tuple[NDArray, NDArray]:
        """Solve ``a x = b`` for a stack; also return which systems were solvable."""
        try:
            return np.linalg.solve(a, b[..., None])[..., 0], np.ones(len(a), dtype=bool)
        except np.linalg.LinAlgError:
            x = np.full(b.shape, np.nan)
            ok = np.zeros(len(a), dtype=bool)
            for i in range(len(a)):
                try:
                    x[i] = np.linalg.solve(a[i], b[i])
                    ok[i] = True
                except np.linalg.LinAlgError:
                    pass
            return x, ok

    def inv(self, a: NDArray) -> NDArray:
        """Inverse of each matrix; the pseudo-inverse where one is singular (as fit_emitters)."""
        try:
            return np.linalg.inv(a)
        except np.linalg.LinAlgError:
            out = np.empty_like(a)
            for i in range(len(a)):
                try:
                    out[i] = np.linalg.inv(a[i])
                except np.linalg.LinAlgError:
                    out[i] = np.linalg.pinv(a[i])
            return out


class _TorchOps:
    """PyTorch spelling of the same operations (any device)."""

    kind = "torch"

    def __init__(self, device: Any) -> None:
        try:
            import torch
        except ImportError as exc:
            raise ImportError(
                f"device={device!r} needs PyTorch (pip install sparseloc[cpu]); "
                "device=None runs on NumPy"
            ) from exc

        self.torch = torch
        self.device = torch.device(device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device {device!r} was asked for but CUDA is not available")
        self.device_name = str(self.device)
        self.float = torch.float64

    def asarray(self, a: Any, dtype: Any = None) -> Any:
        dtype = self.float if dtype is None else dtype
        if isinstance(a, self.torch.Tensor):
            return a.to(device=self.device, dtype=dtype)
        arr = np.asarray(a)
        return self.torch.as_tensor(arr, dtype=dtype, device=self.device)

    def float_dtype(self, precision: str) -> Any:
        return self.torch.float32 if precision == "float32" else self.torch.float64

    def cast(self, a: Any, dtype: Any) -> Any:
        return a.to(dtype)

    def index(self, a: Any) -> Any:
        return self.asarray(a, dtype=self.torch.int64)

    def to_numpy(self, a: Any) -> NDArray:
        if isinstance(a, self.torch.Tensor):
            return a.detach().cpu().numpy()
        return np.asarray(a)

    def zeros(self, shape: tuple[int, ...], dtype: Any = None) -> Any:
        return self.torch.zeros(
            shape, dtype=self.float if dtype is None else dtype, device=self.device
        )

    def arange(self, n: int) -> Any:
        return self.torch.arange(n, dtype=self.torch.int64, device=self.device)

    def floor_int(self, a: Any) -> tuple[Any, Any]:
        f = self.torch.floor(a)
        return f, f.to(self.torch.int64)

    def nonzero(self, mask: Any) -> Any:
        return self.torch.nonzero(mask.reshape(-1)).reshape(-1)

    def sum(self, a: Any, axis: int | tuple[int, ...]) -> Any:
        return a.sum(dim=axis)

    def all(self, a: Any, axis: int | tuple[int, ...]) -> Any:
        return a.flatten(start_dim=1).all(dim=1) if isinstance(axis, tuple) else a.all(dim=axis)

    def stack(self, arrays: list, axis: int) -> Any:
        return self.torch.stack(arrays, dim=axis)

    def cat(self, arrays: list, axis: int) -> Any:
        return self.torch.cat(arrays, dim=axis)

    def copy(self, a: Any) -> Any:
        return a.clone()

    def diagonal(self, a: Any) -> Any:
        return self.torch.diagonal(a, dim1=-2, dim2=-1).clone()

    def transpose(self, a: Any) -> Any:
        return a.transpose(-1, -2)

    def contiguous(self, a: Any) -> Any:
        return a.contiguous()

    def isfinite(self, a: Any) -> Any:
        return self.torch.isfinite(a)

    def log(self, a: Any) -> Any:
        return self.torch.log(a)

    def where(self, cond: Any, a: Any, b: Any) -> Any:
        t = self.torch
        if not isinstance(a, t.Tensor):
            a = t.as_tensor(a, dtype=self.float, device=self.device)
        if not isinstance(b, t.Tensor):
            b = t.as_tensor(b, dtype=a.dtype, device=self.device)
        return t.where(cond, a, b)

    def full(self, shape: tuple[int, ...], value: Any, dtype: Any = None) -> Any:
        dtype = self.float if dtype is None else dtype
        return self.torch.full(shape, value, dtype=dtype, device=self.device)

    @property
    def bool(self) -> Any:
        return self.torch.bool

    def contract_rows(self, s: Any, w: Any, n: int, os_: int) -> Any:
        """``out[:, :, i] = sum_b w[:, b] * s[:, :, os_ * i + b]``: (N, a, L, M) with
        weights (N, 4) -> (N, a, n, M)."""
        stop = os_ * (n - 1) + 1
        out = s[:, :, 0:stop:os_] * w[:, None, 0, None, None]
        for b in range(1, 4):
            out.add_(s[:, :, b : b + stop : os_] * w[:, None, b, None, None])
        return out

    def diag_embed(self, d: Any) -> Any:
        return self.torch.diag_embed(d)

    def solve(self, a: Any, b: Any) -> tuple[Any, Any]:
        x, info = self.torch.linalg.solve_ex(a, b[..., None])
        return x[..., 0], info == 0

    def inv(self, a: Any) -> Any:
        out, info = self.torch.linalg.inv_ex(a)
        bad = info != 0
        if bool(bad.any()):
            out[bad] = self.torch.linalg.pinv(a[bad])
        return out


def _backend(device: Any) -> _NumpyOps | _TorchOps:
    if device is None or (isinstance(device, str) and device == "numpy"):
        return _NumpyOps()
    return _TorchOps(device)


def _chunk_elements(ops: _NumpyOps | _TorchOps) -> int:
    if ops.kind == "numpy":
        return _CHUNK_ELEMENTS["numpy"]
    return _CHUNK_ELEMENTS["cuda" if ops.device.type == "cuda" else "cpu"]


# ---------------------------------------------------------------------------------------------
# The spline renderer
# ---------------------------------------------------------------------------------------------
class _Table:
    """A SplinePSF's coefficient table on one backend, with its geometry.

    An emitter's image on an ``(R, C)`` window reads a block of ``4 x Ly x Lx`` coefficients
    (``L = oversample * (n - 1) + 4``): four planes, and runs of rows and columns that start
    where the emitter's sub-pixel position says. :meth:`blocks` cuts these blocks out of a
    copy of the table padded with ``Ly`` (``Lx``) zero rows (columns) on each side, through a
    sliding-window view: one index triple per plane instead of one index per coefficient.
    Nodes outside the stack read zeros, as in ``SplinePSF._images``.
    """

    def __init__(self, spline: SplinePSF, ops: _NumpyOps | _TorchOps, dtype: Any) -> None:
        coef = np.asarray(spline._coef)
        self.ny, self.nx = int(spline._ny), int(spline._nx)
        if coef.ndim != 3 or coef.shape[1] < self.ny or coef.shape[2] < self.nx:
            raise ValueError(
                f"the spline's coefficient table has shape {coef.shape}; expected "
                f"(planes + 2, >= {self.ny}, >= {self.nx})"
            )
        self.ops = ops
        self.dtype = dtype
        # Only the stack's nodes: rows >= ny and columns >= nx read zero.
        self._coef = np.ascontiguousarray(coef[:, : self.ny, : self.nx])
        self.n_planes = int(np.asarray(spline.z).size)
        self.cy = float(spline.centre[0])
        self.cx = float(spline.centre[1])
        self.oversample = int(spline.oversample)
        self.z0 = float(spline.z[0])
        self.z_step = float(spline.z_step)
        self.pixel_size = float(spline.pixel_size)
        self.geometry = spline.node_geometry((0.0, 0.0), self.pixel_size)
        # One zero-padded copy of the table, x before y, padded by (pad_x, pad_y) nodes on
        # each side: every block size up to the padding is a view of it. It is rebuilt (with
        # room to spare) only when a larger block is asked for, so windows of many shapes
        # share one copy instead of each copying the table.
        self.pad_x = self.pad_y = 0
        self._padded: Any = None
        self._views: dict[tuple[int, int], Any] = {}

    def view(self, lx: int, ly: int) -> Any:
        """Sliding-window view (planes, nx + 2 pad_x - lx + 1, ny + 2 pad_y - ly + 1, lx, ly)
        of the padded table with x before y: ``view[p, sx + pad_x, sy + pad_y]`` is the block
        whose first node is (sy, sx), x-major."""
        key = (lx, ly)
        if lx > self.pad_x or ly > self.pad_y or self._padded is None:
            self.pad_x = max(self.pad_x, -(-lx // 16) * 16)
            self.pad_y = max(self.pad_y, -(-ly // 16) * 16)
            px_, py_ = self.pad_x, self.pad_y
            padded = np.pad(self._coef, ((0, 0), (py_, py_), (px_, px_))).transpose(0, 2, 1)
            self._padded = self.ops.asarray(np.ascontiguousarray(padded), dtype=self.dtype)
            self._views.clear()
        if key not in self._views:
            t = self._padded
            if self.ops.kind == "numpy":
                from numpy.lib.stride_tricks import sliding_window_view

                v = sliding_window_view(t, (lx, ly), axis=(1, 2))
            else:
                v = t.unfold(1, lx, 1).unfold(2, ly, 1)
            self._views[key] = v
        return self._views[key]

    def blocks(self, planes: Any, sy: Any, sx: Any, ly: int, lx: int) -> Any:
        """Blocks (N, 4, lx, ly) of coefficients, x-major: planes (N, 4), first row and column
        (N,)."""
        ops = self.ops
        v = self.view(lx, ly)
        # Blocks wholly outside the stack are all zeros: keep their start in the padding.
        sy = (sy.clip(-ly, self.ny) + self.pad_y)[:, None]
        sx = (sx.clip(-lx, self.nx) + self.pad_x)[:, None]
        out = v[planes, sx, sy]
        return out if ops.kind == "numpy" else out.contiguous()


_TABLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _table(spline: SplinePSF, ops: _NumpyOps | _TorchOps, dtype: Any) -> _Table:
    """The table of ``spline`` on ``ops``'s device in ``dtype`` (cached per spline)."""
    key = (ops.device_name, str(dtype), id(spline._coef))
    try:
        cache = _TABLES.setdefault(spline, {})
    except TypeError:  # not weak-referenceable: no cache
        cache = {}
    tab = cache.get(key)
    if tab is None:
        if len(cache) >= 4:
            cache.clear()
        tab = cache[key] = _Table(spline, ops, dtype)
    return tab


#: The eight polynomials of ``bspline_terms`` (four weights, four derivatives) in the power
#: basis ``1, f, f^2, f^3``: six array operations (Horner) instead of some thirty, each a
#: kernel launch on a GPU.
_BSPLINE_POWER = np.array(
    [
        [1 / 6, 2 / 3, 1 / 6, 0.0, -1 / 2, 0.0, 1 / 2, 0.0],
        [-1 / 2, 0.0, 1 / 2, 0.0, 1.0, -2.0, 1.0, 0.0],
        [1 / 2, -1.0, 1 / 2, 0.0, -1 / 2, 3 / 2, -3 / 2, 1 / 2],
        [-1 / 6, 1 / 2, -1 / 2, 1 / 6, 0.0, 0.0, 0.0, 0.0],
    ]
)


def _bspline(f: Any, ops: _NumpyOps | _TorchOps) -> tuple[Any, Any]:
    """Cubic B-spline weights (N, 4) and their derivatives, as ``bspline_weights``."""
    power = getattr(ops, "bspline_power", None)
    if power is None:  # once per backend object: no host-to-device copy per call
        power = ops.bspline_power = ops.asarray(_BSPLINE_POWER)
    c = f[:, None]
    # elementwise in a fixed order (not a BLAS product or a reduction, whose rounding can
    # depend on N): the same weights for an emitter in any batch
    t = power[0] + c * (power[1] + c * (power[2] + c * power[3]))  # (N, 8), Horner
    return t[:, :4], t[:, 4:]


def _axis(ops, t: Any) -> tuple[Any, Any, Any]:
    """First node (N,) of the block an axis reads, and the weights (N, 4).

    Pixel ``j`` reads nodes ``floor(t) - 1 + oversample * j + (0..3)``.
    """
    tf, ti = ops.floor_int(t)
    w, dw = _bspline(t - tf, ops)
    return ti - 1, w, dw


def _render(
    ops: _NumpyOps | _TorchOps,
    tab: _Table,
    x: Any,
    y: Any,
    z: Any,
    ox: Any,
    oy: Any,
    shape: tuple[int, int],
    derivatives: bool,
) -> Any:
    """Unit-photon images (N, R, C) of N emitters, each on its own window (corner ``ox, oy``),
    and with ``derivatives`` also d/dx, d/dy, d/dz (N, 3, R, C), per nm. Arrays in the table's
    dtype; positions (N,) in nm."""
    rows, cols = shape
    p, os_ = tab.pixel_size, tab.oversample
    n = x.shape[0]
    dtype = tab.dtype
    out = ops.zeros((n, rows, cols), dtype=dtype)
    der = ops.zeros((n, 3, rows, cols), dtype=dtype) if derivatives else None
    if n == 0:
        return (out, der) if derivatives else out
    # The arithmetic of SplinePSF._images (in float64 up to the weights).
    tz, tx, ty = table_coords(tab.geometry, x, y, z, ox, oy)
    tzf, iz = ops.floor_int(tz)
    wz, dwz = _bspline(tz - tzf, ops)
    sx, wx, dwx = _axis(ops, tx)
    sy, wy, dwy = _axis(ops, ty)
    wzs = ops.stack([wz, dwz], axis=1) if derivatives else wz[:, None, :]
    wzs, wx, dwx, wy, dwy = (ops.cast(a, dtype) for a in (wzs, wx, dwx, wy, dwy))
    planes = iz[:, None] + ops.arange(4)[None, :]  # (N, 4)
    ly, lx = os_ * (rows - 1) + 4, os_ * (cols - 1) + 4
    chunk = max(1, _chunk_elements(ops) // (4 * ly * lx))
    for s0 in range(0, n, chunk):
        sl = slice(s0, min(s0 + chunk, n))
        block = tab.blocks(planes[sl], sy[sl], sx[sl], ly, lx)  # (k, 4, lx, ly)
        k = block.shape[0]
        pz = (wzs[sl] @ block.reshape(k, 4, lx * ly)).reshape(k, -1, lx, ly)  # P [, dP/dz]
        ax = ops.contract_rows(pz, wx[sl], cols, os_)  # (k, s, cols, ly): P wx [, dP wx]
        if derivatives:
            adx = ops.contract_rows(pz[:, :1], dwx[sl], cols, os_)  # P dwx
            ax = ops.cat([ax, adx], axis=1)  # (k, 3, cols, ly)
        ay = ops.contiguous(ops.transpose(ax))  # (k, s, ly, cols)
        img = ops.contract_rows(ay, wy[sl], rows, os_)  # image [, d/dz, d/dx] (raw)
        out[sl] = img[:, 0]
        if derivatives:
            ddy = ops.contract_rows(ay[:, :1], dwy[sl], rows, os_)[:, 0]  # d/dy (raw)
            der[sl, 0] = -img[:, 2] * os_ / p
            der[sl, 1] = -ddy * os_ / p
            der[sl, 2] = img[:, 1] / tab.z_step
    return (out, der) if derivatives else out


def _check_spline(spline: Any, pixel_size: float | None = None) -> SplinePSF:
    if not isinstance(spline, SplinePSF):
        raise TypeError(
            f"the batched fit needs a SplinePSF (tabulate other models with "
            f"SplinePSF.from_model); got {type(spline).__name__}"
        )
    if pixel_size is not None:
        p = float(pixel_size)
        if not np.isfinite(p) or p <= 0:
            raise ValueError(f"pixel_size must be a positive number of nm, got {pixel_size!r}")
        if abs(p - spline.pixel_size) > 1e-3 * spline.pixel_size:
            raise ValueError(
                f"this PSF was calibrated at {spline.pixel_size:g} nm pixels but "
                f"{p:g} nm was asked for; calibrate at the data's pixel size"
            )
    return spline


def spline_images(
    spline: SplinePSF,
    x: ArrayLike,
    y: ArrayLike,
    z: ArrayLike,
    shape: tuple[int, int],
    origins: ArrayLike,
    *,
    derivatives: bool = False,
    device: Any = None,
    precision: str = "float64",
) -> Any:
    """Unit-photon images of (B, K) emitters, window ``b`` with its own origin.

    Parameters
    ----------
    spline : SplinePSF
        The PSF.
    x, y, z : array_like, shape (B, K)
        Positions (nm). z is held inside the table's planes as ``SplinePSF`` does; it is not
        checked against the model's range.
    shape : (int, int)
        Window shape ``(R, C)`` in pixels (at the spline's pixel size).
    origins : array_like, shape (B, 2)
        Outer corner (nm, x then y) of each window's pixel (0, 0).
    derivatives : bool
        Also return the derivatives.
    device : None, "numpy", "cpu", "cuda", ... or torch.device
        Backend (see the module notes); arrays come back in its type.
    precision : {"float64", "float32"}
        Arithmetic of the rendering.

    Returns
    -------
    images : ndarray or Tensor, shape (B, K, R, C)
        Expected photons per pixel for one photon per emitter.
    derivs : ndarray or Tensor, shape (B, K, 3, R, C)
        Only with ``derivatives``: d/dx, d/dy, d/dz in photons per pixel per nm.
    """
    spline = _check_spline(spline)
    ops = _backend(device)
    xs, ys, zs = (np.asarray(_as_numpy(a), dtype=np.float64) for a in (x, y, z))
    if xs.ndim != 2 or xs.shape != ys.shape or xs.shape != zs.shape:
        raise ValueError(
            f"x, y and z must be (B, K) arrays of one shape; got {xs.shape}, {ys.shape}, {zs.shape}"
        )
    org = np.asarray(_as_numpy(origins), dtype=np.float64)
    if org.shape != (xs.shape[0], 2):
        raise ValueError(f"origins must have shape ({xs.shape[0]}, 2); got {org.shape}")
    if not all(np.all(np.isfinite(a)) for a in (xs, ys, zs, org)):
        raise ValueError("x, y, z and origins must be finite (no NaN or inf)")
    rows, cols = (int(s) for s in shape)
    if rows <= 0 or cols <= 0:
        raise ValueError(f"shape must be (rows, cols) of positive integers, got {shape!r}")
    b, k = xs.shape
    tab = _table(spline, ops, ops.float_dtype(_check_precision(precision)))
    res = _render(
        ops,
        tab,
        ops.asarray(xs.reshape(-1)),
        ops.asarray(ys.reshape(-1)),
        ops.asarray(zs.reshape(-1)),
        ops.asarray(np.repeat(org[:, 0], k)),
        ops.asarray(np.repeat(org[:, 1], k)),
        (rows, cols),
        derivatives,
    )
    if derivatives:
        return res[0].reshape(b, k, rows, cols), res[1].reshape(b, k, 3, rows, cols)
    return res.reshape(b, k, rows, cols)


def _as_numpy(a: Any) -> Any:
    """Tensors (any device) to NumPy; everything else unchanged."""
    if hasattr(a, "detach") and hasattr(a, "cpu"):
        return a.detach().cpu().numpy()
    return a


def _check_precision(precision: str) -> str:
    if precision not in ("float64", "float32"):
        raise ValueError(f"precision must be 'float64' or 'float32'; got {precision!r}")
    return precision


# ---------------------------------------------------------------------------------------------
# The batched fit
# ---------------------------------------------------------------------------------------------
@dataclass
class BatchFitResult:
    """Maximum-likelihood fits of B windows (NumPy arrays whatever the backend).

    Attributes
    ----------
    theta : ndarray, shape (B, Kmax, 4)
        Fitted x, y, z (nm) and photons; NaN for padded emitters.
    sigma : ndarray, shape (B, Kmax, 4)
        CRLB standard errors of x, y, z (nm) and photons at the fit; NaN for padded emitters.
    background : ndarray, shape (B,)
        Constant background (photons/pixel; the plane's value at the window centre).
    background_params : ndarray, shape (B, n_bg)
        ``b`` or ``(b0, bx, by)`` as in :class:`~sparseloc.solvers.refine.FitResult`.
    background_sigma : ndarray, shape (B, n_bg)
        Their standard errors.
    log_likelihood : ndarray, shape (B,)
        ``log L`` up to a data-only constant (``-sum(w (mu - y log mu))``, real pixels only).
    deviance_per_dof : ndarray, shape (B,)
        Goodness of fit (about 1 for a good fit).
    flags : ndarray of str, shape (B, Kmax)
        ``"ok"``, ``"z_edge"``, ``"outside"``, ``"not_converged"`` or ``"diverged"`` as in
        :func:`fit_emitters`; ``""`` for padded emitters.
    converged : ndarray of bool, shape (B,)
    n_iter : ndarray of int, shape (B,)
        Levenberg-Marquardt iterations of each window.
    n_emitters : ndarray of int, shape (B,)
    model_image : ndarray, shape (B, R, C)
        Expected photons per pixel at the fit (with the offsets), padded pixels included.
    device : str
        Where the fit ran (``"numpy"``, ``"cpu"``, ``"cuda:0"``, ...).
    seconds : float
        Wall time of the fit.
    """

    theta: NDArray[np.float64]
    sigma: NDArray[np.float64]
    background: NDArray[np.float64]
    background_params: NDArray[np.float64]
    background_sigma: NDArray[np.float64]
    log_likelihood: NDArray[np.float64]
    deviance_per_dof: NDArray[np.float64]
    flags: NDArray[np.str_]
    converged: NDArray[np.bool_]
    n_iter: NDArray[np.int64]
    n_emitters: NDArray[np.int64]
    model_image: NDArray[np.float64]
    device: str
    seconds: float

    @property
    def nll(self) -> NDArray[np.float64]:
        """Negative log-likelihood per window, shape (B,)."""
        return -self.log_likelihood

    def __len__(self) -> int:
        return int(self.theta.shape[0])

    def emitters(self, b: int) -> Emitters:
        """The real emitters of window ``b``."""
        return Emitters.from_array(self.theta[b, : self.n_emitters[b]])

    def fit_result(self, b: int) -> FitResult:
        """Window ``b`` as the :class:`FitResult` that :func:`fit_emitters` returns (its
        ``model_image`` keeps the padded shape)."""
        k = int(self.n_emitters[b])
        return FitResult(
            emitters=self.emitters(b),
            sigma=self.sigma[b, :k].copy(),
            background=self.background_params[b].copy(),
            background_sigma=self.background_sigma[b].copy(),
            model_image=self.model_image[b].copy(),
            log_likelihood=float(self.log_likelihood[b]),
            deviance_per_dof=float(self.deviance_per_dof[b]),
            flags=self.flags[b, :k].copy(),
            converged=bool(self.converged[b]),
            n_iter=int(self.n_iter[b]),
        )


class _Batch:
    """A chunk of windows on a backend: its data, its constants and the model evaluations.

    ``theta`` rows are ``[x0, y0, z0, N0, x1, ..., N_{Kmax-1}, b...]`` (P = 4 Kmax + n_bg).
    """

    def __init__(self, ops, tab: _Table, d: dict[str, Any], weight: float, n_bg: int) -> None:
        self.ops = ops
        self.tab = tab
        self.weight = weight
        self.n_bg = n_bg
        self.shape = tuple(d["y"].shape[1:])
        self.kmax = d["emask"].shape[1]
        a = ops.asarray
        self.valid = a(d["valid"])  # (B, R, C): 1.0 on real pixels, 0.0 on padded ones
        self.valid_b = a(d["valid"] > 0, dtype=ops.bool)
        self.v = a(d["v"])
        self.yv = a(d["y"] + d["v"])
        self.offset = a(d["offset"])
        self.basis = a(d["basis"])  # (B, n_bg, R, C)
        self.emask = a(d["emask"], dtype=ops.bool)  # (B, K)
        self.pad = a(d["pad"])  # (B, P): 1.0 for the parameters of padded emitters
        self.lo = a(d["lo"])  # (B, 4): x, y, z, photons lower bounds
        self.hi = a(d["hi"])  # (B, 4)
        self.ox = a(np.repeat(d["origins"][:, 0], self.kmax))  # (B * K,)
        self.oy = a(np.repeat(d["origins"][:, 1], self.kmax))

    def model(self, idx: Any, theta: Any, derivatives: bool) -> tuple[Any, Any]:
        """mu (n, R, C) of windows ``idx`` (n,) at ``theta`` (n, P) and, with
        ``derivatives``, the Jacobian (n, P, R * C)."""
        ops, k = self.ops, self.kmax
        n = theta.shape[0]
        rows, cols = self.shape
        em = theta[:, : 4 * k].reshape(n * k, 4)
        b = theta[:, 4 * k :]
        flat = (idx[:, None] * k + ops.arange(k)[None, :]).reshape(-1)  # (n * K,)
        sel = ops.nonzero(self.emask[idx].reshape(-1))
        e, src = em[sel], flat[sel]
        res = _render(
            ops,
            self.tab,
            e[:, 0],
            e[:, 1],
            e[:, 2],
            self.ox[src],
            self.oy[src],
            self.shape,
            derivatives,
        )
        img, der = res if derivatives else (res, None)
        img = ops.cast(img, ops.float)
        basis = self.basis[idx]
        bg = basis[:, 0] * b[:, 0, None, None]
        for j in range(1, self.n_bg):
            bg = bg + basis[:, j] * b[:, j, None, None]
        full = ops.zeros((n * k, rows, cols))
        full[sel] = img * e[:, 3, None, None]
        mu = (bg + self.offset[idx]) + ops.sum(full.reshape(n, k, rows, cols), axis=1)
        if not derivatives:
            return mu, None
        # One (n, P, R * C) array: emitter j of window i owns rows 4 j .. 4 j + 3.
        jac = ops.zeros((n, 4 * k + self.n_bg, rows * cols))
        jac[:, 4 * k :] = basis.reshape(n, self.n_bg, rows * cols)
        wi, row0 = sel // k, 4 * (sel % k)
        dn = ops.cast(der, ops.float).reshape(-1, 3, rows * cols) * e[:, 3, None, None]
        for j in range(3):
            jac[wi, row0 + j] = dn[:, j]
        jac[wi, row0 + 3] = img.reshape(-1, rows * cols)
        return mu, jac

    def nll(self, idx: Any, mu: Any) -> Any:
        """-log L (n,) without the data-only constant; inf where ``mu + v`` is not positive
        and finite on every real pixel."""
        ops = self.ops
        muv = mu + self.v[idx]
        valid = self.valid_b[idx]
        good = ((muv > 0) & ops.isfinite(muv)) | ~valid
        safe = ops.where(valid & good, muv, 1.0)
        terms = (safe - self.yv[idx] * ops.log(safe)) * self.valid[idx]
        f = self.weight * ops.sum(terms, axis=(1, 2))
        return ops.where(ops.all(good, axis=(1, 2)), f, float("inf"))

    def grad_fisher(self, idx: Any, mu: Any, jac: Any) -> tuple[Any, Any]:
        """Gradient (n, P) and Fisher matrix (n, P, P) of -log L. Padded emitters' parameters
        get a unit diagonal: they are decoupled from the others and their step is zero."""
        ops = self.ops
        n = mu.shape[0]
        valid = self.valid[idx].reshape(n, -1)
        muv = ops.where(valid > 0, (mu + self.v[idx]).reshape(n, -1), 1.0)
        r = valid * (1.0 - self.yv[idx].reshape(n, -1) / muv)
        grad = self.weight * (jac @ r[:, :, None])[:, :, 0]
        fisher = self.weight * ((jac * (valid / muv)[:, None, :]) @ ops.transpose(jac))
        return grad, fisher + ops.diag_embed(self.pad[idx])

    def clamp(self, idx: Any, theta: Any) -> Any:
        """x, y within the window +- margin, z in the model's range, photons >= 1,
        background >= 1e-3 (as :func:`fit_emitters`)."""
        ops, k = self.ops, self.kmax
        n = theta.shape[0]
        em = (
            theta[:, : 4 * k]
            .reshape(n, k, 4)
            .clip(self.lo[idx][:, None, :], self.hi[idx][:, None, :])
        )
        b = theta[:, 4 * k :]
        return ops.cat([em.reshape(n, 4 * k), b[:, :1].clip(_MIN_BG, None), b[:, 1:]], axis=1)


def _fit_chunk(
    ops, tab: _Table, d: dict[str, Any], weight: float, n_bg: int, max_iter: int, tol: float
) -> dict[str, NDArray]:
    """Levenberg-Marquardt on one chunk of windows (the loop of :func:`fit_emitters`, per
    window, on all windows at once). Returns NumPy arrays."""
    batch = _Batch(ops, tab, d, weight, n_bg)
    n = d["y"].shape[0]
    k = batch.kmax
    allidx = ops.arange(n)
    theta = ops.copy(ops.asarray(d["theta0"]))
    if d["estimate_bg"].any():
        # Starting background as fit_emitters: median of the window minus the starting
        # emitters (unclamped) and the offset, at least 1 photon.
        zero_bg = ops.cat([theta[:, : 4 * k], ops.zeros((n, n_bg))], axis=1)
        mu0 = ops.to_numpy(batch.model(allidx, zero_bg, False)[0])
        resid = np.where(d["valid"] > 0, d["y"] - mu0, np.nan)
        est = np.maximum(np.nanmedian(resid.reshape(n, -1), axis=1), 1.0)
        b0 = np.where(d["estimate_bg"], est, d["theta0"][:, 4 * k])
        theta[:, 4 * k] = ops.asarray(b0)
    theta = batch.clamp(allidx, theta)
    mu, jac = batch.model(allidx, theta, True)
    f = batch.nll(allidx, mu)
    lam = ops.full((n,), 1e-3)
    converged = ops.zeros((n,), dtype=ops.bool)
    n_iter = ops.zeros((n,), dtype=ops.index(0).dtype)
    active = allidx
    for it in range(1, max_iter + 1):
        m = int(active.shape[0])
        if m == 0:
            break
        n_iter[active] = it
        grad, fisher = batch.grad_fisher(active, mu[active], jac[active])
        diag = ops.diagonal(fisher).clip(1e-12, None)
        th_a, f_a, lam_a = theta[active], f[active], lam[active]
        found = ops.zeros((m,), dtype=ops.bool)
        new_theta = ops.copy(th_a)
        new_mu = ops.zeros((m, *batch.shape))
        new_f = ops.copy(f_a)
        search = ops.arange(m)
        has_jac = ops.zeros((m,), dtype=ops.bool)
        for trial_no in range(_TRIALS):
            if int(search.shape[0]) == 0:
                break
            a = fisher[search] + lam_a[search][:, None, None] * ops.diag_embed(diag[search])
            step, ok = ops.solve(a, -grad[search])
            trial = batch.clamp(active[search], th_a[search] + step)
            ok = ok & ops.all(ops.isfinite(trial), axis=1)
            trial = ops.where(ok[:, None], trial, th_a[search])
            # Most steps pass at the first damping: render its Jacobian along (it is the next
            # iteration's); later trials render images only.
            first = trial_no == 0
            mu_t, jac_t = batch.model(active[search], trial, first)
            f_t = ops.where(ok, batch.nll(active[search], mu_t), float("inf"))
            better = f_t < f_a[search]
            hit = search[better]
            new_theta[hit] = trial[better]
            new_mu[hit] = mu_t[better]
            new_f[hit] = f_t[better]
            found[hit] = True
            if first:
                jac[active[hit]] = jac_t[better]
                has_jac[hit] = True
            miss = search[~better]
            lam_a[miss] = lam_a[miss] * 10.0
            search = miss
        # No step lowers -log L: a (constrained) optimum.
        converged[active[~found]] = True
        acc = ops.nonzero(found)
        if int(acc.shape[0]) == 0:
            active = acc
            break
        ia = active[acc]
        rel = (f[ia] - new_f[acc]) / abs(f[ia]).clip(1.0, None)
        theta[ia] = new_theta[acc]
        f[ia] = new_f[acc]
        mu[ia] = new_mu[acc]
        lam[ia] = (lam_a[acc] / 10.0).clip(1e-7, None)
        late = ops.nonzero(found & ~has_jac)
        if int(late.shape[0]):
            il = active[late]
            jac[il] = batch.model(il, theta[il], True)[1]
        done = rel < tol
        converged[ia[done]] = True
        active = ia[~done]
    _, fisher = batch.grad_fisher(allidx, mu, jac)
    var = ops.diagonal(ops.inv(fisher))
    out = {
        "theta": ops.to_numpy(theta),
        "var": ops.to_numpy(var),
        "f": ops.to_numpy(f),
        "mu": ops.to_numpy(mu),
        "converged": ops.to_numpy(converged).astype(bool),
        "n_iter": ops.to_numpy(n_iter).astype(np.int64),
    }
    return out


def _prepare(
    windows,
    starts,
    n_emitters,
    spline,
    pixel_size,
    origins,
    offsets,
    background,
    noise,
    read_variance,
    mask,
    plane,
    xy_margin,
) -> dict[str, Any]:
    """Validate the inputs (ValueError naming the problem) and lay out NumPy arrays."""
    if noise not in NOISE_MODELS:
        raise ValueError(f"noise must be one of {', '.join(NOISE_MODELS)}; got {noise!r}")
    y = np.asarray(_as_numpy(windows), dtype=np.float64)
    if y.ndim != 3:
        raise ValueError(f"windows must be a (B, rows, cols) stack of windows; got shape {y.shape}")
    nb, rows, cols = y.shape
    if nb == 0:
        raise ValueError("windows is empty: there is nothing to fit")
    st = np.asarray(_as_numpy(starts), dtype=np.float64)
    if st.ndim != 3 or st.shape[0] != nb or st.shape[2] != 4:
        raise ValueError(
            f"starts must have shape (B, Kmax, 4) = ({nb}, Kmax, 4) (x, y, z in nm, photons); "
            f"got {st.shape}"
        )
    kmax = st.shape[1]
    if n_emitters is None:
        ne = np.full(nb, kmax, dtype=np.int64)
    else:
        ne_raw = np.asarray(_as_numpy(n_emitters))
        if ne_raw.shape != (nb,):
            raise ValueError(f"n_emitters must have shape ({nb},); got {ne_raw.shape}")
        if not np.all(np.isfinite(ne_raw.astype(np.float64))) or np.any(ne_raw != np.round(ne_raw)):
            raise ValueError("n_emitters must hold whole numbers")
        ne = ne_raw.astype(np.int64)
        if np.any(ne < 0) or np.any(ne > kmax):
            raise ValueError(f"n_emitters must lie between 0 and Kmax = {kmax}")
    emask = np.arange(kmax)[None, :] < ne[:, None]
    org = np.asarray(_as_numpy(origins), dtype=np.float64)
    if org.shape != (nb, 2):
        raise ValueError(f"origins must have shape ({nb}, 2) (x, y in nm); got {org.shape}")
    if not np.all(np.isfinite(org)):
        raise ValueError("origins must be finite (no NaN or inf)")
    if mask is None:
        valid = np.ones(y.shape, dtype=bool)
    else:
        valid = np.asarray(_as_numpy(mask))
        if valid.shape != y.shape:
            raise ValueError(f"mask must have the windows' shape {y.shape}; got {valid.shape}")
        valid = valid.astype(bool)
    nvalid = valid.sum(axis=(1, 2))
    if np.any(nvalid == 0):
        raise ValueError(f"window {int(np.argmin(nvalid))} has no real pixel in its mask")
    if not np.all(np.isfinite(y[valid])):
        raise ValueError("the windows contain NaN or inf values (on pixels the mask keeps)")
    if noise != "scmos" and np.any(y[valid] < -1e-9):
        raise ValueError("the windows have negative photon counts; convert ADU to photons first")
    y = np.where(valid, y, 0.0)
    if not np.all(np.isfinite(st[emask])):
        raise ValueError("starts must be finite (no NaN or inf) for the real emitters")
    if offsets is None:
        off = np.zeros(y.shape)
    else:
        try:
            off = np.broadcast_to(np.asarray(_as_numpy(offsets), dtype=np.float64), y.shape)
        except ValueError as exc:
            raise ValueError(
                f"offsets must have the windows' shape {y.shape}; got {np.shape(offsets)}"
            ) from exc
        if not np.all(np.isfinite(off[valid])):
            raise ValueError("offsets must be finite (no NaN or inf)")
        off = np.where(valid, off, 0.0)
    if noise == "scmos":
        if read_variance is None:
            raise ValueError("noise='scmos' needs read_variance (photons^2, scalar or map)")
        try:
            v = np.broadcast_to(np.asarray(_as_numpy(read_variance), dtype=np.float64), y.shape)
        except ValueError as exc:
            raise ValueError(
                f"read_variance must be a scalar or broadcast to the windows' shape {y.shape}; "
                f"got {np.shape(read_variance)}"
            ) from exc
        if not np.all(np.isfinite(v[valid])):
            raise ValueError("read_variance must be finite (no NaN or inf)")
        if np.any(v[valid] < 0):
            raise ValueError("read_variance must be >= 0")
        v = np.where(valid, v, 0.0)
    else:
        if read_variance is not None:
            raise ValueError("read_variance is only used with noise='scmos'")
        v = np.zeros(y.shape)
    margin = float(xy_margin)
    if not np.isfinite(margin) or margin < 0:
        raise ValueError(f"xy_margin must be a non-negative number of pixels; got {xy_margin!r}")
    # Each window's extent: the bounding box of its real pixels.
    rows_any = valid.any(axis=2)
    cols_any = valid.any(axis=1)
    r0 = rows_any.argmax(axis=1)
    r1 = rows - rows_any[:, ::-1].argmax(axis=1)
    c0 = cols_any.argmax(axis=1)
    c1 = cols - cols_any[:, ::-1].argmax(axis=1)
    px = float(pixel_size)
    m = margin * px
    zlo, zhi = spline.z_range
    wx0, wx1 = org[:, 0] + c0 * px, org[:, 0] + c1 * px
    wy0, wy1 = org[:, 1] + r0 * px, org[:, 1] + r1 * px
    lo = np.stack([wx0 - m, wy0 - m, np.full(nb, zlo), np.full(nb, _MIN_PHOTONS)], axis=1)
    hi = np.stack([wx1 + m, wy1 + m, np.full(nb, zhi), np.full(nb, np.inf)], axis=1)
    n_bg = 3 if plane else 1
    basis = np.zeros((nb, n_bg, rows, cols))
    basis[:, 0] = 1.0
    if plane:
        nr, nc = r1 - r0, c1 - c0
        cc = np.arange(cols)[None, :] - c0[:, None]
        rr = np.arange(rows)[None, :] - r0[:, None]
        u = (cc - (nc[:, None] - 1) / 2) / np.maximum(nc[:, None] / 2, 1)
        w = (rr - (nr[:, None] - 1) / 2) / np.maximum(nr[:, None] / 2, 1)
        basis[:, 1] = np.where(valid, u[:, None, :], 0.0)
        basis[:, 2] = np.where(valid, w[:, :, None], 0.0)
    if background is None:
        b0 = np.full(nb, np.nan)
        estimate = np.ones(nb, dtype=bool)
    else:
        try:
            b0 = np.broadcast_to(np.asarray(_as_numpy(background), dtype=np.float64), (nb,))
        except ValueError as exc:
            raise ValueError(
                f"background must be a scalar or have shape ({nb},); got {np.shape(background)}"
            ) from exc
        estimate = ~np.isfinite(b0)  # NaN: estimate that window's start
        b0 = np.where(estimate, np.nan, b0)
    # Padded emitters: harmless finite values (they are never rendered and never move).
    centre = np.stack([(wx0 + wx1) / 2, (wy0 + wy1) / 2], axis=1)
    filler = np.concatenate([centre, np.full((nb, 1), (zlo + zhi) / 2), np.ones((nb, 1))], axis=1)
    em0 = np.where(emask[:, :, None], st, filler[:, None, :])
    theta0 = np.concatenate([em0.reshape(nb, 4 * kmax), np.zeros((nb, n_bg))], axis=1)
    theta0[:, 4 * kmax] = np.where(estimate, 0.0, b0)
    pad = np.concatenate(
        [np.repeat(~emask, 4, axis=1).astype(np.float64), np.zeros((nb, n_bg))], axis=1
    )
    yv = y + v
    sat = np.sum(
        np.where(valid & (yv > 0), yv * np.log(np.where(yv > 0, yv, 1.0)), 0.0)
        - np.where(valid, yv, 0.0),
        axis=(1, 2),
    )
    return {
        "y": y,
        "v": v,
        "valid": valid.astype(np.float64),
        "offset": off,
        "basis": basis,
        "emask": emask,
        "pad": pad,
        "lo": lo,
        "hi": hi,
        "origins": org,
        "theta0": theta0,
        "estimate_bg": estimate,
        "n_emitters": ne,
        "n_valid": nvalid,
        "sat": sat,
        "box": np.stack([wx0, wx1, wy0, wy1], axis=1),
        "z_range": (zlo, zhi),
    }


def _take(d: dict[str, Any], sl: slice) -> dict[str, Any]:
    return {
        key: (val[sl] if isinstance(val, np.ndarray) and val.ndim >= 1 else val)
        for key, val in d.items()
    }


def fit_batch(
    windows: ArrayLike,
    starts: ArrayLike,
    n_emitters: ArrayLike | None,
    spline: SplinePSF,
    *,
    pixel_size: float,
    origins: ArrayLike,
    offsets: ArrayLike | None = None,
    background: float | ArrayLike | None = None,
    mask: ArrayLike | None = None,
    plane: bool = False,
    noise: str = "poisson",
    read_variance: float | ArrayLike | None = None,
    max_iter: int = 60,
    tol: float = 1e-6,
    xy_margin: float = 1.0,
    device: Any = None,
    precision: str = "float64",
    chunk: int | None = None,
    qe: float = 1.0,
) -> BatchFitResult:
    """Maximum-likelihood fits of K emitters plus a background in each of B windows.

    Every window is fitted as :func:`~sparseloc.solvers.refine.fit_emitters` fits one (same
    start, same steps, same stopping rule, same clamping, same uncertainties and flags); the
    windows share only the array operations.

    Parameters
    ----------
    windows : array_like, shape (B, R, C)
        Windows in photons, padded to one shape (see ``mask``).
    starts : array_like, shape (B, Kmax, 4)
        Starting x, y, z (nm) and photons; rows beyond ``n_emitters[b]`` are ignored (they
        may hold anything, NaN included).
    n_emitters : array_like of int, shape (B,), or None
        Real emitters per window (0 fits the background alone); ``None``: all ``Kmax``.
    spline : SplinePSF
        The PSF (tabulate a pupil model with :meth:`SplinePSF.from_model`).
    pixel_size : float
        Pixel size (nm); must be the spline's.
    origins : array_like, shape (B, 2)
        Outer corner (nm, x then y) of each window's pixel (0, 0).
    offsets : array_like, shape (B, R, C), optional
        Known expected light (photons/pixel) added to each model and not fitted.
    background : float or array_like, shape (B,), optional
        Starting background (photons/pixel); estimated from each window (as
        :func:`fit_emitters` does) when ``None`` or, per window, NaN.
    mask : array_like of bool, shape (B, R, C), optional
        True on real pixels; padded (False) pixels take no part in the fit. Default all real.
    plane : bool
        Fit a tilted-plane background instead of a constant.
    noise : {"poisson", "emccd", "scmos"}
        Likelihood (see :mod:`sparseloc.solvers.refine`).
    read_variance : float or array_like, optional
        sCMOS read-noise variance (photons^2): a scalar, (R, C) or (B, R, C).
    max_iter : int
        Levenberg-Marquardt iterations (per window).
    tol : float
        A window stops when the relative decrease of its ``-log L`` is below this.
    xy_margin : float
        How far (pixels) an emitter may leave its window.
    device : None, "numpy", "cpu", "cuda", "cuda:N" or torch.device
        Backend: NumPy (default) or PyTorch on that device (torch imported only then).
    precision : {"float64", "float32"}
        Arithmetic of the PSF rendering (everything else is float64).
    chunk : int, optional
        Windows fitted together (bounds the memory: about ``chunk * (4 Kmax + n_bg) * R * C``
        doubles for the Jacobian); default 1024 on the CPU, 16384 on CUDA.
    qe : float
        Quantum efficiency in (0, 1] (see :func:`~sparseloc.solvers.refine.fit_emitters`).

    Returns
    -------
    BatchFitResult

    Raises
    ------
    ValueError
        Shapes that do not match, NaN or inf in the data, negative counts (except sCMOS), an
        unknown noise model, a pixel size other than the spline's.
    TypeError
        ``spline`` is not a :class:`SplinePSF`.
    """
    t0 = time.perf_counter()
    spline = _check_spline(spline, pixel_size)
    _check_precision(precision)
    if int(max_iter) < 0:
        raise ValueError(f"max_iter must be >= 0 (0: evaluate the starts); got {max_iter!r}")
    if not np.isfinite(tol) or tol < 0:
        raise ValueError(f"tol must be a non-negative number; got {tol!r}")
    if chunk is not None and int(chunk) < 1:
        raise ValueError(f"chunk must be at least 1; got {chunk!r}")
    weight = likelihood_weight(noise, qe) if noise in NOISE_MODELS else 1.0
    if read_variance is not None and check_qe(qe) != 1.0:
        # on the photoelectron scale of the likelihood (see refine's module notes)
        read_variance = np.asarray(_as_numpy(read_variance), dtype=np.float64) * float(qe)
    d = _prepare(
        windows,
        starts,
        n_emitters,
        spline,
        pixel_size,
        origins,
        offsets,
        background,
        noise,
        read_variance,
        mask,
        plane,
        xy_margin,
    )
    ops = _backend(device)
    tab = _table(spline, ops, ops.float_dtype(precision))
    if chunk is None:
        chunk = 16384 if ops.kind == "torch" and ops.device.type == "cuda" else 1024
    n_bg = 3 if plane else 1
    nb = d["y"].shape[0]
    kmax = d["emask"].shape[1]
    parts = []
    for s0 in range(0, nb, int(chunk)):
        sl = slice(s0, min(s0 + int(chunk), nb))
        parts.append(_fit_chunk(ops, tab, _take(d, sl), weight, n_bg, int(max_iter), float(tol)))
    res = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    out = _collect(d, res, kmax, n_bg, weight, ops.device_name, time.perf_counter() - t0)
    log.debug(
        "fit_batch: %d windows, %d emitters on %s in %.3f s; %d converged, mean %.1f iterations",
        nb,
        int(d["n_emitters"].sum()),
        ops.device_name,
        out.seconds,
        int(out.converged.sum()),
        float(out.n_iter.mean()),
    )
    return out


def _collect(
    d, res, kmax: int, n_bg: int, weight: float, device: str, seconds: float
) -> BatchFitResult:
    """NumPy results, uncertainties and flags as :func:`fit_emitters` reports them."""
    nb = res["theta"].shape[0]
    emask = d["emask"]
    em = res["theta"][:, : 4 * kmax].reshape(nb, kmax, 4).copy()
    em[~emask] = np.nan
    bgp = res["theta"][:, 4 * kmax :].copy()
    var = res["var"]
    sd = np.sqrt(np.where(var > 0, var, np.nan))
    sigma = sd[:, : 4 * kmax].reshape(nb, kmax, 4).copy()
    sigma[~emask] = np.nan
    bg_sd = sd[:, 4 * kmax :]
    converged = res["converged"]
    zlo, zhi = d["z_range"]
    box = d["box"]
    with np.errstate(invalid="ignore"):
        at_edge = (em[..., 2] <= zlo + 1.0) | (em[..., 2] >= zhi - 1.0)
        outside = (
            (em[..., 0] < box[:, :1])
            | (em[..., 0] > box[:, 1:2])
            | (em[..., 1] < box[:, 2:3])
            | (em[..., 1] > box[:, 3:4])
        )
        bad = ~np.all(np.isfinite(em), axis=2) | (em[..., 3] <= _MIN_PHOTONS * 1.01)
    flags = np.full((nb, kmax), "ok", dtype="<U16")
    flags[at_edge] = "z_edge"
    flags[outside] = "outside"
    flags[(flags == "ok") & ~converged[:, None]] = "not_converged"
    flags[bad] = "diverged"
    flags[~emask] = ""
    mu = res["mu"]
    valid = d["valid"]
    yv = d["y"] + d["v"]
    muv = np.where(valid > 0, mu + d["v"], 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        dev = 2.0 * weight * (d["sat"] - np.sum(valid * (yv * np.log(muv) - muv), axis=(1, 2)))
    dof = np.maximum(d["n_valid"] - (4 * d["n_emitters"] + n_bg), 1)
    # The plane's value at the window centre is b0 (its coordinates are centred).
    return BatchFitResult(
        theta=em,
        sigma=sigma,
        background=bgp[:, 0].copy(),
        background_params=bgp,
        background_sigma=bg_sd,
        log_likelihood=-res["f"],
        deviance_per_dof=dev / dof,
        flags=flags,
        converged=converged,
        n_iter=res["n_iter"],
        n_emitters=d["n_emitters"].copy(),
        model_image=mu,
        device=device,
        seconds=seconds,
    )
