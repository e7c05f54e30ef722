"""Accuracy on outside data (issue "Trust on data nobody here tuned on"): one table.

Every row is data this project did not make (``../shared/data``), localized with default settings
from a bead calibration of the same data set, as a microscopist would:

- storm-analysis's double-helix frames (its grid frame and the 0.5 and 1 /um^2 random frames),
  calibrated from its bead z-scan;
- storm-analysis's astigmatic grid frames (10 frames of 126 emitters, 1,000 photons,
  background 20), calibrated from its bead z-scan, with the RMSE over the Cramer-Rao bound of
  the calibrated model at the truth;
- the SMLM 2016 challenge's 64 real LD astigmatic frames, calibrated from the challenge's
  astigmatic bead stack with the challenge's EMCCD camera: once with the model centred on its
  light's centroid (the default) and once on the beads' known positions (``--beads``);
- double-helix and astigmatic movies rendered from the challenge's measured bead stacks
  (``challenge_render.py``: numpy/scipy only, no sparseloc code) with the challenge's LD and HD
  ground truth (the first 300 LD and 40 HD frames, 64 x 64 px of 100 nm), its EMCCD (baseline
  100 ADU, 45 e-/ADU, EM gain 300, QE 0.9, read noise 74.4 e-) and a background of 100 photons/px;
  each localized from a calibration on the same bead stack, with ``--beads`` (the main rows) and
  with the centroid rule (rows marked "centroid").

Under each main row, the same run started from the true emitters in place of the pursuit
(``localize(..., starts=truth)``): the ceiling of what the fits and the count selection keep,
which the issue's acceptance compares against. Under the challenge rows' recall by photons, the
median lateral Cramer-Rao bound of the emitters of each bin, each alone on the challenge's EMCCD,
and what the data show of them: the median support of the true emitters of each bin (the frame
check's ``2 delta log L`` of each with and without it, the others fixed,
:func:`sparseloc.pipeline.check_frame`) and the fraction above the bar of a lone emitter
(:data:`~sparseloc.solvers.frame.SINGLE_THRESHOLD`, the chi-square 0.1 % tail). An emitter
below that bar cannot be told from the noise by a test that keeps false emitters rare, whatever
its Cramer-Rao bound: the bound says how precisely an emitter known to be there is placed.

Scores follow the SMLM challenge (250 nm lateral, 500 nm axial, one-to-one per frame; efficiency
with alpha 1/nm lateral and 0.5/nm axial). The peer figures come from the data's READMEs.

Usage::

    python benchmarks/outside.py [--data ../shared/data] [--out FILE]
        [--ld-frames 300] [--hd-frames 40] [--no-centroid] [--quick]
        [--parts storm,challenge,rendered]

``--quick`` renders 100 LD and 20 HD frames and skips the centroid variant of the rendered rows.
"""

from __future__ import annotations

import argparse
import itertools
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import tifffile

from challenge_render import BACKGROUND, BeadPSF, read_activations, render_movie
from sparseloc.calibrate import calibrate_file, read_bead_positions
from sparseloc.config import build_job
from sparseloc.crlb import crlb
from sparseloc.distributed import CameraFrames
from sparseloc.evaluate import evaluate, match_localizations
from sparseloc.io.calibration import save_calibration
from sparseloc.io.movie import Movie
from sparseloc.io.truth import read_truth_csv
from sparseloc.pipeline import LocalizeParams, check_frame, localize
from sparseloc.solvers.frame import SINGLE_THRESHOLD

