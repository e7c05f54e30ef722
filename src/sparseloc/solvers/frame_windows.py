"""Windows of the frame solver: groups of emitters, their windows, and the light of their
neighbours held fixed in each window's fit; the memory of moves that failed."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..psf.base import PSFModel
from .variance import cropped_maps

__all__ = [
    "FLIP_MEMORY_NM",
    "MAX_GROUP",
    "NeighbourLight",
    "background_shape",
    "emitter_groups",
    "inside",
    "light_pieces",
    "lost_flip_near",
    "near_window",
    "region_window",
    "split_group",
    "sum_pieces",
    "window_box",
    "window_boxes",
    "window_data",
    "window_kwargs",
]


def split_group(idx: NDArray[np.intp], xy: NDArray, max_size: int) -> list[NDArray[np.intp]]:
    """Halve a group across the longer side of its bounding box until no part exceeds
    ``max_size`` (the parts' neighbours are held fixed in each fit, so splitting costs
    little accuracy and keeps each fit small)."""
    if len(idx) <= max_size:
        return [idx]
    p = xy[idx]
    axis = int(np.argmax(np.ptp(p, axis=0)))
    order = idx[np.argsort(p[:, axis], kind="stable")]
    half = len(order) // 2
    return split_group(order[:half], xy, max_size) + split_group(order[half:], xy, max_size)


#: Most emitters the frame solver fits together: larger groups are split (a dense field
#: would otherwise make one huge fit; memory and time grow with its square).
MAX_GROUP = 8


def emitter_groups(
    xy: NDArray, distance: float, max_size: int = MAX_GROUP
) -> list[NDArray[np.intp]]:
    """Connected components of points closer than ``distance``, split into parts of at most
    ``max_size``."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    if len(xy) == 0:
        return []
    pairs = cKDTree(xy).query_pairs(distance, output_type="ndarray")
    from scipy.sparse import coo_matrix

    n = len(xy)
    adj = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(adj, directed=False)
    out: list[NDArray[np.intp]] = []
    for k in range(labels.max() + 1):
        out.extend(split_group(np.flatnonzero(labels == k), xy, max_size))
    return out


#: A z flip (or a relocation) that failed is not tried again for an emitter within these
#: distances (nm, lateral and axial) of where it failed, later on the same frame.
FLIP_MEMORY_NM = (20.0, 50.0)


def lost_flip_near(failed: list[NDArray] | None, xyz: NDArray) -> bool:
    """Whether an emitter (x, y, z in nm) is within :data:`FLIP_MEMORY_NM` of a position where
    a z flip (or a relocation) lost."""
    if not failed:
        return False
    f = np.asarray(failed)
    lat, ax = FLIP_MEMORY_NM
    return bool(
        np.any(
            (np.hypot(f[:, 0] - xyz[0], f[:, 1] - xyz[1]) <= lat) & (np.abs(f[:, 2] - xyz[2]) <= ax)
        )
    )


def inside(arr: NDArray, box: tuple[int, int, int, int], pixel_size: float) -> NDArray[np.bool_]:
    """(K,): whether each emitter of ``arr`` (K, 4+) lies on the pixels ``box``."""
    r0, r1, c0, c1 = box
    c, r = arr[:, 0] / pixel_size, arr[:, 1] / pixel_size
    return (r >= r0) & (r < r1) & (c >= c0) & (c < c1)


def near_window(xy: NDArray[np.float64], box: tuple[int, int, int, int], px: float, reach: float):
    """Which points (N, 2+; nm) lie within ``reach`` (nm, per axis) of a window (r0, r1, c0,
    c1 in pixels): the emitters whose light goes into the window's offset."""
    r0, r1, c0, c1 = box
    return (
        (xy[:, 0] > c0 * px - reach)
        & (xy[:, 0] < c1 * px + reach)
        & (xy[:, 1] > r0 * px - reach)
        & (xy[:, 1] < r1 * px + reach)
    )


def window_box(em: NDArray[np.float64], rows: int, cols: int, px: float, pad: int) -> tuple:
    """Window (r0, r1, c0, c1) of a group's emitters (K, 4 in nm): their pixels and ``pad``
    more each way, inside the frame (:func:`window_boxes` of one group)."""
    x, y = em[:, 0], em[:, 1]
    box = window_boxes(x.min(), x.max(), y.min(), y.max(), rows, cols, px, pad)
    return tuple(int(v) for v in box)


def window_boxes(x0, x1, y0, y1, rows: int, cols: int, px: float, pad: int) -> tuple:
    """Windows (r0, r1, c0, c1) of groups whose emitters span ``x0..x1``, ``y0..y1`` (nm,
    numbers or arrays of one value per group): their pixels and ``pad`` more each way, inside
    the frame; whole numbers as floats, of the inputs' shape."""
    r0 = np.clip(np.floor(y0 / px) - pad, 0, rows - 1)
    r1 = np.clip(np.ceil(y1 / px) + pad + 1, r0 + 1, rows)
    c0 = np.clip(np.floor(x0 / px) - pad, 0, cols - 1)
    c1 = np.clip(np.ceil(x1 / px) + pad + 1, c0 + 1, cols)
    return r0, r1, c0, c1


