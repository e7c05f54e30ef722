"""plot_solve: the paper-style figure of one window's solve (Figs 2-3)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from sparseloc.dictionary import Dictionary
from sparseloc.plotting import plot_solve
from sparseloc.solvers import Emitters, WindowSolution, matching_pursuit
from sparseloc.solvers.hybrid import hybrid_solve

PX, W = 160.0, 11
TRUTH = np.array(
    [[620.0, 700.0, -150.0, 1100.0], [1050.0, 820.0, 100.0, 1000.0], [840.0, 1150.0, 220.0, 1200.0]]
)


@pytest.fixture(scope="module")
def case(dh_model):
    coarse = Dictionary(dh_model, W, PX, 80.0, 120.0, (-300, 300))
    fine = Dictionary(dh_model, W, PX, 10.0, 15.0, (-300, 300))
    t = TRUTH
    mu = dh_model.render(t[:, 0], t[:, 1], t[:, 2], t[:, 3], (W, W), PX) + 5.0
    window = np.random.default_rng(7).poisson(mu).astype(float)
    return window, coarse, fine


def _check_png(path):
    from matplotlib.image import imread

    assert path.is_file()
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = imread(path)
    assert img.ndim == 3 and img.shape[2] in (3, 4)
    assert 500 < img.shape[0] < 3000 and 800 < img.shape[1] < 4000
    assert img.shape[1] > img.shape[0]  # 3 panels wide, 2 high
    assert np.ptp(img[..., :3]) > 0.5  # not blank


def test_plot_hybrid_with_truth(case, tmp_path):
    window, coarse, fine = case
    sol = hybrid_solve(window, coarse, fine)
    assert len(sol.details["box_centres"]) > 0
    out = plot_solve(window, sol, tmp_path / "solve.png", pixel_size=PX, truth=TRUTH, title="t")
    assert out == tmp_path / "solve.png"
    _check_png(out)


def test_plot_mp_without_truth(case, tmp_path):
    window, coarse, _ = case
    sol = matching_pursuit(window, coarse)
    _check_png(plot_solve(window, sol, tmp_path / "mp.png", pixel_size=PX))


def test_plot_empty_solutions(case, tmp_path):
    _, coarse, fine = case
    noise = np.random.default_rng(3).poisson(8.0, (W, W)).astype(float)
    sol = hybrid_solve(noise, coarse, fine)  # nothing found: no boxes, no box_half_width
    assert len(sol.emitters) == 0
    _check_png(plot_solve(noise, sol, tmp_path / "empty.png", pixel_size=PX, truth=TRUTH[:0]))
    # a bare solution with an offset window, no details at all, and truth without photons
    bare = WindowSolution(Emitters.empty(), 8.0, np.full((W, W), 8.0), "co")
    shifted = TRUTH[:, :3] + [5000.0, -800.0, 0.0]
    out = plot_solve(
        noise, bare, tmp_path / "bare.png", pixel_size=PX, origin=(5000.0, -800.0), truth=shifted
    )
    _check_png(out)


def test_import_does_not_load_matplotlib():
    code = "import sys, sparseloc.plotting; print('matplotlib' in sys.modules)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "False"