PX = 100.0
COLS = ["x_nm", "y_nm", "z_nm", "photons"]
#: Peer results from the data's READMEs: (program, Jaccard %, RMSE lateral nm, RMSE axial nm);
#: None where the README gives no such figure.
PEERS = {
    "SA DH grid": ("storm-analysis FISTA+spline", None, "x/y/z 3.4/3.7/5.5", None),
    "SA DH 0.5/um2": ("storm-analysis, tuned", 91.4, 26.9, 40.1),
    "SA DH 1/um2": ("storm-analysis, tuned", 81.7, 52.2, 85.4),
    "SA AS grid": ("storm-analysis spliner", None, "x/y/z 20.3/20.3/31.5", None),
}
SA_FRAMES = {
    "SA DH grid": "dh_fista_diag_test01",
    "SA DH 0.5/um2": "dh_random_density0.005px2",
    "SA DH 1/um2": "dh_random_density0.01px2",
}
#: The SMLM 2016 challenge's EMCCD (its README): baseline 100 ADU, 45 e-/ADU, EM gain 300, QE 0.9.
CHALLENGE_CAMERA = {"camera": "emccd", "offset": 100.0, "gain": 45.0, "em_gain": 300.0, "qe": 0.9}


def storm_rows(data: Path) -> list[dict]:
    """storm-analysis's DH frames and its astigmatic grid frame."""
    rows = []
    sa = data / "storm_analysis_sim"
    for kind, frames in (("dh", SA_FRAMES), ("astig", {"SA AS grid": "as_spliner_diag_test02"})):
        folder = sa / kind
        cal = calibrate_file(
            folder / "beads_zscan.tif", PX, z_file=folder / "beads_zscan_z.csv", offset=100.0
        )
        for label, name in frames.items():
            # every page: the astigmatic grid's TIFF holds its 10 frames as 10 one-page
            # series, of which tifffile.imread reads the first only
            with tifffile.TiffFile(folder / f"{name}.tif") as tif:
                frame = np.stack([page.asarray() for page in tif.pages]).astype(np.float64)
            frame -= 100.0
            truth = read_truth_csv(folder / f"{name}_groundtruth.csv", pixel_size=PX)
            truth = truth[truth["frame"] < len(frame)]
            t0 = time.perf_counter()
            params = LocalizeParams(pixel_size=PX)
            res = localize(frame, cal.psf, params)
            row = score(label, res.table, truth, time.perf_counter() - t0)
            row["ceiling"] = ceiling(frame, cal.psf, params, truth)
            if kind == "astig":
                row.update(crlb_ratio(cal.psf, res.table, truth, background=20.0))
                row["exact_model"] = exact_model_ratio(cal.psf, frame.shape, truth, 20.0)
            rows.append(row)
    return rows


def exact_model_ratio(model, shape, truth: pd.DataFrame, background: float) -> list[float]:
    """RMSE / sqrt(CRLB) per axis where the model is exact: the truth's emitters rendered by
    ``model`` itself on ``background`` (photons/px) with Poisson noise (seed 0), localized
    with ``model``. The fits' own excess over the bound at these photons, which the outside
    data's ratio adds the model's misfit to."""
    rng = np.random.default_rng(0)
    frames = np.stack(
        [
            rng.poisson(
                model.render(*truth[truth["frame"] == f][COLS].to_numpy().T, shape[-2:], PX)
                + background
            ).astype(np.float64)
            for f in range(shape[0])
        ]
    )
    res = localize(frames, model, LocalizeParams(pixel_size=PX))
    return crlb_ratio(model, res.table, truth, background)["rmse_over_crlb"]


#: Resamples of the bootstrap interval of the RMSE / sqrt(CRLB) ratios.
BOOTSTRAP = 2000


