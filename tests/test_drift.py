"""Drift correction (RCC and fiducials) on simulated localizations with a known drift."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from sparseloc.drift import DriftResult, apply_drift, fiducial_drift, plot_drift, rcc_drift
from sparseloc.io.tables import complete_locs, empty_locs
from sparseloc.simulate import filament_scene

N_FRAMES = 600
FOV_NM = 4000.0
NOISE_NM = np.array([15.0, 15.0, 40.0])  # lateral, lateral, axial localization noise


def true_drift(frames: np.ndarray) -> np.ndarray:
    """A slow non-linear drift (nm), zero at frame 0: ~200 nm in x and y, 100 nm in z."""
    u = np.asarray(frames, dtype=float) / (N_FRAMES - 1)
    return np.stack(
        [200 * u**1.5, -150 * u + 50 * np.sin(2 * np.pi * u), 50 * (1 - np.cos(np.pi * u))],
        axis=1,
    )


def observe(truth: pd.DataFrame, rng: np.random.Generator) -> pd.DataFrame:
    """Localizations = truth + drift of the frame + Gaussian noise."""
    pos = truth[["x_nm", "y_nm", "z_nm"]].to_numpy()
    pos = pos + true_drift(truth["frame"].to_numpy()) + rng.normal(0, NOISE_NM, pos.shape)
    return pd.DataFrame(
        {
            "frame": truth["frame"].to_numpy(),
            "x_nm": pos[:, 0],
            "y_nm": pos[:, 1],
            "z_nm": pos[:, 2],
        }
    )


def rms_error(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-axis RMS of the difference after removing the constant offset (drift is defined up
    to a constant)."""
    diff = est - truth
    diff = diff - diff.mean(axis=0)
    return np.sqrt(np.mean(diff**2, axis=0))


@pytest.fixture(scope="module")
def truth() -> pd.DataFrame:
    rng = np.random.default_rng(7)
    return filament_scene(rng, N_FRAMES, (FOV_NM, FOV_NM), n_filaments=3)[
        ["frame", "x_nm", "y_nm", "z_nm"]
    ].reset_index(drop=True)


@pytest.fixture(scope="module")
def locs(truth) -> pd.DataFrame:
    return observe(truth, np.random.default_rng(8))


@pytest.fixture(scope="module")
def rcc(locs) -> DriftResult:
    return rcc_drift(locs)


def test_rcc_recovers_drift(rcc, locs):
    assert rcc.method == "rcc"
    assert rcc.reliable, rcc.warnings
    assert rcc.warnings == []
    np.testing.assert_array_equal(rcc.frames, np.arange(locs.frame.min(), locs.frame.max() + 1))
    assert rcc.drift.shape == (rcc.frames.size, 3)
    np.testing.assert_array_equal(rcc.drift[0], 0.0)  # convention: zero at the first frame
    truth = true_drift(rcc.frames)
    err = rms_error(rcc.drift, truth)
    assert err[0] < 15 and err[1] < 15, err
    assert err[2] < 25, err
    # the estimate must follow the drift, not just be small: doing nothing is far off
    assert np.all(rms_error(np.zeros_like(truth), truth)[:2] > 45)
    assert np.corrcoef(rcc.drift[:, 2], truth[:, 2])[0, 1] > 0.98
    assert rcc.segment_shifts.shape == (10, 3)
    assert rcc.pairs.shape == (45, 2)
    assert rcc.pair_used.all()


def test_inconsistent_pair_rejected(locs):
    # a cloud of blinking molecules seen in segment 3 (frames 180-239) and, displaced by
    # (400, -300) nm, in segment 7 (frames 420-479): pair (3, 7) peaks at the wrong shift
    rng = np.random.default_rng(9)
    cx, cy = (np.repeat(rng.uniform(0, FOV_NM, 1000), 4) for _ in range(2))
    cloud = [
        pd.DataFrame(
            {"frame": rng.integers(lo, lo + 60, cx.size), "x_nm": cx + dx, "y_nm": cy + dy}
        )
        for lo, dx, dy in ((180, 0.0, 0.0), (420, 400.0, -300.0))
    ]
    table = pd.concat([locs, *cloud], ignore_index=True).assign(z_nm=lambda t: t.z_nm.fillna(0))
    res = rcc_drift(table)
    k = next(i for i, (a, b) in enumerate(res.pairs) if (a, b) == (3, 7))
    assert not res.pair_used[k, 0]
    assert res.pair_used[:, 0].sum() == len(res.pairs) - 1
    assert res.reliable, res.warnings
    truth = true_drift(res.frames)
    assert np.all(rms_error(res.drift, truth) < [15, 15, 25])
    # without the rejection the bad pair pulls segments 3 and 7 off
    design = np.zeros((len(res.pairs), 10))
    design[np.arange(len(res.pairs)), res.pairs[:, 1]] = 1
    design[np.arange(len(res.pairs)), res.pairs[:, 0]] = -1
    naive = np.linalg.lstsq(design[:, 1:], res.pair_shifts[:, :2], rcond=None)[0]
    naive = np.vstack([[0.0, 0.0], naive]) - res.segment_shifts[0, :2]
    assert np.max(np.abs(naive - res.segment_shifts[:, :2])) > 20


