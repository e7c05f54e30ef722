"""Frames to a table: tiling, ownership, detection and an end-to-end run on a fast model."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from sparseloc.detect import detect_candidates, temporal_background, tiles, z_averaged_psf
from sparseloc.evaluate import evaluate
from sparseloc.io.tables import LOCS_COLUMNS
from sparseloc.pipeline import LocalizeParams, localize
from sparseloc.psf import make_psf

PX = 160.0


@pytest.mark.parametrize(
    ("shape", "window", "margin"), [((32, 45), 11, 3), ((11, 11), 11, 2), ((50, 23), 9, 1)]
)
def test_cores_partition_the_frame(shape, window, margin):
    owners = np.zeros(shape, dtype=int)
    for t in tiles(shape, window, margin):
        owners[t.core_rows[0] : t.core_rows[1], t.core_cols[0] : t.core_cols[1]] += 1
        # the window lies in the frame and covers its core
        assert 0 <= t.row0 <= shape[0] - window and 0 <= t.col0 <= shape[1] - window
        assert t.row0 <= t.core_rows[0] and t.core_rows[1] <= t.row0 + window
        assert t.col0 <= t.core_cols[0] and t.core_cols[1] <= t.col0 + window
    assert np.all(owners == 1)


def test_ownership_of_a_point_on_a_core_border():
    ts = tiles((40, 40), 11, 3)
    x = np.array([5 * PX, 5 * PX - 1e-6, 0.0, 40 * PX - 1e-6])  # on / just before a border
    y = np.array([7 * PX, 7 * PX, 0.0, 40 * PX - 1e-6])
    counts = sum(t.owns(x, y, PX).astype(int) for t in ts)
    assert np.all(counts == 1)


def test_frames_smaller_than_a_window_are_refused():
    with pytest.raises(ValueError, match="smaller than one window"):
        tiles((8, 40), 11, 3)


def test_background_and_detection_find_a_double_helix_once():
    model = make_psf("dh-analytic")
    rng = np.random.default_rng(0)
    truth = np.array([[1500.0, 2000.0, 300.0], [3500.0, 3200.0, -400.0]])
    frames = []
    for _ in range(9):
        mu = model.render(truth[:, 0], truth[:, 1], truth[:, 2], [3000.0, 3000.0], (40, 40), PX)
        blink = rng.random() < 0.3  # molecules blink: the percentile ignores them
        frames.append(rng.poisson(12.0 + mu * (blink or _ == 4)))
    frames = np.array(frames, dtype=float)
    bg = temporal_background(frames)
    assert abs(np.median(bg) - 12.0) < 1.0
    tmpl = z_averaged_psf(model, PX, model.z_range, 21)
    cand = detect_candidates(frames[4], bg, tmpl, threshold=5.0)
    assert len(cand) == 2  # one candidate per two-lobed image, not one per lobe
    found = cand[:, ::-1] * PX + PX / 2  # (x, y) nm of the pixel centres
    for p in truth[:, :2]:
        assert np.min(np.linalg.norm(found - p, axis=1)) < 2 * PX

    # The noise model scales the bar: variance noise_factor * background + read variance. Both
    # images have a signal-to-noise ratio between 80 and 100 here.
    def found(threshold, **noise):
        return detect_candidates(frames[4], bg, tmpl, threshold=threshold, **noise)

    assert len(found(60.0)) == 2
    assert len(found(60.0, noise_factor=4.0)) == 0  # four times the variance: half the SNR
    assert len(found(60.0, read_variance=3.0 * bg)) == 0  # a map of 3 b: the same
    np.testing.assert_array_equal(found(30.0, noise_factor=4.0), found(60.0))
    np.testing.assert_array_equal(found(30.0, read_variance=3.0 * bg), found(60.0))
    half = np.zeros(frames[4].shape)
    half[:, :20] = 1e6
    right = detect_candidates(frames[4], bg, tmpl, threshold=5.0, read_variance=half)
    assert len(right) >= 1 and np.all(right[:, 1] > 20)  # the left emitter is not found


def test_end_to_end_on_a_small_movie():
    from sparseloc.simulate import simulate

    model = make_psf("dh-analytic")
    sim = simulate(
        model,
        scene="uniform",
        n_frames=2,
        shape=(32, 32),
        pixel_size=PX,
        density=0.15,
        photons=(3000.0, 4000.0),
        background=10.0,
        seed=3,
        z_range=(-300.0, 300.0),
    )
    frames = sim.movie.astype(float) - sim.camera.offset
    params = LocalizeParams(
        pixel_size=PX, z_range=(-300.0, 300.0), window=11, margin=3, fine=(20.0, 30.0)
    )
    done = []
    res = localize(frames, model, params, progress=done.append)
    assert sum(done) == 2
    assert list(res.table.columns) == list(LOCS_COLUMNS)
    ev = evaluate(res.table, sim.truth)
    assert ev.recall >= 0.8 and ev.jaccard >= 60.0
    assert ev.rmse_lateral < 40.0
    # no emitter reported twice: no two localizations of one frame within 50 nm
    for _, df in res.table.groupby("frame"):
        xy = df[["x_nm", "y_nm"]].to_numpy()
        d = np.linalg.norm(xy[:, None] - xy[None], axis=2) + np.eye(len(xy)) * 1e9
        assert d.min() > 50.0
    assert res.metadata["psf_hash"] and res.metadata["params"]["pixel_size"] == PX
    assert isinstance(res.table, pd.DataFrame)


@pytest.mark.parametrize("solver", [{}, {"engine": "numpy"}, {"method": "hybrid"}])
def test_the_camera_qe_reaches_the_likelihood(solver):
    """Frames from a camera with qe 0.5, converted to photons: localized with ``qe=0.5`` the
    same emitters come back with standard errors sqrt(2) larger than the photon-counting
    model claims (their photoelectrons carry half the information). The frame solver (on
    either engine) and the hybrid solver."""
    from sparseloc.camera import Camera, to_photons
    from sparseloc.simulate import simulate

    model = make_psf("dh-analytic")
    cam = Camera(offset=100.0, gain=1.0, qe=0.5)
    sim = simulate(
        model,
        scene="uniform",
        n_frames=3,
        shape=(32, 32),
        pixel_size=PX,
        density=0.15,
        photons=(4000.0, 5000.0),
        background=10.0,
        seed=5,
        z_range=(-300.0, 300.0),
        camera=cam,
    )
    frames = to_photons(sim.movie, cam)
    # searched with a margin around the emitters' depths: fits are bounded by the range
    kw = dict(pixel_size=PX, z_range=(-400.0, 400.0), background="spatial", **solver)
    with pytest.raises(ValueError, match="qe"):
        LocalizeParams(**kw, qe=0.0)
    plain = localize(frames, model, LocalizeParams(**kw)).table
    got = localize(frames, model, LocalizeParams(**kw, qe=0.5)).table
    # the same decisions (the frame solver's add threshold is on the photon-counting scale)
    # and the same optimum: the same localizations
    assert len(got) == len(plain) >= 3
    for col in ("x_nm", "y_nm", "z_nm", "photons"):
        np.testing.assert_allclose(got[col], plain[col], rtol=1e-6, atol=1e-3)
    assert evaluate(got, sim.truth).recall >= 0.8
    # goodness of fit: about 1 on the photoelectrons' scale, about 1 / qe without it
    assert 0.8 < got["gof"].median() < 1.3 and plain["gof"].median() > 1.6
    ratio = got["sigma_x_nm"].to_numpy() / plain["sigma_x_nm"].to_numpy()
    assert np.allclose(ratio, np.sqrt(2.0), rtol=0.1)


@pytest.mark.parametrize("bad", [-1, 1.5])
def test_relocate_must_be_a_whole_number(bad):
    with pytest.raises(ValueError, match="relocate"):
        LocalizeParams(pixel_size=PX, relocate=bad)


def test_relocate_reaches_the_frame_solver():
    """LocalizeParams.relocate is what the frame solver's fits get."""
    from sparseloc.pipeline import _FrameSolver

    model = make_psf("dh-analytic")
    for n in (0, 3):
        solver = _FrameSolver(model, LocalizeParams(pixel_size=PX, relocate=n), (32, 32))
        assert solver.fit_kwargs()["relocate"] == n