def crlb_ratio(model, locs: pd.DataFrame, truth: pd.DataFrame, background: float) -> dict:
    """RMSE over the root-mean-square Cramer-Rao bound of ``model`` at the matched truth
    (each emitter alone in a 21 x 21 px window, Poisson), per axis; its bootstrap 95 %
    interval over the matched emitters (the grid's few deep emitters, whose bounds are largest,
    weigh most in both sums); and the mean squared error over each emitter's own bound (1 for
    an efficient fit, whatever the mix of depths)."""
    m = match_localizations(locs, truth)
    cols = ["x_nm", "y_nm", "z_nm"]
    tr = truth.iloc[m.truth_row]
    err = locs.iloc[m.loc_row][cols].to_numpy() - tr[cols].to_numpy()
    c = 10.5 * PX
    sd = np.array(
        [
            np.asarray(
                crlb(model, [c], [c], [t.z_nm], [t.photons], background, (21, 21), PX)
            ).reshape(-1)[:3]
            for _, t in tr.iterrows()
        ]
    )

    def ratios(idx):
        return np.sqrt(np.mean(err[idx] ** 2, axis=0) / np.mean(sd[idx] ** 2, axis=0))

    rng = np.random.default_rng(0)
    boot = np.array([ratios(rng.integers(0, len(err), len(err))) for _ in range(BOOTSTRAP)])
    rms = np.sqrt(np.mean(sd**2, axis=0))
    return {
        "crlb_x_nm": rms[0],
        "crlb_y_nm": rms[1],
        "crlb_z_nm": rms[2],
        "rmse_over_crlb": list(ratios(np.arange(len(err)))),
        "rmse_over_crlb_95": [list(v) for v in np.percentile(boot, [2.5, 97.5], axis=0).T],
        "mean_sq_error_over_crlb": list(np.mean((err / sd) ** 2, axis=0)),
    }


def challenge_truth(path: Path, n_frames: int) -> pd.DataFrame:
    """The challenge's activations (1-based frames) of the first ``n_frames`` frames, as a
    truth table with 0-based frames."""
    a = pd.read_csv(path, skipinitialspace=True)
    a.columns = [c.strip() for c in a.columns]
    a = a[a["frame"] <= n_frames]
    return pd.DataFrame(
        {
            "frame": a["frame"].to_numpy(np.int64) - 1,
            "x_nm": a["xnano"].to_numpy(float),
            "y_nm": a["ynano"].to_numpy(float),
            "z_nm": a["znano"].to_numpy(float),
            "photons": a["intensity"].to_numpy(float),
        }
    )


def challenge_rows(data: Path, workdir: Path) -> list[dict]:
    """The challenge's real LD astigmatic frames with an astigmatic bead calibration, centred
    on the light's centroid and on the beads' known positions."""
    folder = data / "smlm2016"
    rows = []
    for label, beads in (
        ("", None),
        (" --beads", read_bead_positions(folder / "beads_gt.csv", PX)),
    ):
        cal = calibrate_file(
            folder / "beads_as.tif", PX, 10.0, z0_slice=75, offset=100.0, beads=beads
        )
        psf_file = save_calibration(cal, workdir / "smlm_as.h5")
        with Movie.open(folder / "test_frames_LD_AS.tif") as movie:
            options = {"psf": str(psf_file), "pixel_size": PX, **CHALLENGE_CAMERA}
            job = build_job(options, movie)
            t0 = time.perf_counter()
            frames = CameraFrames(movie, job.camera, job.defects)
            res = localize(frames, job.model, job.params)
            truth = challenge_truth(folder / "activations_LD.csv", len(movie))
            row = score("SMLM16 LD AS" + label, res.table, truth, time.perf_counter() - t0)
            if beads is not None:
                row["ceiling"] = ceiling(frames, job.model, job.params, truth)
                row["support_by_photons"] = support_by_photons(frames, job.model, job.params, truth)
        row["recall_by_photons"] = recall_by_photons(res.table, truth)
        row["crlb_by_photons"] = crlb_by_photons(job.model, truth, 100.0 * CHALLENGE_CAMERA["qe"])
        rows.append(row)
    return rows


#: Rendered challenge movies: (modality label, bead stack), (density label, activations file,
#: seed of the camera noise).
RENDER_PSFS = (("DH", "beads_dh.tif"), ("AS", "beads_as.tif"))
RENDER_DENSITIES = (("LD", "activations_LD.csv", 1), ("HD", "activations_HD.csv", 2))


