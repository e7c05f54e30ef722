"""Issue 27 items 1, 10 and 19 (render/report/merge): impossible uncertainties are flagged, every
consumer treats flagged rows by one rule, absurd coordinates and frames cannot blow up memory,
and ``sparseloc overlay`` draws localizations over a frame of the movie."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from sparseloc.cli import app
from sparseloc.io.tables import complete_locs, read_parquet, write_table
from sparseloc.psf import make_psf
from sparseloc.solvers import Emitters
from sparseloc.solvers.refine import fit_emitters

PX = 100.0
runner = CliRunner()


def _table(n: int = 300, seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    df = pd.DataFrame(
        {
            "frame": rng.integers(0, 50, n),
            "x_nm": rng.uniform(0, 5000, n),
            "y_nm": rng.uniform(0, 5000, n),
            "z_nm": rng.uniform(-300, 300, n),
            "photons": 2000.0,
            "sigma_x_nm": 10.0,
            "sigma_y_nm": 10.0,
            "sigma_z_nm": 30.0,
            "gof": 1.0,
        }
    )
    return complete_locs(df)


def _with_bad_rows(df: pd.DataFrame) -> pd.DataFrame:
    """Rows as an old ``localize`` wrote them: flagged, with absurd or NaN uncertainties."""
    t = df.copy()
    t.loc[:59, "flag"] = "z_edge"
    t.loc[:19, "sigma_z_nm"] = 9.7e9
    t.loc[20:39, "sigma_z_nm"] = 1e-14
    t.loc[40:59, ["sigma_x_nm", "sigma_y_nm", "sigma_z_nm"]] = np.nan
    return t


def _window(model, truth, shape=(17, 17), background=10.0, seed=0):
    t = np.atleast_2d(truth)
    mu = model.render(t[:, 0], t[:, 1], t[:, 2], t[:, 3], shape, PX) + background
    return np.random.default_rng(seed).poisson(mu).astype(float)


# -- item 1: the rule that writes uncertainties and flags --------------------------------------


def test_fit_flags_rule_nans_impossible_uncertainties():
    from sparseloc.solvers.mle import fit_flags

    em = np.array(
        [
            [800.0, 800.0, 0.0, 3000.0],  # fine
            [800.0, 800.0, 0.0, 3000.0],  # sigma_z 1e9 nm
            [800.0, 800.0, 0.0, 3000.0],  # sigma_x 1e-14 nm
            [800.0, 800.0, 0.0, 3000.0],  # NaN sigma
            [800.0, 800.0, 1000.0, 3000.0],  # z on the range's edge
        ]
    )
    good = [8.0, 8.0, 20.0, 60.0]
    sd = np.array(
        [good, [8.0, 8.0, 1e9, 60.0], [1e-14, 8.0, 20.0, 60.0], [8.0, np.nan, 20.0, 60.0], good]
    )
    sigma, flags = fit_flags(
        em, sd, z_range=(-1000.0, 1000.0), window=(0.0, 0.0, 1700.0, 1700.0), converged=True
    )
    assert flags[0] == "ok" and np.allclose(sigma[0], good)
    assert list(flags[1:4]) == ["bad_sigma"] * 3
    assert flags[4] == "z_edge"
    assert np.isnan(sigma[1:]).all()
    # a Fisher matrix that is not positive definite voids every emitter of the fit
    sigma, flags = fit_flags(
        em[:1],
        sd[:1],
        z_range=(-1000.0, 1000.0),
        window=(0.0, 0.0, 1700.0, 1700.0),
        converged=True,
        fisher_ok=False,
    )
    assert flags[0] == "bad_sigma" and np.isnan(sigma).all()


def test_fit_at_the_z_edge_has_nan_uncertainties(dh_model):
    narrow = make_psf("dh", z_range=(-300.0, 300.0))
    img = _window(dh_model, [[850.0, 850.0, 700.0, 3000.0]], seed=6)
    fit = fit_emitters(
        img, narrow, Emitters.from_array([[850.0, 850.0, 200.0, 3000.0]]), pixel_size=PX
    )
    assert fit.flags[0] == "z_edge"
    assert np.isnan(fit.sigma[0]).all()


def test_fit_with_a_singular_fisher_matrix_is_flagged():
    model = make_psf("dh-analytic")
    img = _window(model, [[850.0, 850.0, 0.0, 3000.0]], seed=1)
    # two identical starting emitters stay identical: their parameters cannot be told apart
    start = Emitters.from_array([[850.0, 850.0, 0.0, 1500.0], [850.0, 850.0, 0.0, 1500.0]])
    fit = fit_emitters(img, model, start, pixel_size=PX)
    assert np.all(fit.flags != "ok")
    assert np.isnan(fit.sigma).all()


def test_an_emitter_without_z_information_leaves_its_neighbour_its_uncertainties():
    """A spline whose images stop changing towards the end of its z range (as calibrated
    ones do) gives an emitter fitted there no z information; its neighbour keeps its
    uncertainties."""
    from sparseloc.psf.spline import SplinePSF

    z = np.arange(-300.0, 301.0, 20.0)
    stack = make_psf("dh-analytic").images(
        np.full(z.size, 1250.0), np.full(z.size, 1250.0), z, (25, 25), PX
    )
    stack[:3] = stack[3]
    model = SplinePSF(stack, PX, z, normalise=False)
    truth = np.array([[700.0, 1200.0, -300.0, 3000.0], [2700.0, 1200.0, 0.0, 3000.0]])
    img = _window(model, truth, shape=(25, 35), seed=6)
    fit = fit_emitters(img, model, Emitters.from_array(truth), pixel_size=PX)
    assert list(fit.flags) == ["z_edge", "ok"]
    assert np.isnan(fit.sigma[0]).all()
    assert np.all(np.isfinite(fit.sigma[1])) and 1.0 < fit.sigma[1, 0] < 50.0


def test_the_standard_errors_of_the_constrained_parameters_survive_an_unconstrained_one():
    from sparseloc.solvers.mle import _standard_errors

    rng = np.random.default_rng(3)
    a = rng.normal(size=(6, 6))
    good = a @ a.T + 6.0 * np.eye(6)
    fisher = np.zeros((7, 7))
    fisher[:6, :6] = good
    sd, ok = _standard_errors(fisher)  # the last parameter carries no information
    assert ok and np.isnan(sd[6])
    assert np.allclose(sd[:6], np.sqrt(np.diag(np.linalg.inv(good))))
    twin = np.zeros((8, 8))  # parameters 6 and 7 enter the data only as their sum
    twin[:6, :6] = good
    twin[6:, 6:] = 2.0
    sd, ok = _standard_errors(twin)
    assert ok and np.isnan(sd[6:]).all()
    assert np.allclose(sd[:6], np.sqrt(np.diag(np.linalg.inv(good))))


def test_well_posed_fit_keeps_its_uncertainties():
    model = make_psf("dh-analytic")
    truth = np.array([[860.0, 830.0, 250.0, 3000.0]])
    img = _window(model, truth, seed=2)
    fit = fit_emitters(img, model, Emitters.from_array(truth + 20.0), pixel_size=PX)
    assert fit.flags[0] == "ok"
    assert np.all(np.isfinite(fit.sigma)) and 1.0 < fit.sigma[0, 0] < 50.0


# -- item 1: one rule for the consumers ---------------------------------------------------------


def test_usable_locs_excludes_flagged_rows_unless_all_flags():
    from sparseloc.postprocess import usable_locs

    t = _with_bad_rows(_table())
    assert len(usable_locs(t)) == len(t) - 60
    assert (usable_locs(t)["flag"] == "ok").all()
    assert len(usable_locs(t, all_flags=True)) == len(t)


def test_render_excludes_flagged_rows_and_all_flags_includes_them(tmp_path):
    src = tmp_path / "locs.parquet"
    write_table(_with_bad_rows(_table()), src)
    r = runner.invoke(app, ["render", str(src), "-o", str(tmp_path / "a.png")])
    assert r.exit_code == 0, r.output
    assert "60 flagged" in r.output
    r = runner.invoke(app, ["render", str(src), "--all-flags", "-o", str(tmp_path / "b.png")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "b.png").stat().st_size > 0


def test_render_memory_is_bounded_by_the_image_not_the_sigmas():
    from sparseloc.render import render_gaussian

    t = _table()
    t.loc[:100, ["sigma_x_nm", "sigma_y_nm"]] = 2e9  # a third of the rows, beyond the 95th pct
    img = render_gaussian(t, px_nm=10.0)
    # the image covers the data (5 um) and a margin, not 4 x 2e9 nm
    assert max(img.density.shape) * 10.0 < 50_000


def test_report_excludes_flagged_rows(tmp_path):
    from sparseloc.report import build_report

    t = _with_bad_rows(_table())
    page = build_report(t)
    assert "excluded 60 flagged" in page
    page = build_report(t, all_flags=True)
    assert "excluded 60 flagged" not in page


def test_evaluate_excludes_flagged_rows(tmp_path):
    from sparseloc.evaluate import evaluate

    t = _table()
    truth = t[["frame", "x_nm", "y_nm", "z_nm", "photons"]].copy()
    t.loc[:99, "flag"] = "z_edge"
    assert evaluate(t, truth).n_locs == len(t) - 100
    assert evaluate(t, truth, all_flags=True).n_locs == len(t)
    src, tr = tmp_path / "l.parquet", tmp_path / "truth.csv"
    write_table(t, src)
    truth.to_csv(tr, index=False)
    r = runner.invoke(app, ["evaluate", str(src), str(tr), "--all-flags"])
    assert r.exit_code == 0, r.output


def test_drift_accepts_all_flags(tmp_path):
    from sparseloc.drift_common import read_locs

    t = _table()
    t.loc[:99, "flag"] = "z_edge"
    assert len(read_locs(t).frame) == len(t) - 100
    assert len(read_locs(t, all_flags=True).frame) == len(t)
    src = tmp_path / "l.parquet"
    write_table(t, src)
    r = runner.invoke(
        app, ["drift", str(src), "--all-flags", "--segments", "2", "-o", str(tmp_path / "d.csv")]
    )
    assert "No such option" not in r.output


def test_filter_merge_excludes_flagged_rows(tmp_path):
    t = _table()
    t.loc[:99, "flag"] = "z_edge"
    src, out = tmp_path / "l.parquet", tmp_path / "m.parquet"
    write_table(t, src)
    r = runner.invoke(app, ["filter", str(src), "--merge", "-o", str(out)])
    assert r.exit_code == 0, r.output
    merged, _ = read_parquet(out)
    assert (merged["flag"] == "ok").all()


# -- item 19: absurd coordinates, frames and all-NaN tables -------------------------------------


@pytest.mark.parametrize("bad", [np.inf, 1e300])
def test_render_drops_absurd_coordinates_with_a_warning(tmp_path, bad, caplog):
    t = _table()
    t.loc[:4, "x_nm"] = bad
    src, out = tmp_path / "l.parquet", tmp_path / "r.png"
    write_table(t, src)
    with caplog.at_level(logging.WARNING):
        r = runner.invoke(app, ["render", str(src), "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert r.exception is None
    assert any("5 localizations" in m and "coordinate" in m for m in caplog.messages), (
        caplog.messages
    )
    assert out.stat().st_size > 0


@pytest.mark.parametrize("bad", [np.inf, 1e300])
def test_report_drops_absurd_coordinates(tmp_path, bad, caplog):
    t = _table()
    t.loc[:4, "y_nm"] = bad
    src, out = tmp_path / "l.parquet", tmp_path / "r.html"
    write_table(t, src)
    with caplog.at_level(logging.WARNING):
        r = runner.invoke(app, ["report", str(src), "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert r.exception is None
    assert any("5 localizations" in m and "coordinate" in m for m in caplog.messages)
    assert out.is_file()


def test_report_with_a_huge_frame_number_stays_small(tmp_path):
    from sparseloc.report import build_report

    t = _table()
    t.loc[0, "frame"] = 2**40
    page = build_report(t)  # the old code asked for 8 TiB
    assert "<img" in page


def test_filter_merge_of_an_all_nan_table_is_one_sentence(tmp_path):
    t = _table()
    for c in ["x_nm", "y_nm", "z_nm", "photons", "sigma_x_nm", "sigma_y_nm", "sigma_z_nm"]:
        t[c] = np.nan
    src, out = tmp_path / "nan.parquet", tmp_path / "m.parquet"
    write_table(t, src)
    r = runner.invoke(app, ["filter", str(src), "--merge", "-o", str(out)])
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    assert r.exception is None or isinstance(r.exception, SystemExit)
    assert r.output.strip().startswith("error:") and r.output.count("\n") == 1
    assert not out.exists()


def test_merge_blinks_of_nan_positions_does_not_crash():
    from sparseloc.postprocess import merge_blinks

    t = _table(5)
    t["x_nm"] = np.nan
    assert len(merge_blinks(t)) == 5


# -- item 10: overlay ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def movie_and_locs(tmp_path_factory):
    """A small dense simulated movie and localizations of its emitters (truth + noise)."""
    import tifffile

    tmp = tmp_path_factory.mktemp("overlay")
    model = make_psf("dh-analytic")
    rng = np.random.default_rng(5)
    frames, rows = [], []
    for f in range(3):
        k = 12
        em = np.column_stack(
            [
                rng.uniform(300, 2900, k),
                rng.uniform(300, 2900, k),
                rng.uniform(-400, 400, k),
                rng.uniform(2000, 4000, k),
            ]
        )
        mu = model.render(em[:, 0], em[:, 1], em[:, 2], em[:, 3], (32, 32), PX) + 10.0
        frames.append(rng.poisson(mu).astype(np.uint16) + 100)
        for e in em:
            rows.append((f, *e))
    movie = tmp / "movie.tif"
    tifffile.imwrite(movie, np.stack(frames), photometric="minisblack")
    df = pd.DataFrame(rows, columns=["frame", "x_nm", "y_nm", "z_nm", "photons"])
    df["x_nm"] += rng.normal(0, 10, len(df))
    df = complete_locs(df)
    df.loc[::5, "flag"] = "z_edge"
    locs = tmp / "locs.parquet"
    write_table(df, locs)
    return movie, locs, df


def test_overlay_library_draws_a_frame(movie_and_locs, tmp_path):
    from sparseloc.overlay import plot_overlay

    movie, _, df = movie_and_locs
    from sparseloc.io.movie import Movie

    with Movie.open(movie) as m:
        frame = m[1]
    out = plot_overlay(frame, df, frame_index=1, pixel_size=PX, path=tmp_path / "o.png")
    assert out.stat().st_size > 1000


def test_overlay_cli_writes_a_png(movie_and_locs, tmp_path):
    movie, locs, _ = movie_and_locs
    out = tmp_path / "overlay.png"
    r = runner.invoke(
        app,
        ["overlay", str(movie), str(locs), "--frame", "1", "--pixel-size", "100", "-o", str(out)],
    )
    assert r.exit_code == 0, r.output
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob("*.tmp*"))


def test_overlay_cli_refuses_a_frame_outside_the_movie(movie_and_locs, tmp_path):
    movie, locs, _ = movie_and_locs
    out = tmp_path / "overlay.png"
    r = runner.invoke(
        app,
        ["overlay", str(movie), str(locs), "--frame", "7", "--pixel-size", "100", "-o", str(out)],
    )
    assert r.exit_code == 2
    assert r.output.startswith("error:") and "frame" in r.output
    assert not out.exists()


def test_report_with_the_movie_has_an_overlay(movie_and_locs, tmp_path):
    movie, locs, _ = movie_and_locs
    out = tmp_path / "r.html"
    r = runner.invoke(
        app, ["report", str(locs), "--movie", str(movie), "--pixel-size", "100", "-o", str(out)]
    )
    assert r.exit_code == 0, r.output
    page = out.read_text()
    assert "Localizations over frame" in page


def test_report_without_the_movie_has_no_overlay(movie_and_locs):
    from sparseloc.report import build_report

    _, _, df = movie_and_locs
    assert "Localizations over frame" not in build_report(df)


def test_warnings_name_the_dropped_rows(caplog):
    from sparseloc.postprocess import usable_locs

    t = _table()
    t.loc[:2, "x_nm"] = np.inf
    with caplog.at_level(logging.WARNING):
        out = usable_locs(t)
    assert len(out) == len(t) - 3
    assert any("3 localizations" in r.getMessage() for r in caplog.records)


def test_overlay_zooms_on_a_region(movie_and_locs, tmp_path):
    """The fourth walk-through: the tetrapod overlay was too small to tell whether each PSF
    image had one marker, and overlay had no zoom."""
    from sparseloc.io.movie import Movie
    from sparseloc.overlay import overlay_figure

    movie, locs, df = movie_and_locs
    with Movie.open(movie) as m:
        frame = m[1]
    fig = overlay_figure(frame, df, frame_index=1, pixel_size=PX, region=(0, 16, 0, 16))
    ax = fig.axes[0]
    assert ax.get_xlim() == pytest.approx((0.0, 1.6)) and ax.get_ylim() == pytest.approx((1.6, 0))
    in_frame = df[df["frame"] == 1]
    inside = ((in_frame["x_nm"] < 1600) & (in_frame["y_nm"] < 1600)).sum()
    assert ax.get_title() == f"frame 1: {inside} localizations"
    out = tmp_path / "zoom.png"
    args = ["overlay", str(movie), str(locs), "--frame", "1", "--pixel-size", "100"]
    r = runner.invoke(app, [*args, "-o", str(out), "--region", "8:24,8:24"])
    assert r.exit_code == 0, r.output
    # the line printed counts the markers drawn, as the picture's title does
    x, y = in_frame["x_nm"] / PX, in_frame["y_nm"] / PX
    drawn = int(((x >= 8) & (x < 24) & (y >= 8) & (y < 24)).sum())
    assert drawn < len(in_frame)
    assert f"(frame 1, {drawn} localizations)" in r.output
    for bad in ("8-24,8-24", "40:50,40:50"):
        r = runner.invoke(app, [*args, "-o", str(tmp_path / "bad.png"), "--region", bad])
        assert r.exit_code == 2 and "region" in r.output, r.output
    assert not (tmp_path / "bad.png").exists()


def test_overlay_names_swapped_arguments_and_frames_say_their_form(movie_and_locs, tmp_path):
    """The fifth walk-through: swapped overlay arguments said only that the TIFF is not a
    table; ``--frames 5`` said only that it must look like START:STOP."""
    movie, locs, _ = movie_and_locs
    res = runner.invoke(app, ["overlay", str(locs), str(movie), "-o", str(tmp_path / "o.png")])
    assert res.exit_code == 2 and "the movie goes first" in res.output, res.output
    assert not (tmp_path / "o.png").exists()
    from sparseloc.config import frame_range

    with pytest.raises(ValueError, match="0:5 for the first five frames, 5:6 for frame 5"):
        frame_range("5", 10)


def test_a_window_method_on_wide_windows_is_announced_as_slow():
    """The fifth walk-through: --method hybrid on a calibrated PSF's 43 px windows took 327 s
    for two frames, without a word before."""
    from sparseloc.cli import _wide_window_note
    from sparseloc.config import LocalizeParams

    assert _wide_window_note(LocalizeParams(pixel_size=100.0)) == ""
    assert _wide_window_note(LocalizeParams(pixel_size=100.0, method="hybrid", window=11)) == ""
    note = _wide_window_note(
        LocalizeParams(pixel_size=100.0, method="hybrid", window=43, margin=17)
    )
    assert "windows of 43 px" in note and "minutes per frame" in note


def test_the_scale_bar_grows_with_the_image():
    """The fifth walk-through: on the tetrapod's whole 54 um frame the bar was 1 um long."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sparseloc.plotting import _scale_bar

    said = {}
    for width in (1.3, 6.4, 54.1):
        fig, ax = plt.subplots()
        _scale_bar(ax, (0.0, width, width, 0.0), "white")
        said[width] = ax.texts[0].get_text()
        plt.close(fig)
    assert said == {1.3: "0.2 µm", 6.4: "1 µm", 54.1: "10 µm"}