def light_pieces(
    model: PSFModel,
    em: NDArray,
    shape: tuple[int, int],
    px: float,
    origin: tuple[float, float],
    reach: float,
) -> list[tuple[tuple[int, int, int, int], NDArray[np.float64]] | None]:
    """Each emitter's (K, 4) image (photons/pixel) on the window's pixels within ``reach``
    (nm, per axis) of it: its box (r0, r1, c0, c1) in the window and the image there; None
    for an emitter out of reach of the window."""
    rows, cols = shape
    out: list = []
    for x, y, z, n in np.asarray(em, dtype=np.float64).reshape(-1, 4):
        c0 = max(int(np.floor((x - reach - origin[0]) / px)), 0)
        c1 = min(int(np.ceil((x + reach - origin[0]) / px)) + 1, cols)
        r0 = max(int(np.floor((y - reach - origin[1]) / px)), 0)
        r1 = min(int(np.ceil((y + reach - origin[1]) / px)) + 1, rows)
        if r1 <= r0 or c1 <= c0:
            out.append(None)
            continue
        o = (origin[0] + c0 * px, origin[1] + r0 * px)
        img = model.render([x], [y], [z], [n], (r1 - r0, c1 - c0), px, origin=o)
        out.append(((r0, r1, c0, c1), img))
    return out


def sum_pieces(pieces, box: tuple[int, int, int, int]) -> NDArray[np.float64]:
    """Sum of :func:`light_pieces` over a box (r0, r1, c0, c1) of their window."""
    r0, r1, c0, c1 = box
    out = np.zeros((r1 - r0, c1 - c0))
    for piece in pieces:
        if piece is None:
            continue
        (a0, a1, b0, b1), img = piece
        i0, i1, j0, j1 = max(a0, r0), min(a1, r1), max(b0, c0), min(b1, c1)
        if i1 > i0 and j1 > j0:
            out[i0 - r0 : i1 - r0, j0 - c0 : j1 - c0] += img[i0 - a0 : i1 - a0, j0 - b0 : j1 - b0]
    return out


class NeighbourLight:
    """The light of a frame's emitters in any window, summed from one image per emitter.

    A sweep renders its neighbours' light into every group's window, and most neighbours
    are the same emitters, unmoved, from window to window and sweep to sweep. For a spline
    model each emitter's image is rendered once per position, over the box beyond which the
    model is exactly zero (:meth:`~sparseloc.psf.spline.SplinePSF.zero_beyond`), and cropped
    into each window: the same values as rendering them there (to rounding); on 4 dense
    frames the sweeps' offsets took 0.77 s instead of 1.85 s (profiled, one process). Other
    models render into the window directly. ``fixed`` (photons/pixel, the frame's shape):
    light known besides the emitters' (bright emitters' halos), added in every window.
    """

    def __init__(
        self, model: PSFModel, shape: tuple[int, int], px: float, fixed: NDArray | None = None
    ):
        from ..psf.spline import SplinePSF

        self.model, self.shape, self.px = model, shape, px
        self.fixed = fixed
        self.extent = model.zero_beyond(px) if isinstance(model, SplinePSF) else None
        self._pieces: dict[bytes, tuple] = {}

    def _render(self, rows: NDArray) -> None:
        """Images of emitters (K, 4) not seen yet, in one call: each over a box of the same
        shape from the pixel before its extent begins (the boxes may reach past the frame;
        the sums crop them)."""
        px = self.px
        r0, c0, wy, wx = self._boxes(rows)
        # positions relative to each box: one window shape serves them all
        imgs = self.model.images(
            rows[:, 0] - c0 * px, rows[:, 1] - r0 * px, rows[:, 2], (wy, wx), px
        )
        for row, a, b, img in zip(rows, r0.astype(int), c0.astype(int), imgs, strict=True):
            self._pieces[row.tobytes()] = ((a, a + wy, b, b + wx), row[3] * img)

    def window(self, em: NDArray, box: tuple[int, int, int, int]) -> NDArray[np.float64]:
        """(r1 - r0, c1 - c0): the light of emitters ``em`` (K, 4) and the fixed light on
        the frame's pixels ``box`` (r0, r1, c0, c1)."""
        em = np.ascontiguousarray(em, dtype=np.float64).reshape(-1, 4)
        light = self._emitters(em, box)
        return light if self.fixed is None else light + self.known(box)

    def known(self, box: tuple[int, int, int, int]) -> NDArray[np.float64]:
        """The fixed light on the pixels ``box`` (zero without it)."""
        r0, r1, c0, c1 = box
        if self.fixed is None:
            return np.zeros((r1 - r0, c1 - c0))
        return np.array(self.fixed[r0:r1, c0:c1], dtype=np.float64)

    def _emitters(self, em: NDArray, box: tuple[int, int, int, int]) -> NDArray[np.float64]:
        r0, r1, c0, c1 = box
        if len(em) == 0:
            return np.zeros((r1 - r0, c1 - c0))
        if self.extent is None:
            origin = (c0 * self.px, r0 * self.px)
            return self.model.render(*em.T, (r1 - r0, c1 - c0), self.px, origin=origin)
        em = em[self._touching(em, box)]
        if len(em) == 0:
            return np.zeros((r1 - r0, c1 - c0))
        new = [k for k, row in enumerate(em) if row.tobytes() not in self._pieces]
        if new:
            self._render(em[new])
        return sum_pieces([self._pieces[row.tobytes()] for row in em], box)

    def _touching(self, em: NDArray, box: tuple[int, int, int, int]) -> NDArray[np.bool_]:
        """Which emitters (K, 4) have light on the pixels ``box``: their boxes of
        :meth:`_render` (the model's extent) intersect it. The others add exactly zero, so
        they are neither rendered nor summed."""
        r0, c0, wy, wx = self._boxes(em)
        b = box
        return (r0 < b[1]) & (r0 + wy > b[0]) & (c0 < b[3]) & (c0 + wx > b[2])

    def _boxes(self, rows: NDArray) -> tuple[NDArray, NDArray, int, int]:
        """First row and column (K,) of each emitter's box and the boxes' shape: from the
        pixel before the model's extent begins."""
        (ry, rx), px = self.extent, self.px
        wy, wx = int(np.floor(2 * ry / px)) + 2, int(np.floor(2 * rx / px)) + 2
        c0 = np.floor((rows[:, 0] - rx) / px - 0.5)
        r0 = np.floor((rows[:, 1] - ry) / px - 0.5)
        return r0, c0, wy, wx

    def keep(self, em: NDArray) -> None:
        """Forget the images of emitters no longer in ``em`` (K, 4)."""
        live = {np.ascontiguousarray(row).tobytes() for row in em}
        self._pieces = {k: v for k, v in self._pieces.items() if k in live}


