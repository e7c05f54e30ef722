"""Movies rendered from the SMLM 2016 challenge's measured bead z-stacks (numpy/scipy only).

An independent check of sparseloc's calibration: nothing here uses sparseloc. The PSF is the
challenge's measured bead stack (``beads_dh.tif`` or ``beads_as.tif``, 151 planes, z = -750 ..
+750 nm in 10 nm steps, 100 nm pixels) and the emitters are the challenge's ground truth
(``activations_LD.csv`` / ``activations_HD.csv``) seen by the challenge's EMCCD.

PSF (:class:`BeadPSF`):

1. background: per plane, the mean of the pixels farther than ``R_FAR`` px from every bead
   (100.0 ADU, the baseline, in both stacks);
2. each bead's background-subtracted stack is resampled (cubic spline) on a
   ``(2 h + 1)^2`` grid of integer pixel offsets from the bead's true position
   (``beads_gt.csv``; pixel (r, c) has its centre at x = (c + 0.5) 100 nm, y = (r + 0.5) 100 nm),
   so the model's centre pixel is the emitter, not the centroid of its light;
3. per bead and plane, the image is divided by its sum over a core of ``CORE`` px half-width
   (clean for every bead), then the beads are averaged pixel by pixel over those whose sample is
   valid there: inside the field and farther than ``R_EXCL`` px from every other bead (beads 1
   and 5 of the challenge stacks are 45 px apart and share halo light);
4. each plane is normalised to unit sum.

Rendering (:meth:`BeadPSF.render`): an emitter at (x, y, z) is the model resampled at the
emitter's sub-pixel offset (cubic spline in x, y, per plane) and interpolated linearly between
the two planes around z, times its photons.

Camera (:func:`emccd`): photons (signal + background) -> Poisson electrons at QE (plus spurious
charge) -> EM gain register (gamma, shape = electrons, scale = EM gain) -> Gaussian read noise
(e-) -> ADU = e- / gain + baseline, rounded, uint16.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import tifffile
from scipy import ndimage

PX = 100.0  #: nm per pixel, bead stacks and movies
Z_FIRST, Z_STEP = -750.0, 10.0  #: frame k (1-based) of a bead stack is at z = -750 + 10 (k - 1)
R_FAR = 30.0  #: px from every bead: background pixels
CORE = 12  #: px half-width of the core that sets each bead's brightness per plane
R_EXCL = 25.0  #: px: a bead's sample is not used within this distance of another bead
HALF = 25  #: px half-width of the model (51 x 51 px = 5.1 um: 97 % of a DH plane's light)

#: The challenge's EMCCD (the data's README, from DECODE's documentation).
CAMERA = {
    "baseline": 100.0,  # ADU
    "e_per_adu": 45.0,
    "em_gain": 300.0,
    "qe": 0.9,
    "read_noise": 74.4,  # e- rms
    "spurious": 0.002,  # e- / px / frame
}
BACKGROUND = 100.0  #: photons / px / frame (the real LD frames' median, 700 ADU at QE 0.9)


def bead_positions(path: Path) -> np.ndarray:
    """Beads' true positions (x_nm, y_nm), one row per bead, from ``beads_gt.csv``."""
    g = pd.read_csv(path)
    return g.groupby("bead")[["x_nm", "y_nm"]].first().to_numpy(float)