def test_overlay_colours_markers_by_z_and_marks_flagged_ones():
    """Item 10: each localization's marker has the depth colour map's colour of its z (the
    same map as ``render``), a flagged one a grey cross."""
    from matplotlib import colormaps
    from matplotlib.colors import to_rgba

    from sparseloc.overlay import FLAGGED_COLOR, overlay_figure
    from sparseloc.render import DEPTH_CMAP

    locs = pd.DataFrame(
        {
            "frame": [0, 0, 0],
            "x_nm": [1000.0, 3000.0, 5000.0],
            "y_nm": [1000.0, 3000.0, 5000.0],
            "z_nm": [-400.0, 400.0, 0.0],
            "photons": [1000.0] * 3,
            "flag": ["ok", "ok", "z_edge"],
        }
    )
    fig = overlay_figure(
        np.zeros((64, 64)), locs, frame_index=0, pixel_size=PX, z_range=(-500.0, 500.0)
    )
    ok, flagged = fig.axes[0].collections[:2]
    np.testing.assert_allclose(ok.get_edgecolors(), colormaps[DEPTH_CMAP]([0.1, 0.9]))
    assert len(ok.get_offsets()) == 2 and len(flagged.get_offsets()) == 1
    shown = np.vstack([flagged.get_edgecolors(), flagged.get_facecolors()])
    assert any(np.allclose(c, to_rgba(FLAGGED_COLOR)) for c in shown)