def rendered_rows(
    data: Path, workdir: Path, ld_frames: int, hd_frames: int, centroid: bool = True
) -> list[dict]:
    """Double-helix and astigmatic movies rendered from the challenge's bead stacks
    (``challenge_render``) with its LD and HD ground truth and camera, localized from a
    calibration on the same stack: with ``--beads`` (label "... (rendered)") and, if
    ``centroid``, with the centroid rule (label "... (rendered) centroid")."""
    folder = data / "smlm2016"
    n_frames = {"LD": ld_frames, "HD": hd_frames}
    variants = [("", read_bead_positions(folder / "beads_gt.csv", PX))]
    if centroid:
        variants.append((" centroid", None))
    rows = []
    for kind, stack in RENDER_PSFS:
        psf = BeadPSF.from_beads(folder / stack, folder / "beads_gt.csv")
        movies = {}
        for dens, acts, seed in RENDER_DENSITIES:
            n = n_frames[dens]
            frames = render_movie(psf, read_activations(folder / acts, n), n, seed=seed)
            path = workdir / f"render_{kind}_{dens}.tif"
            tifffile.imwrite(path, frames)
            movies[dens] = (path, challenge_truth(folder / acts, n))
        for suffix, beads in variants:
            cal = calibrate_file(folder / stack, PX, 10.0, z0_slice=75, offset=100.0, beads=beads)
            psf_file = save_calibration(cal, workdir / f"smlm_{kind}.h5")
            for dens, (path, truth) in movies.items():
                with Movie.open(path) as movie:
                    options = {"psf": str(psf_file), "pixel_size": PX, **CHALLENGE_CAMERA}
                    job = build_job(options, movie)
                    t0 = time.perf_counter()
                    frames = CameraFrames(movie, job.camera, job.defects)
                    res = localize(frames, job.model, job.params)
                    label = f"SMLM16 {kind} {dens} (rendered){suffix}"
                    row = score(label, res.table, truth, time.perf_counter() - t0)
                    if not suffix:
                        row["ceiling"] = ceiling(frames, job.model, job.params, truth)
                        # the rendered background is known: the check's box backgrounds
                        known = truth.assign(background=BACKGROUND)
                        row["support_by_photons"] = support_by_photons(
                            frames, job.model, job.params, known
                        )
                row["recall_by_photons"] = recall_by_photons(res.table, truth)
                row["crlb_by_photons"] = crlb_by_photons(
                    job.model, truth, 100.0 * CHALLENGE_CAMERA["qe"]
                )
                row["frames"] = n_frames[dens]
                rows.append(row)
    return rows


#: Photon bins (of the truth) for the recall of the challenge rows.
PHOTON_BINS = (0.0, 1000.0, 2000.0, 4000.0, np.inf)


def recall_by_photons(locs: pd.DataFrame, truth: pd.DataFrame) -> list[tuple[str, int, float]]:
    """Recall per photon bin of the truth: (bin, emitters, recall)."""
    from sparseloc.evaluate import match_localizations

    found = np.zeros(len(truth), bool)
    found[match_localizations(locs, truth)["truth_row"].to_numpy(int)] = True
    out = []
    for lo, hi in itertools.pairwise(PHOTON_BINS):
        sel = (truth["photons"].to_numpy() >= lo) & (truth["photons"].to_numpy() < hi)
        n = int(sel.sum())
        out.append((f"{lo:.0f}-{hi:.0f}", n, float(found[sel].mean()) if n else float("nan")))
    return out


def ceiling(frames, model, params: LocalizeParams, truth: pd.DataFrame) -> dict:
    """What the fits keep when started from the true emitters (the same fits, count selection
    and relocation as the row's run, without the pursuit): the row's ceiling."""
    res = localize(frames, model, params, starts=truth, check=False)
    ev = evaluate(res.table, truth)
    return {
        "jaccard": ev.jaccard,
        "recall": ev.recall,
        "precision": ev.precision,
        "rmse_lateral_nm": ev.rmse_lateral,
        "rmse_axial_nm": ev.rmse_axial,
        "recall_by_photons": recall_by_photons(res.table, truth),
    }