def window_data(f: NDArray, box: tuple[int, int, int, int], fit_kwargs: dict) -> NDArray:
    """A window of the frame, clipped at zero unless the likelihood has read noise
    (``fit_kwargs["read_variance"]``: read noise puts some pixels below zero; the Poisson fit
    without it needs counts >= 0)."""
    r0, r1, c0, c1 = box
    y = f[r0:r1, c0:c1]
    return y if fit_kwargs.get("read_variance") is not None else np.maximum(y, 0.0)


def background_shape(background: NDArray, radius: float) -> NDArray[np.float64]:
    """The shape the window fits give their background (:func:`fit_emitters`'s
    ``background_shape``): the run's background estimate of the frame (photons/pixel),
    smoothed by a Gaussian of ``radius`` pixels, one image's core: the estimate's pixel
    noise and what is left of its emitters' bumps go, a haze broader than an image stays.

    Parameters
    ----------
    background : ndarray, shape (rows, cols)
        The frame's background estimate (photons/pixel).
    radius : float
        Smoothing sigma (pixels): the PSF's core radius (the radius holding half the light
        of its broadest plane, :attr:`~sparseloc.solvers.frame_mp.FrameTemplates.core_radius`).

    Returns
    -------
    ndarray, shape (rows, cols)
    """
    from scipy.ndimage import gaussian_filter

    bg = np.asarray(background, dtype=np.float64)
    if bg.ndim != 2 or np.ptp(bg) == 0:
        return bg
    return gaussian_filter(bg, float(radius), mode="nearest")


def region_window(
    frame: NDArray,
    background: NDArray,
    box: tuple[int, int, int, int],
    light: NeighbourLight,
    rest: NDArray,
    pixel_size: float,
    fit_kwargs: dict,
    fixed_light: NDArray | None = None,
    reach: float | None = None,
) -> tuple[NDArray, dict]:
    """The data and :func:`fit_emitters` keywords of the frame's pixels ``box`` (r0, r1, c0,
    c1) for a region's fit: the light of emitters ``rest`` (K, 4; those within ``reach`` nm of
    the window where given) and ``fixed_light`` (photons/pixel over the frame) known as the
    offset, the background's (photons/pixel, the frame's shape) median over the window as the
    start of its fitted constant."""
    r0, r1, c0, c1 = box
    if reach is not None and len(rest):
        rest = rest[near_window(rest, box, pixel_size, reach)]
    offset = light.window(rest, box) if len(rest) else np.zeros((r1 - r0, c1 - c0))
    if fixed_light is not None:
        offset = offset + fixed_light[r0:r1, c0:c1]
    start = float(max(np.median(background[r0:r1, c0:c1]), 1e-3))
    kw = window_kwargs(frame, box, pixel_size, offset, start, fit_kwargs)
    return window_data(frame, box, fit_kwargs), kw


def window_kwargs(f, box, px, offset, background, fit_kwargs) -> dict:
    """Keywords of :func:`fit_emitters` for a window of the frame; the maps of
    ``fit_kwargs`` (the frame's: read variance, background shape, censored pixels) are
    cropped to it."""
    r0, _, c0, _ = box
    kw = cropped_maps(fit_kwargs, f.shape, box)
    kw.update(pixel_size=px, origin=(c0 * px, r0 * px), offset=offset, background=background)
    return kw