@dataclass
class BeadPSF:
    """Averaged, registered, per-plane normalised bead stack: ``stack[k, HALF + dr, HALF + dc]``
    is the fraction of the light of an emitter at z_k that falls in the pixel ``dr`` rows and
    ``dc`` columns from the emitter's pixel position."""

    stack: np.ndarray  # (n_z, 2 HALF + 1, 2 HALF + 1)
    z: np.ndarray  # (n_z,) nm
    n_beads: np.ndarray  # (2 HALF + 1, 2 HALF + 1): beads averaged per pixel

    @classmethod
    def from_beads(
        cls, stack_path: Path, beads_csv: Path, half: int = HALF, use: list[int] | None = None
    ) -> BeadPSF:
        raw = tifffile.imread(stack_path).astype(np.float64)
        xy = bead_positions(beads_csv)
        if use is not None:
            xy_used = xy[use]
        else:
            xy_used = xy
        n_z, ny, nx = raw.shape
        rows, cols = np.mgrid[:ny, :nx]
        rc_all = np.c_[xy[:, 1] / PX - 0.5, xy[:, 0] / PX - 0.5]  # (row, col) of every bead
        dist = np.min([np.hypot(rows - r, cols - c) for r, c in rc_all], axis=0)
        far = dist > R_FAR
        bg = raw[:, far].mean(axis=1)
        sub = raw - bg[:, None, None]

        off = np.arange(-half, half + 1, dtype=float)
        dr, dc = np.meshgrid(off, off, indexing="ij")
        acc = np.zeros((n_z, 2 * half + 1, 2 * half + 1))
        cnt = np.zeros((2 * half + 1, 2 * half + 1))
        core = (np.abs(dr) <= CORE) & (np.abs(dc) <= CORE)
        for x, y in xy_used:
            r0, c0 = y / PX - 0.5, x / PX - 0.5
            rr, cc = r0 + dr, c0 + dc
            ok = (rr >= 0) & (rr <= ny - 1) & (cc >= 0) & (cc <= nx - 1)
            for r1, c1 in rc_all:
                if np.hypot(r1 - r0, c1 - c0) < 1e-6:
                    continue  # this bead
                ok &= np.hypot(rr - r1, cc - c1) > R_EXCL
            if not ok[core].all():
                raise ValueError(f"bead at ({x:.0f}, {y:.0f}) nm: its core is not clean")
            img = np.stack(
                [ndimage.map_coordinates(p, [rr, cc], order=3, mode="nearest") for p in sub]
            )
            img /= img[:, core].sum(axis=1)[:, None, None]
            acc += np.where(ok, img, 0.0)
            cnt += ok
        if (cnt == 0).any():
            raise ValueError("some model pixels have no clean bead")
        model = acc / cnt
        model /= model.sum(axis=(1, 2))[:, None, None]
        z = Z_FIRST + Z_STEP * np.arange(n_z)
        return cls(model, z, cnt)

    @property
    def half(self) -> int:
        return (self.stack.shape[1] - 1) // 2

    def plane(self, z: float) -> tuple[int, float]:
        """The plane below ``z`` and the weight of the one above."""
        f = np.clip((z - self.z[0]) / (self.z[1] - self.z[0]), 0.0, len(self.z) - 1.0)
        k = min(int(np.floor(f)), len(self.z) - 2)
        return k, f - k

    def render(self, shape: tuple[int, int], x: float, y: float, z: float) -> np.ndarray:
        """Fraction of the light of an emitter at (x, y, z) nm per pixel of a ``shape`` field
        (pixel centre (c + 0.5, r + 0.5) * PX)."""
        out = np.zeros(shape)
        h = self.half
        r0, c0 = y / PX - 0.5, x / PX - 0.5
        ra = np.arange(max(int(np.ceil(r0 - h)), 0), min(int(np.floor(r0 + h)), shape[0] - 1) + 1)
        ca = np.arange(max(int(np.ceil(c0 - h)), 0), min(int(np.floor(c0 + h)), shape[1] - 1) + 1)
        if not len(ra) or not len(ca):
            return out
        rr, cc = np.meshgrid(ra - r0 + h, ca - c0 + h, indexing="ij")
        k, w = self.plane(z)
        img = (1.0 - w) * ndimage.map_coordinates(
            self.stack[k], [rr, cc], order=3, mode="grid-constant"
        ) + w * ndimage.map_coordinates(self.stack[k + 1], [rr, cc], order=3, mode="grid-constant")
        out[ra[0] : ra[-1] + 1, ca[0] : ca[-1] + 1] = img
        return out


def read_activations(path: Path, n_frames: int) -> pd.DataFrame:
    """The challenge's activations of frames 1..``n_frames`` (1-based frames kept)."""
    a = pd.read_csv(path, skipinitialspace=True)
    a.columns = [c.strip() for c in a.columns]
    return a[a["frame"] <= n_frames].reset_index(drop=True)


def emccd(photons: np.ndarray, rng: np.random.Generator, camera: dict = CAMERA) -> np.ndarray:
    """ADU (uint16) of an EMCCD for expected ``photons`` per pixel."""
    e = rng.poisson(camera["qe"] * photons + camera["spurious"])
    amp = np.where(e > 0, rng.gamma(np.maximum(e, 1), camera["em_gain"]), 0.0)
    amp = amp + rng.normal(0.0, camera["read_noise"], photons.shape)
    adu = np.rint(amp / camera["e_per_adu"] + camera["baseline"])
    return np.clip(adu, 0, 65535).astype(np.uint16)