def test_summary_counts_groups_for_the_frame_solver():
    from sparseloc.io.tables import empty_locs
    from sparseloc.pipeline import LocalizeResult

    frame = LocalizeResult(empty_locs(), 2, 7, 1.0, {"params": {"method": "frame"}})
    assert "7 groups" in frame.summary() and "windows" not in frame.summary()
    hybrid = LocalizeResult(empty_locs(), 2, 7, 1.0, {"params": {"method": "hybrid"}})
    assert "7 windows" in hybrid.summary()


def test_the_runs_z_range_bounds_the_fits_not_only_the_search():
    """Emitters 80 nm beyond the run's z range: every fit stays inside it (the emitters' own
    at its end, flagged), as a pupil model's own range bounds them, instead of settling
    where the model's wider range lets them."""
    from sparseloc.psf.spline import SplinePSF

    model = SplinePSF.from_model(make_psf("dh-analytic"), PX, roi=21, z_step=20.0)
    truth = np.array([[1500.0, 1600.0, 380.0, 5000.0], [3600.0, 3400.0, 380.0, 5000.0]])
    mu = model.render(*truth.T, (32, 32), PX) + 10.0
    frames = np.random.default_rng(0).poisson(mu)[None].astype(float)
    table = localize(frames, model, LocalizeParams(pixel_size=PX, z_range=(-300.0, 300.0))).table
    assert len(table) >= 2 and table["z_nm"].max() <= 300.0 + 1e-6
    xy = table[["x_nm", "y_nm"]].to_numpy()
    nearest = [np.argmin(np.hypot(*(xy - t[:2]).T)) for t in truth]
    assert list(table["flag"].iloc[nearest]) == ["z_edge", "z_edge"]
    assert model.z_range == (-1000.0, 1000.0)  # the caller's model is left as it was