def test_apply_drift_brings_positions_closer(rcc, locs, truth):
    before = locs.copy()
    corrected = apply_drift(locs, rcc)
    pd.testing.assert_frame_equal(locs, before)  # input untouched
    cols = ["x_nm", "y_nm", "z_nm"]
    ref = truth[cols].to_numpy()
    err_before = rms_error(locs[cols].to_numpy(), ref)
    err_after = rms_error(corrected[cols].to_numpy(), ref)
    assert np.all(err_after < err_before), (err_before, err_after)
    # what remains is the localization noise
    assert np.all(err_after < 1.15 * NOISE_NM), err_after


def test_at_and_apply_with_known_drift():
    frames = np.arange(10, 15)
    drift = np.column_stack([np.arange(5.0), -np.arange(5.0), 2 * np.arange(5.0)])
    res = DriftResult(frames=frames, drift=drift, method="test")
    np.testing.assert_allclose(res.at([10, 12.5, 14]), [[0, 0, 0], [2.5, -2.5, 5], [4, -4, 8]])
    np.testing.assert_allclose(res.at([0, 100]), [[0, 0, 0], [4, -4, 8]])  # clamped
    table = pd.DataFrame({"frame": [10, 13, 99], "x_nm": [1.0, 1.0, 1.0], "y_nm": [0.0] * 3})
    out = apply_drift(table, res)
    np.testing.assert_allclose(out["x_nm"], [1.0, -2.0, -3.0])
    np.testing.assert_allclose(out["y_nm"], [0.0, 3.0, 4.0])
    assert "z_nm" not in out.columns
    full = apply_drift(complete_locs(table.assign(z_nm=[0.0, 0.0, 0.0])), res)
    np.testing.assert_allclose(full["z_nm"], [0.0, -6.0, -8.0])
    assert len(apply_drift(empty_locs(), res)) == 0
    with pytest.raises(ValueError, match="shape"):
        DriftResult(frames=frames, drift=drift[:, :2], method="test")


def test_fiducial_drift_recovers_drift(truth):
    rng = np.random.default_rng(11)
    beads = []
    for _ in range(3):
        x, y = rng.uniform(0.15 * FOV_NM, 0.85 * FOV_NM, 2)
        present = np.nonzero(rng.random(N_FRAMES) < 0.95)[0]
        beads.append(pd.DataFrame({"frame": present, "x_nm": x, "y_nm": y, "z_nm": 100.0}))
    scene = pd.concat([truth, *beads], ignore_index=True).sort_values("frame", kind="stable")
    res = fiducial_drift(observe(scene, rng))
    assert res.method == "fiducial"
    assert res.reliable, res.warnings
    assert res.fiducials.shape == (3, 3)
    assert min(res.details["frames_present"]) >= 0.8 * N_FRAMES
    np.testing.assert_array_equal(res.drift[0], 0.0)
    err = rms_error(res.drift, true_drift(res.frames))
    assert err[0] < 10 and err[1] < 10, err
    assert err[2] < 20, err


def test_a_steady_fiducial_drift_is_followed_to_the_movies_ends():
    """A drift at a steady rate (60 and 30 nm over 150 frames) seen on three fiducials with
    2 nm noise: its smoothing keeps the rate at both ends (a mirror there would flatten the
    first and last dozen frames and shorten the span)."""
    rng = np.random.default_rng(4)
    frames = np.arange(150)
    rows = []
    for x, y in ((1000.0, 1200.0), (2500.0, 3000.0), (3300.0, 800.0)):
        drift = np.stack([0.4 * frames, 0.2 * frames], axis=1)
        xy = np.array([x, y]) + drift + rng.normal(0.0, 2.0, (frames.size, 2))
        rows.append(pd.DataFrame({"frame": frames, "x_nm": xy[:, 0], "y_nm": xy[:, 1]}))
    res = fiducial_drift(pd.concat(rows, ignore_index=True).sort_values("frame", kind="stable"))
    span = res.drift[-1, :2] - res.drift[0, :2]
    np.testing.assert_allclose(span, [0.4 * 149, 0.2 * 149], atol=1.5)
    truth = np.stack([0.4 * res.frames, 0.2 * res.frames], axis=1)
    assert np.all(rms_error(res.drift[:, :2], truth) < 1.0)