def crlb_by_photons(model, truth: pd.DataFrame, background: float) -> list[float]:
    """Per photon bin of the truth, the median lateral Cramer-Rao bound (nm, the root mean of
    the x and y variances) of its emitters each alone on the challenge's EMCCD (detected
    photons: the truth's times the QE; ``background`` in detected photons/pixel)."""
    from sparseloc.crlb import crlb_single

    qe = CHALLENGE_CAMERA["qe"]
    photons = truth["photons"].to_numpy(float)
    sd = crlb_single(
        model,
        truth["z_nm"].to_numpy(float),
        photons * qe,
        background,
        PX,
        noise="emccd",
        singular="pinv",
    )
    lateral = np.sqrt((sd[:, 0] ** 2 + sd[:, 1] ** 2) / 2.0)
    out = []
    for lo, hi in itertools.pairwise(PHOTON_BINS):
        sel = (photons >= lo) & (photons < hi)
        out.append(float(np.median(lateral[sel])) if sel.any() else float("nan"))
    return out


def support_by_photons(
    frames, model, params: LocalizeParams, truth: pd.DataFrame
) -> list[tuple[float, float]]:
    """Per photon bin of the truth: the median support of its emitters (``2 delta log L`` of
    the frame with and without each, the frame's other true emitters fixed; the frame check of
    :func:`sparseloc.pipeline.check_frame` applied to the truth) and the fraction of them
    above :data:`~sparseloc.solvers.frame.SINGLE_THRESHOLD`. Around each emitter the
    background is the truth's ``background`` column where it has one (a rendered movie's
    constant), else the run's estimate (which, in a dense frame, holds part of the emitters'
    light and so lowers their support)."""
    support = np.full(len(truth), np.nan)
    frame_of = truth["frame"].to_numpy()
    for f in np.unique(frame_of):
        rows = np.flatnonzero(frame_of == f)
        support[rows] = check_frame(frames, int(f), truth.iloc[rows], model, params).support
    photons = truth["photons"].to_numpy(float)
    out = []
    for lo, hi in itertools.pairwise(PHOTON_BINS):
        s = support[(photons >= lo) & (photons < hi)]
        if s.size:
            out.append((float(np.median(s)), float(np.mean(s > SINGLE_THRESHOLD))))
        else:
            out.append((float("nan"), float("nan")))
    return out


def score(label: str, locs: pd.DataFrame, truth: pd.DataFrame, seconds: float) -> dict:
    ev = evaluate(locs, truth)
    return {
        "data": label,
        "n_truth": ev.n_truth,
        "jaccard": ev.jaccard,
        "recall": ev.recall,
        "precision": ev.precision,
        "rmse_lateral_nm": ev.rmse_lateral,
        "rmse_axial_nm": ev.rmse_axial,
        "rmse_xyz_nm": [ev.rmse_x, ev.rmse_y, ev.rmse_z],
        "bias_xyz_nm": [ev.bias_x, ev.bias_y, ev.bias_z],
        "efficiency_lateral": ev.efficiency_lateral,
        "efficiency_axial": ev.efficiency_axial,
        "seconds": seconds,
    }


#: Width of the table's data column.
W = 32