def render_movie(
    psf: BeadPSF,
    truth: pd.DataFrame,
    n_frames: int,
    shape: tuple[int, int] = (64, 64),
    background: float = BACKGROUND,
    seed: int = 0,
    noise: bool = True,
) -> np.ndarray:
    """Frames 1..``n_frames`` of the activations ``truth`` (challenge columns, 1-based
    frames): ADU (uint16) with ``noise``, else expected photons (float)."""
    rng = np.random.default_rng(seed)
    frames = []
    by_frame = {f: g for f, g in truth.groupby("frame")}
    for f in range(1, n_frames + 1):
        mu = np.full(shape, float(background))
        g = by_frame.get(f)
        if g is not None:
            for x, y, z, n in g[["xnano", "ynano", "znano", "intensity"]].to_numpy(float):
                mu += n * psf.render(shape, x, y, z)
        frames.append(emccd(mu, rng) if noise else mu)
    return np.stack(frames)


def sanity(stack_path: Path, beads_csv: Path, planes=(0, 40, 75, 110, 150)) -> dict:
    """NCC between each bead's own background-subtracted, normalised image and an emitter
    rendered at its true position and plane, with the model from all beads and from the other
    beads (leave one out). Returns {'all': array (beads, planes), 'loo': ...}."""
    raw = tifffile.imread(stack_path).astype(np.float64)
    xy = bead_positions(beads_csv)
    full = BeadPSF.from_beads(stack_path, beads_csv)
    _, ny, nx = raw.shape
    rows, cols = np.mgrid[:ny, :nx]
    dist = np.min([np.hypot(rows - y / PX + 0.5, cols - x / PX + 0.5) for x, y in xy], axis=0)
    bg = raw[:, dist > R_FAR].mean(axis=1)
    out = {"all": np.zeros((len(xy), len(planes))), "loo": np.zeros((len(xy), len(planes)))}
    for b, (x, y) in enumerate(xy):
        others = [i for i in range(len(xy)) if i != b]
        try:
            loo = BeadPSF.from_beads(stack_path, beads_csv, use=others)
        except ValueError:
            loo = None
        r0, c0 = round(y / PX - 0.5), round(x / PX - 0.5)
        h = CORE + 6
        win = (slice(max(r0 - h, 0), r0 + h + 1), slice(max(c0 - h, 0), c0 + h + 1))
        for j, k in enumerate(planes):
            own = (raw[k] - bg[k])[win]
            for key, model in (("all", full), ("loo", loo)):
                if model is None:
                    out[key][b, j] = np.nan
                    continue
                ren = model.render((ny, nx), x, y, full.z[k])[win]
                a, m = own - own.mean(), ren - ren.mean()
                out[key][b, j] = float((a * m).sum() / np.sqrt((a * a).sum() * (m * m).sum()))
    return out


def show_hd_frame(folder: Path, png: Path, frame: int = 1) -> None:
    """PNG of HD frame ``frame`` rendered with both bead stacks (expected photons and ADU),
    the true positions marked, and model planes 0/40/75/110/150."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    acts = read_activations(folder / "activations_HD.csv", frame)
    here = acts[acts["frame"] == frame]
    fig, ax = plt.subplots(2, 3, figsize=(15, 10))
    for i, kind in enumerate(("dh", "as")):
        psf = BeadPSF.from_beads(folder / f"beads_{kind}.tif", folder / "beads_gt.csv")
        mu = render_movie(psf, acts, frame, noise=False)[-1]
        adu = render_movie(psf, acts, frame, seed=2)[-1]
        for a, img, what in ((ax[i, 0], mu, "expected photons"), (ax[i, 1], adu, "ADU")):
            a.imshow(img, cmap="gray")
            a.plot(here["xnano"] / PX - 0.5, here["ynano"] / PX - 0.5, "r+")
            a.set_title(f"{kind.upper()} HD frame {frame}, {what}")
        planes = psf.stack[[0, 40, 75, 110, 150]]
        n = planes.shape[1]
        ax[i, 2].imshow(np.sqrt(np.clip(planes, 0, None)).transpose(1, 0, 2).reshape(n, -1))
        ax[i, 2].set_title("model, z = -750/-350/0/350/750 nm (sqrt)")
    fig.tight_layout()
    fig.savefig(png, dpi=70)


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="sanity checks of the challenge renderer")
    ap.add_argument("folder", type=Path, nargs="?", default=Path("../shared/data/smlm2016"))
    ap.add_argument("--png", type=Path, default=Path("/tmp/challenge_hd_frame.png"))
    args = ap.parse_args()
    for kind in ("dh", "as"):
        res = sanity(args.folder / f"beads_{kind}.tif", args.folder / "beads_gt.csv")
        for key, v in res.items():
            print(kind, key, "NCC per bead (rows) and plane 0/40/75/110/150:")
            print(np.array2string(v, precision=4))
    show_hd_frame(args.folder, args.png)
    print(f"wrote {args.png}")