def test_fiducial_presence_threshold(truth):
    # one bead seen in 70 % of the frames: a fiducial only when min_fraction allows it
    rng = np.random.default_rng(12)
    present = np.nonzero(rng.random(N_FRAMES) < 0.7)[0]
    # away from the filaments, so that no molecule stands in for the bead when it is off
    grid = np.stack(np.meshgrid(*[np.linspace(500, FOV_NM - 500, 15)] * 2), -1).reshape(-1, 2)
    xy = truth[["x_nm", "y_nm"]].to_numpy()
    far = grid[np.argmax([np.min(np.hypot(*(xy - g).T)) for g in grid])]
    bead = pd.DataFrame({"frame": present, "x_nm": far[0], "y_nm": far[1], "z_nm": 0.0})
    table = observe(pd.concat([truth, bead], ignore_index=True), rng)
    with pytest.raises(ValueError, match=r"present in >= 480 of the 600 frames"):
        fiducial_drift(table, min_fraction=0.8)
    res = fiducial_drift(table, min_fraction=0.6)
    assert res.details["fiducials"] == 1
    assert abs(res.details["frames_present"][0] - present.size) <= 5
    assert any("single fiducial" in w for w in res.warnings)
    err = rms_error(res.drift[:, :2], true_drift(res.frames)[:, :2])
    assert np.all(err < 10), err


def test_fiducial_drift_without_fiducials_raises(locs):
    with pytest.raises(ValueError, match=r"no fiducial found.*best candidates: \d+ frames"):
        fiducial_drift(locs)


def test_sparse_table_raises():
    rng = np.random.default_rng(3)
    n = 30
    sparse = pd.DataFrame(
        {
            "frame": rng.integers(0, 100, n),
            "x_nm": rng.uniform(0, 5000, n),
            "y_nm": rng.uniform(0, 5000, n),
        }
    )
    with pytest.raises(ValueError, match=r"too few localizations.*30 usable"):
        rcc_drift(sparse)


@pytest.mark.parametrize(
    ("n", "fov_nm", "reason"),
    [
        (5000, 5000.0, "valid correlation peak"),  # dense: no peak stands out of the noise
        (2500, 20000.0, "disagree"),  # sparse: chance coincidences give inconsistent peaks
    ],
)
def test_unstructured_data_flagged_unreliable(n, fov_nm, reason):
    # independent random positions: nothing is shared between segments to correlate
    rng = np.random.default_rng(4)
    noise = pd.DataFrame(
        {
            "frame": rng.integers(0, 1000, n),
            "x_nm": rng.uniform(0, fov_nm, n),
            "y_nm": rng.uniform(0, fov_nm, n),
            "z_nm": rng.uniform(-500, 500, n),
        }
    )
    res = rcc_drift(noise)
    assert not res.reliable
    assert not res.details["reliable_xy"] and not res.details["reliable_z"]
    assert any(w.startswith("xy:") and reason in w for w in res.warnings), res.warnings
    assert any(w.startswith("z:") for w in res.warnings)


def test_fewer_locs_reduce_segments(locs):
    per_segment = len(locs) // 6
    res = rcc_drift(locs, min_locs_per_segment=per_segment)
    assert 2 < res.details["segments"] < 10
    assert any("reduced segments from 10" in w for w in res.warnings)
    assert res.reliable  # fewer segments is a note, not a failure
    err = rms_error(res.drift, true_drift(res.frames))
    assert np.all(err < [15, 15, 25]), err


def test_drift_beyond_max_shift_flagged(locs):
    # the x/y drift spans ~200 nm: a +-150 nm search cannot measure the distant pairs
    res = rcc_drift(locs, max_shift_nm=150.0)
    assert not res.reliable and not res.details["reliable_xy"]
    assert any(w.startswith("xy:") and "raise max_shift_nm" in w for w in res.warnings)


def test_two_segments_not_cross_checked(locs):
    res = rcc_drift(locs, segments=2)
    assert not res.reliable
    assert any("cannot be cross-checked" in w for w in res.warnings)