def print_table(rows: list[dict]) -> None:
    hdr = (
        f"{'data':>{W}} {'truth':>5} | {'Jac %':>5} {'rec':>5} {'prec':>5} | {'lat':>5} {'ax':>5} "
        f"{'x':>5} {'y':>5} {'z':>5} nm | {'bias x':>6} {'y':>5} {'z':>5} nm | "
        f"{'E lat':>5} {'E ax':>5} | peer"
    )
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        peer = PEERS.get(r["data"])
        peer_txt = "" if peer is None else ", ".join(str(v) for v in peer if v is not None)
        x, y, z = r["rmse_xyz_nm"]
        bx, by, bz = r["bias_xyz_nm"]
        print(
            f"{r['data']:>{W}} {r['n_truth']:5d} | {r['jaccard']:5.1f} {r['recall']:5.3f} "
            f"{r['precision']:5.3f} | {r['rmse_lateral_nm']:5.1f} {r['rmse_axial_nm']:5.1f} "
            f"{x:5.1f} {y:5.1f} {z:5.1f}    | {bx:6.1f} {by:5.1f} {bz:5.1f}    | "
            f"{r['efficiency_lateral']:5.1f} {r['efficiency_axial']:5.1f} | {peer_txt}"
        )
        if "recall_by_photons" in r:
            bins = ", ".join(f"{b}: {rc:.2f} of {n}" for b, n, rc in r["recall_by_photons"])
            print(f"{'':>{W}}        recall by photons {bins}")
        if "crlb_by_photons" in r:
            bins = ", ".join(f"{v:.0f}" for v in r["crlb_by_photons"])
            print(f"{'':>{W}}        median lateral sqrt(CRLB) of an emitter alone, nm: {bins}")
        if "support_by_photons" in r:
            med = ", ".join(f"{m:.0f}" for m, _ in r["support_by_photons"])
            above = ", ".join(f"{a:.2f}" for _, a in r["support_by_photons"])
            print(
                f"{'':>{W}}        the true emitters' median support (2 delta log L): {med}; "
                f"above {SINGLE_THRESHOLD:.2f}: {above}"
            )
        if "ceiling" in r:
            c = r["ceiling"]
            bins = ", ".join(f"{rc:.2f}" for _, _, rc in c["recall_by_photons"])
            print(
                f"{'':>{W}}        started from the truth: Jaccard {c['jaccard']:.1f}, recall "
                f"{c['recall']:.3f}, precision {c['precision']:.3f}, RMSE lateral "
                f"{c['rmse_lateral_nm']:.1f} axial {c['rmse_axial_nm']:.1f} nm; by photons {bins}"
            )
        if "rmse_over_crlb" in r:
            ratio = "/".join(f"{v:.2f}" for v in r["rmse_over_crlb"])
            print(
                f"{'':>{W}}        RMSE / sqrt(CRLB) x/y/z {ratio} (sqrt CRLB "
                f"{r['crlb_x_nm']:.1f}/{r['crlb_y_nm']:.1f}/{r['crlb_z_nm']:.1f} nm)"
            )
        if "exact_model" in r:
            ratio = "/".join(f"{v:.2f}" for v in r["exact_model"])
            print(
                f"{'':>{W}}        the same emitters rendered by the calibrated model itself "
                f"(an exact model): RMSE / sqrt(CRLB) x/y/z {ratio}"
            )
        if "rmse_over_crlb_95" in r:
            ci = "/".join(f"{lo:.2f}-{hi:.2f}" for lo, hi in r["rmse_over_crlb_95"])
            per = "/".join(f"{v:.2f}" for v in r["mean_sq_error_over_crlb"])
            print(
                f"{'':>{W}}        bootstrap 95 % x/y/z {ci}; mean (error / sqrt(CRLB))^2 "
                f"per emitter x/y/z {per}"
            )


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/outside.json"))
    ap.add_argument("--ld-frames", type=int, default=300, help="rendered LD frames")
    ap.add_argument("--hd-frames", type=int, default=40, help="rendered HD frames")
    ap.add_argument("--no-centroid", action="store_true", help="rendered rows with --beads only")
    ap.add_argument(
        "--quick", action="store_true", help="100 LD and 20 HD rendered frames, --beads only"
    )
    ap.add_argument(
        "--parts",
        default="storm,challenge,rendered",
        help="which rows, comma-separated: storm (storm-analysis's frames), challenge (the real "
        "LD AS frames), rendered (movies rendered from the challenge's bead stacks)",
    )
    args = ap.parse_args(argv)
    parts = set(args.parts.split(","))
    if not parts <= {"storm", "challenge", "rendered"}:
        ap.error(f"--parts takes storm, challenge, rendered, not {args.parts!r}")
    if args.quick:
        args.ld_frames, args.hd_frames, args.no_centroid = 100, 20, True
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        rows = storm_rows(args.data) if "storm" in parts else []
        rows += challenge_rows(args.data, Path(tmp)) if "challenge" in parts else []
        if "rendered" in parts:
            rows += rendered_rows(
                args.data, Path(tmp), args.ld_frames, args.hd_frames, not args.no_centroid
            )
    print_table(rows)
    print(f"total {time.perf_counter() - t0:.0f} s")
    out = {"rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2, default=float))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