_UNDER_A_LIMIT = """
import resource, sys
from sparseloc.cli import main

def command(args):
    sys.argv = ["sparseloc", *args]
    try:
        main()
    except SystemExit as exc:
        return exc.code

# a small render first loads every module and library the command uses, then the limit:
# what the process holds now and 300 MiB, far below the 1.2 GiB the requested image needs
given = sys.argv[1:]
at = given.index("--then")
assert command(given[:at]) in (0, None)
held = int(open("/proc/self/status").read().split("VmSize:")[1].split()[0]) * 1024
resource.setrlimit(resource.RLIMIT_AS, (held + 300 * 2**20, resource.RLIM_INFINITY))
sys.exit(command(given[at + 1:]))
"""


def run_under_a_limit(tmp_path, command: str, suffix: str, args: list[str]):
    """``sparseloc args`` in a subprocess with 300 MiB beyond what it holds after a small run
    of ``command`` (whose output has the suffix ``suffix``); returns the finished process."""
    import subprocess
    import sys

    small = tmp_path / "small.parquet"
    write_table(_table(), small)
    warm = [command, str(small), "-o", str(tmp_path / f"small{suffix}")]
    return subprocess.run(
        [sys.executable, "-c", _UNDER_A_LIMIT, *warm, "--then", *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="Linux limits")
@pytest.mark.parametrize(
    ("command", "suffix", "extra"), [("render", ".png", ["--px", "8"]), ("report", ".html", [])]
)
def test_under_a_memory_limit_a_command_says_so_in_one_sentence(tmp_path, command, suffix, extra):
    """Item 1: under a memory limit, an image too large for it ends in one sentence and exit
    code 1, not NumPy's _ArrayMemoryError traceback, and writes nothing."""
    t = _table(2000)
    t["x_nm"] *= 20.0  # a field 100 um wide: 12,500 x 12,500 px at 8 nm
    t["y_nm"] *= 20.0
    src = tmp_path / "locs.parquet"
    write_table(t, src)
    out = tmp_path / f"out{suffix}"
    r = run_under_a_limit(tmp_path, command, suffix, [command, str(src), "-o", str(out), *extra])
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert lines[-1].startswith(f"error: {command} ran out of memory"), r.stderr
    assert "did not fit" in lines[-1]
    assert not out.exists()


def test_render_says_when_the_frc_plot_it_was_asked_for_is_not_written(tmp_path):
    """A single-frame table has no FRC (the halves split frames): render --frc wrote no plot
    and said nothing of it."""
    t = _table()
    t["frame"] = 0
    src = tmp_path / "one_frame.parquet"
    write_table(t, src)
    frc_png = tmp_path / "frc.png"
    r = runner.invoke(
        app, ["render", str(src), "-o", str(tmp_path / "r.png"), "--frc", str(frc_png)]
    )
    assert r.exit_code == 0, r.output
    assert "FRC not computed" in r.output
    assert "--frc frc.png was not written" in r.output
    assert not frc_png.exists() and (tmp_path / "r.png").exists()


def test_a_calibrations_pixel_size_against_the_movies_names_the_calibration():
    """A hidden-data trial was told "--pixel-size 100 nm differs from the movie's metadata
    (65 nm)" without having given --pixel-size: the 100 nm came from the calibration file."""
    from types import SimpleNamespace

    from sparseloc.config import LOCALIZE_DEFAULTS, resolve_pixel_size

    opts = {**LOCALIZE_DEFAULTS, "psf": "beads_100nm.h5"}
    with pytest.raises(ValueError) as err:
        resolve_pixel_size(opts, SimpleNamespace(pixel_size=100.0), 65.0)
    said = str(err.value)
    assert "calibration 'beads_100nm.h5' was made at 100 nm" in said and "65 nm" in said
    assert "--pixel-size" not in said
    with pytest.raises(ValueError, match="--pixel-size 100 nm differs"):
        resolve_pixel_size({**opts, "pixel_size": 100.0}, SimpleNamespace(pixel_size=None), 65.0)