def test_2d_table(locs):
    table = locs.drop(columns="z_nm")
    # a full table from complete_locs (z filled with 0) plus flagged junk far outside the field
    full = complete_locs(table)
    junk = full.iloc[:5].assign(x_nm=1e7, flag="diverged")
    full = pd.concat([full, junk], ignore_index=True)
    for t in (table, full):
        res = rcc_drift(t)
        assert res.reliable, res.warnings
        assert not res.details["z_estimated"]
        np.testing.assert_array_equal(res.drift[:, 2], 0.0)
        err = rms_error(res.drift[:, :2], true_drift(res.frames)[:, :2])
        assert np.all(err < 15), err
    out = apply_drift(table, res)
    assert list(out.columns) == list(table.columns)


@pytest.mark.parametrize(
    ("table", "kwargs", "match"),
    [
        (empty_locs(), {}, "empty"),
        (pd.DataFrame({"frame": [0, 1], "x_nm": [0.0, 1.0]}), {}, "missing the column"),
        (pd.DataFrame({"frame": np.arange(5), "x_nm": 0.0, "y_nm": 0.0}), {}, "5 frame"),
        (pd.DataFrame({"frame": [0, 1], "x_nm": 0.0, "y_nm": 0.0}), {"segments": 1}, "segments"),
        (pd.DataFrame({"frame": [0, 1], "x_nm": 0.0, "y_nm": 0.0}), {"bin_nm": -1}, "bin_nm"),
        (pd.DataFrame({"frame": [0.5], "x_nm": [0.0], "y_nm": [0.0]}), {}, "whole numbers"),
        ("not a table", {}, "DataFrame"),
    ],
)
def test_rcc_bad_input(table, kwargs, match):
    with pytest.raises(ValueError, match=match):
        rcc_drift(table, **kwargs)


def test_fiducial_bad_input(locs):
    with pytest.raises(ValueError, match="min_fraction"):
        fiducial_drift(locs, min_fraction=1.5)
    with pytest.raises(ValueError, match="radius_nm"):
        fiducial_drift(locs, radius_nm=0)
    with pytest.raises(ValueError, match="empty"):
        fiducial_drift(empty_locs())


def test_plot_drift(rcc, tmp_path):
    path = plot_drift(rcc, tmp_path / "drift.png", truth=true_drift(rcc.frames))
    assert path == tmp_path / "drift.png"
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="truth must have shape"):
        plot_drift(rcc, tmp_path / "bad.png", truth=np.zeros((3, 3)))
    assert not (tmp_path / "bad.png").exists()


def test_segment_messages_name_a_possible_count():
    # one frame: no count of segments works; a few frames: the range that does
    one = pd.DataFrame({"frame": [3, 3, 3], "x_nm": 0.0, "y_nm": 0.0})
    with pytest.raises(ValueError, match="needs localizations in at least 2 frames"):
        rcc_drift(one, segments=2)
    few = pd.DataFrame({"frame": [0, 1, 2], "x_nm": 0.0, "y_nm": 0.0})
    with pytest.raises(ValueError, match="use between 2 and 3 segments"):
        rcc_drift(few, segments=5)


def test_smooth_p_tells_a_drift_from_independent_noise():
    """Von Neumann's ratio: independent shifts are called a drift about 1 % of the time (the
    test's level), a slow drift under that noise always."""
    from sparseloc.drift import NO_DRIFT_P, smooth_p

    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 3.0, (4000, 10, 1))
    called = np.mean([smooth_p(s)[0] < NO_DRIFT_P for s in noise])
    assert 0.002 < called < 0.03, called
    trend = np.linspace(0.0, 30.0, 10)[:, None]
    assert np.all([smooth_p(trend + s)[0] < NO_DRIFT_P for s in noise[:200]])
    assert np.isnan(smooth_p(np.zeros((10, 1)))[0]) and np.isnan(smooth_p(noise[0, :3])[0])
    # the fifth walk-through: 4 segments of a straight drift were called noise; below 6
    # segments even a straight line is not told apart from noise at 1 %, and none is said
    line = np.linspace(0.0, 100.0, 10)[:, None]
    assert np.isnan(smooth_p(line[:4])[0]) and np.isnan(smooth_p(line[:5])[0])
    assert smooth_p(line[:6])[0] < NO_DRIFT_P