def test_a_narrowed_table_renders_the_same_images_and_refuses_a_range_beyond_its_own():
    from sparseloc.psf.spline import SplinePSF

    model = SplinePSF.from_model(make_psf("dh-analytic"), PX, roi=21, z_step=20.0)
    assert model.within(None) is model and model.within(model.z_range) is model
    narrow = model.within((-200.0, 400.0))
    assert narrow.z_range == (-200.0, 400.0)
    np.testing.assert_array_equal(
        narrow.images([800.0], [800.0], [100.0], (11, 11), PX),
        model.images([800.0], [800.0], [100.0], (11, 11), PX),
    )
    with pytest.raises(ValueError, match="within the PSF model's"):
        localize(np.zeros((1, 32, 32)), model, LocalizeParams(pixel_size=PX, z_range=(-5e3, 0.0)))


@pytest.mark.parametrize("z_max", [600.0, 200.0])
def test_the_run_summary_notes_emitters_beyond_the_z_range(capsys, z_max):
    """A sample deeper than the model's z range leaves its deep emitters' fits stopped at
    the range's ends (flag z_edge), with no z: the run summary says how many; a sample within
    the range gets no note."""
    from sparseloc.cli import _run_notes, _z_ends_note
    from sparseloc.simulate import simulate

    model = make_psf("astig-gauss")
    sim = simulate(model, scene="uniform", n_frames=3, shape=(64, 64), pixel_size=100.0,
                   density=0.5, photons=(2000.0, 5000.0), background=10.0, seed=0)  # fmt: skip
    frames = sim.movie.astype(np.float64) - sim.camera.offset
    p = LocalizeParams(pixel_size=100.0, z_range=(-z_max, z_max))
    res = localize(frames, model, p)
    edge = int((res.table["flag"] == "z_edge").sum())
    ends = res.metadata.get("at_z_ends")
    _run_notes(res.metadata)
    out = capsys.readouterr().out
    if z_max == 600.0:
        assert ends is None and "z_edge" not in out
    else:
        assert ends["count"] == edge > 0.2 * len(res.table)
        assert f"note: {edge} localizations" in out and "-200 to 200 nm" in out
        # the run narrowed the model's range: widening it is the remedy, not a new model
        assert "widen --z-min / --z-max (the model covers -600 to 600 nm)" in out
        full = {**ends, "z_min_nm": -600.0, "z_max_nm": 600.0}
        assert "a model over a deeper range" in _z_ends_note(full)


def test_a_clipped_movie_is_localized_from_its_unclipped_pixels():
    # Bright emitters whose peaks a camera clips: taken at face value the flat peaks give a
    # false emitter and misplaced ones (measured: Jaccard 83.3 %, RMSE 10.7 / 10.8 nm);
    # with the saturation given, the clipped pixels leave the fits and the table is the
    # unclipped movie's (90.9 %, 2.0 / 4.4 nm against 2.0 / 4.6 nm).
    from dataclasses import replace

    from sparseloc.simulate import simulate

    px = 100.0
    model = make_psf("astig-gauss")
    sim = simulate(model, scene="uniform", n_frames=2, shape=(40, 40), pixel_size=px,
                   density=0.25, photons=(20000.0, 40000.0), background=10.0,
                   seed=4)  # fmt: skip
    frames = sim.movie.astype(float) - sim.camera.offset
    clip = 1500.0
    clipped = np.minimum(frames, clip)
    assert np.count_nonzero(frames >= clip) >= 20
    p = LocalizeParams(pixel_size=px)
    runs = {
        "whole": localize(frames, model, p, check=False),
        "face value": localize(clipped, model, p, check=False),
        "censored": localize(clipped, model, replace(p, saturation=clip), check=False),
    }
    ev = {k: evaluate(r.table, sim.truth) for k, r in runs.items()}
    assert abs(ev["censored"].rmse_lateral - ev["whole"].rmse_lateral) < 1.0
    assert abs(ev["censored"].rmse_axial - ev["whole"].rmse_axial) < 1.0
    assert ev["censored"].jaccard == ev["whole"].jaccard
    assert ev["face value"].rmse_lateral > 3 * ev["whole"].rmse_lateral
    assert ev["censored"].jaccard > ev["face value"].jaccard
    assert runs["censored"].metadata["params"]["saturation"] == clip