def test_a_drift_free_table_gets_a_caution_and_a_drifting_one_none(truth, locs, tmp_path):
    """The fourth walk-through: the default 10 segments moved a drift-free simulation by a
    few nm without a word."""
    from typer.testing import CliRunner

    from sparseloc.cli import app
    from sparseloc.drift import no_drift_caution
    from sparseloc.io.tables import read_table_and_metadata, write_table

    assert no_drift_caution(rcc_drift(locs, log_warnings=False)) is None
    rng = np.random.default_rng(8)
    pos = truth[["x_nm", "y_nm", "z_nm"]].to_numpy() + rng.normal(0, NOISE_NM, (len(truth), 3))
    still = pd.DataFrame({"frame": truth["frame"], "x_nm": pos[:, 0], "y_nm": pos[:, 1],
                          "z_nm": pos[:, 2]})  # fmt: skip
    assert "like noise" in no_drift_caution(rcc_drift(still, log_warnings=False))
    src = tmp_path / "still.parquet"
    write_table(complete_locs(still), src)
    res = CliRunner().invoke(app, ["drift", str(src), "-o", str(tmp_path / "dc.parquet")])
    assert res.exit_code == 0, res.output
    assert "caution: the 10 segments' shifts vary" in res.output
    _, meta = read_table_and_metadata(tmp_path / "dc.parquet")
    assert "like noise" in meta["drift"]["caution"]


def test_an_unreliable_z_advises_fewer_segments_or_no_z_in_the_commands_terms():
    """Issue 27 item 8: the warning of a z stage that found too few correlations names what a
    user can change (fewer segments, ``drift --no-z``), not the library's ``estimate_z``."""
    rng = np.random.default_rng(0)
    n = 20000
    t, ang = rng.uniform(0, 1, n), rng.integers(0, 6, n) * 0.5  # lines in xy
    table = pd.DataFrame(
        {
            "frame": rng.integers(0, 500, n),
            "x_nm": 2000 + 4000 * t * np.cos(ang) + rng.normal(0, 15, n),
            "y_nm": 2000 + 4000 * t * np.sin(ang) + rng.normal(0, 15, n),
            "z_nm": rng.uniform(-800, 800, n),  # no structure in z: no z correlation
        }
    )
    res = rcc_drift(table, segments=5, log_warnings=False)
    z_warnings = [w for w in res.warnings if w.startswith("z:")]
    assert any("fewer segments" in w and "drift --no-z" in w for w in z_warnings), res.warnings
    assert not any("estimate_z" in w or "=" in w for w in res.warnings), res.warnings


def test_the_plot_of_a_drift_whose_z_was_rejected_shows_no_z_points(tmp_path, monkeypatch):
    """A new user's drift.png said "rcc drift (reliable)" and "dz (not estimated)" while
    green dz points were drawn: the rejected z stage's segment shifts."""
    import sparseloc.plotting
    from sparseloc.drift import lateral_only

    rng = np.random.default_rng(0)
    n = 20000
    t, ang = rng.uniform(0, 1, n), rng.integers(0, 6, n) * 0.5
    frame = rng.integers(0, 500, n)
    table = pd.DataFrame(
        {
            "frame": frame,
            "x_nm": 2000 + 4000 * t * np.cos(ang) + rng.normal(0, 15, n) + 0.02 * frame,
            "y_nm": 2000 + 4000 * t * np.sin(ang) + rng.normal(0, 15, n),
            "z_nm": rng.uniform(-800, 800, n),  # no z structure: the z stage fails
        }
    )
    xy = lateral_only(rcc_drift(table, segments=5, log_warnings=False))
    assert xy is not None and xy.reliable
    drawn = {}
    monkeypatch.setattr(
        sparseloc.plotting, "save_figure", lambda fig, path, dpi: drawn.update(fig=fig)
    )
    plot_drift(xy, tmp_path / "d.png")
    ax = drawn["fig"].axes[0]
    assert "z unreliable, not corrected" in ax.get_title()
    z_lines = [ln for ln in ax.get_lines() if ln.get_color() == "C2"]
    assert len(z_lines) == 1 and np.all(z_lines[0].get_ydata() == 0.0)
    assert "dz (not corrected: unreliable)" in [ln.get_label() for ln in z_lines]


def test_the_range_names_a_z_the_estimate_left_alone():
    """A z that the estimate did not correct (its pairs unreliable, or a 2D table) is named
    so in the range the drift command and the report print, not read as a measured 0 nm."""
    from sparseloc.drift_common import DriftResult

    frames = np.arange(10)
    drift = np.column_stack([np.linspace(0, 40, 10), np.linspace(0, -30, 10), np.zeros(10)])
    kept = DriftResult(frames, drift, "rcc", details={"z_estimated": True})
    assert kept.range_text() == "x 40.0 nm, y 30.0 nm, z 0.0 nm"
    dropped = DriftResult(
        frames, drift, "rcc", details={"z_estimated": False, "z_dropped": ["z: ..."]}
    )
    assert dropped.range_text(0) == "x 40 nm, y 30 nm, z not corrected (unreliable)"
    flat = DriftResult(frames, drift, "fiducial", details={"z_estimated": False})
    assert flat.range_text().endswith("z not estimated")
