"""Engine conformance: the numba engine (spline kernel, the compiled Levenberg-Marquardt loop,
the pursuit's selection) against the NumPy reference on the same requests, the engine setting,
and the frame solver's skipping of groups that a sweep left in place."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.engine import resolve_engine, use_engine
from sparseloc.psf import make_psf
from sparseloc.psf.spline import SplinePSF
from sparseloc.solvers.emitters import Emitters
from sparseloc.solvers.frame import frame_fit, frame_templates
from sparseloc.solvers.refine import fit_emitters

PX = 100.0

pytestmark = pytest.mark.skipif(
    resolve_engine("auto") != "numba", reason="the numba engine does not run here"
)


@pytest.fixture(scope="module")
def table():
    # Oversampled table of the cheap analytic double helix: stride 2 in the kernel.
    return SplinePSF.from_model(make_psf("dh-analytic"), PX, roi=31, z_step=20.0)


def _both(model, fn):
    """fn() on the numba engine, then on the NumPy engine (``model``: unused, kept for the
    callers' readability)."""
    with use_engine("numba"):
        a = fn()
    with use_engine("numpy"):
        b = fn()
    return a, b


@pytest.fixture(scope="module")
def bead_table():
    # A stack at the camera's pixels (oversample 1), as a bead calibration gives.
    m = make_psf("dh-analytic")
    z = np.arange(-600.0, 601.0, 40.0)
    imgs = m.images(np.full(z.size, 1350.0), np.full(z.size, 1350.0), z, (27, 27), PX)
    return SplinePSF(imgs, PX, z)


def test_kernel_matches_the_numpy_path_without_oversampling(bead_table):
    rng = np.random.default_rng(4)
    x, y = rng.uniform(600, 1500, (2, 5))
    z = rng.uniform(-550, 550, 5)
    (img_c, der_c), (img_n, der_n) = _both(
        bead_table, lambda: bead_table._images(x, y, z, (19, 17), PX, (100.0, 50.0), True)
    )
    np.testing.assert_allclose(img_c, img_n, rtol=0, atol=1e-12 * np.abs(img_n).max())
    np.testing.assert_allclose(der_c, der_n, rtol=0, atol=1e-12 * np.abs(der_n).max())


@pytest.mark.parametrize(
    ("shape", "origin"),
    [((21, 21), (0.0, 0.0)), ((15, 23), (350.0, -420.0)), ((9, 9), (-3000.0, 0.0))],
)
def test_kernel_matches_the_numpy_path(table, shape, origin):
    rng = np.random.default_rng(3)
    x = rng.uniform(500, 1600, 6)
    y = rng.uniform(500, 1600, 6)
    z = rng.uniform(*table.z_range, 6)
    (img_c, der_c), (img_n, der_n) = _both(
        table, lambda: table._images(x, y, z, shape, PX, origin, True)
    )
    scale = max(np.abs(img_n).max(), 1e-12)
    assert np.abs(img_c - img_n).max() <= 1e-12 * scale
    for i in range(3):
        s = max(np.abs(der_n[:, i]).max(), 1e-12)
        assert np.abs(der_c[:, i] - der_n[:, i]).max() <= 1e-12 * s
    # the far case is all zeros in both
    if origin[0] < -2000:
        assert np.all(img_c == 0.0)


@pytest.mark.parametrize("shape", [(1, 13), (11, 1), (1, 1), (7, 12)])
@pytest.mark.parametrize("derivatives", [True, False])
def test_kernel_matches_the_numpy_path_at_stride_3_and_thin_windows(shape, derivatives):
    """Oversample 3, windows of one row or column, with and without derivatives, and
    emitters whose footprint leaves the table on either side."""
    m = SplinePSF.from_model(make_psf("dh-analytic"), PX, roi=15, z_step=40.0, oversample=3)
    x = np.array([300.0, -500.0, 1800.0, 600.0])
    y = np.array([200.0, 700.0, -900.0, 50.0])
    z = np.array([0.0, -300.0, 250.0, 400.0])
    a, b = _both(m, lambda: m._images(x, y, z, shape, PX, (0.0, 0.0), derivatives))
    if derivatives:
        (img_c, der_c), (img_n, der_n) = a, b
        np.testing.assert_allclose(der_c, der_n, rtol=0, atol=1e-12 * np.abs(der_n).max())
    else:
        img_c, img_n = a, b
    np.testing.assert_allclose(img_c, img_n, rtol=0, atol=1e-12 * max(np.abs(img_n).max(), 1e-12))
    assert np.abs(img_n).max() > 0  # some light reaches the window


@pytest.mark.parametrize("noise", ["poisson", "emccd", "scmos"])
def test_compiled_fit_takes_the_same_steps(table, noise):
    rng = np.random.default_rng(11)
    for trial in range(6):
        k = 1 + trial % 3
        truth = np.c_[
            rng.uniform(700, 1400, k),
            rng.uniform(700, 1400, k),
            rng.uniform(-500, 500, k),
            rng.uniform(1000, 4000, k),
        ]
        off = table.render([300.0], [1800.0], [100.0], [2000.0], (21, 21), PX)
        mu = table.render(*truth.T, (21, 21), PX) + 10.0 + off
        img = rng.poisson(mu).astype(float)
        start = truth + rng.normal(0, [30, 30, 60, 300], truth.shape)
        start[:, 2] = np.clip(start[:, 2], *table.z_range)
        kw = dict(pixel_size=PX, offset=off, noise=noise, plane=trial % 2 == 1)
        if noise == "scmos":
            kw["read_variance"] = np.full((21, 21), 3.0)
        a, b = _both(
            table,
            lambda kw=kw, img=img, start=start: fit_emitters(
                img, table, Emitters.from_array(start), **kw
            ),
        )
        assert a.n_iter == b.n_iter and a.converged == b.converged
        np.testing.assert_allclose(a.emitters.as_array(), b.emitters.as_array(), atol=1e-6)
        np.testing.assert_allclose(a.log_likelihood, b.log_likelihood, rtol=1e-10)
        np.testing.assert_allclose(a.sigma, b.sigma, rtol=1e-6)
        np.testing.assert_allclose(a.background, b.background, rtol=1e-8, atol=1e-8)
        assert list(a.flags) == list(b.flags)


@pytest.mark.parametrize("max_iter", [0, 1, 2])
def test_compiled_fit_uncertainties_at_an_early_stop(table, max_iter):
    """The standard errors come from the Fisher matrix at the returned parameters, also when
    the loop stops after few (or no) iterations."""
    truth = np.array([[1000.0, 1100.0, 150.0, 3000.0], [1400.0, 900.0, -250.0, 2000.0]])
    img = np.random.default_rng(8).poisson(table.render(*truth.T, (21, 21), PX) + 10.0)
    shift = np.array([[60.0, -40.0, 100.0, 500.0], [-50.0, 30.0, -80.0, 0.0]])
    start = Emitters.from_array(truth + shift)
    a, b = _both(
        table,
        lambda: fit_emitters(img.astype(float), table, start, pixel_size=PX, max_iter=max_iter),
    )
    assert a.n_iter == b.n_iter == max_iter
    np.testing.assert_allclose(a.emitters.as_array(), b.emitters.as_array(), atol=1e-6)
    np.testing.assert_allclose(a.sigma, b.sigma, rtol=1e-8)


def test_analytic_models_fit_on_numpy_under_the_numba_engine(monkeypatch):
    # The numba engine covers spline tables; other models fit through NumPy, whatever the
    # setting, and a spline table reaches the compiled loop.
    import sparseloc.solvers._fit_numba as fn

    calls = []
    real = fn.lm_fit
    monkeypatch.setattr(fn, "lm_fit", lambda *a: calls.append(1) or real(*a))
    m = make_psf("dh-analytic")
    mu = m.render([1000.0], [1000.0], [0.0], [3000.0], (21, 21), PX) + 10.0
    img = np.random.default_rng(0).poisson(mu).astype(float)
    start = Emitters.from_array([[1020.0, 980.0, 50.0, 2500.0]])
    with use_engine("numba"):
        fit = fit_emitters(img, m, start, pixel_size=PX)
        assert np.hypot(fit.emitters.x[0] - 1000.0, fit.emitters.y[0] - 1000.0) < 30.0
        assert calls == []
        table = SplinePSF.from_model(m, PX, roi=31, z_step=20.0)
        fit_emitters(img, table, start, pixel_size=PX)
        assert calls == [1]
    with use_engine("numpy"):
        fit_emitters(img, table, start, pixel_size=PX)
        assert calls == [1]


def test_the_engine_setting(monkeypatch):
    from sparseloc import engine

    with pytest.raises(ValueError, match="engine must be one of auto, numpy, numba"):
        engine.check_engine("cuda")
    with use_engine("numpy") as chosen:
        assert chosen == "numpy" and engine.kernels() is None
        with use_engine("numba") as inner:
            assert inner == "numba" and engine.kernels() is not None
        assert engine.active_engine() == "numpy"
    monkeypatch.setenv("SPARSELOC_ENGINE", "numpy")
    assert resolve_engine("auto") == "numpy" and resolve_engine("numba") == "numba"
    monkeypatch.setenv("SPARSELOC_ENGINE", "gpu")
    with pytest.raises(ValueError, match="SPARSELOC_ENGINE"):
        resolve_engine("auto")


def test_skipping_settled_groups_changes_little(table):
    rng = np.random.default_rng(5)
    n = 14
    truth = np.c_[
        rng.uniform(300, 3900, n),
        rng.uniform(300, 3900, n),
        rng.uniform(-500, 500, n),
        rng.uniform(1500, 4000, n),
    ]
    shape = (42, 42)
    frame = rng.poisson(table.render(*truth.T, shape, PX) + 10.0).astype(float)
    start = truth + rng.normal(0, [40, 40, 80, 300], truth.shape)
    start[:, 2] = np.clip(start[:, 2], *table.z_range)
    t = frame_templates(table, PX, dxy=50.0, dz=120.0)
    kw = dict(
        pixel_size=PX,
        background=10.0,
        group_distance=t.core_radius * PX,
        pad=int(np.ceil(0.6 * t.core_radius)),
        reach=0.5 * t.images.shape[-1] * PX,
    )
    calls = {"n": 0}
    import sparseloc.solvers.frame as frame_mod

    real = frame_mod.fit_with_count_selection

    def counting(*a, **k):
        calls["n"] += 1
        return real(*a, **k)

    frame_mod.fit_with_count_selection = counting
    try:
        full = frame_fit(frame, table, Emitters.from_array(start), skip_tolerance=0.0, **kw)
        n_full = calls["n"]
        calls["n"] = 0
        fast = frame_fit(frame, table, Emitters.from_array(start), **kw)
        n_fast = calls["n"]
    finally:
        frame_mod.fit_with_count_selection = real
    assert n_fast < n_full  # groups were skipped
    a = full.emitters.as_array()
    b = fast.emitters.as_array()
    assert len(a) == len(b)
    # same emitters to well within the localization precision
    d = np.hypot(*(a[:, None, :2] - b[None, :, :2]).transpose(2, 0, 1)).min(axis=1)
    assert np.all(d < 5.0)


@pytest.mark.parametrize("bad", [(2, np.nan), (0, np.nan), (3, np.nan)])
def test_a_non_finite_start_is_refused_as_in_numpy(table, bad):
    # The compiled loop has no bounds checks: a NaN must never reach it.
    col, value = bad
    img = np.full((15, 15), 10.0)
    start = np.array([[700.0, 700.0, 0.0, 2000.0]])
    start[0, col] = value
    with pytest.raises(ValueError, match="finite"):
        fit_emitters(img, table, Emitters.from_array(start), pixel_size=PX, background=10.0)


@pytest.mark.parametrize("npar", [1, 2, 5, 9, 13, 15, 33, 35])
def test_compiled_scoring_matches_numpy(npar):
    # The Fisher matrix is summed in 2 x 4 blocks with clamped edges: every parameter count
    # (4 K + 1 or 4 K + 3, and odd sizes) must give J diag(keep/mu) J' and J' keep (1 - y/mu)
    # exactly as the plain products do (keep: 0 for a censored pixel).
    from sparseloc.solvers._fit_numba import _scoring

    rng = np.random.default_rng(npar)
    rows, cols = 7, 9
    jac = rng.normal(size=(npar, rows * cols))
    mu = rng.uniform(5.0, 50.0, size=(rows, cols))
    v = rng.uniform(0.0, 2.0, size=(rows, cols))
    y = rng.poisson(mu).astype(float) + v
    keep = (rng.uniform(size=(rows, cols)) > 0.2).astype(float)
    grad, fisher = np.empty(npar), np.empty((npar, npar))
    _scoring(
        mu,
        v,
        y,
        keep,
        0.5,
        jac,
        np.empty(rows * cols),
        np.empty(rows * cols),
        np.empty((npar, rows * cols)),
        grad,
        fisher,
    )
    muv = (mu + v).ravel()
    k = keep.ravel()
    np.testing.assert_allclose(fisher, 0.5 * (jac * k / muv) @ jac.T, rtol=1e-12, atol=1e-12)
    grad_ref = 0.5 * jac @ (k * (1.0 - y.ravel() / muv))
    np.testing.assert_allclose(grad, grad_ref, rtol=1e-12, atol=1e-12)


def test_template_selection_is_bit_identical_on_both_engines():
    from dataclasses import replace

    from sparseloc.solvers.frame_mp import Correlator

    rng = np.random.default_rng(3)
    imgs = rng.random((7, 9, 9))
    imgs[4] = imgs[1]  # a duplicate template: equal scores, the first must win in both
    z = np.zeros(7)
    base = frame_templates(make_psf("dh-analytic"), PX, dxy=PX, dz=2000.0, size=9)
    tmpl = replace(base, images=imgs, dx=z, dy=z, z=z)
    frame = rng.random((30, 26)) - 0.2
    cor = Correlator(tmpl, frame.shape, batch=3)  # batches of 3, 3 and 1 templates
    fast, ref = _both(None, lambda: cor.best(frame))
    for a, b in zip(fast, ref, strict=True):
        assert a.dtype == b.dtype
        assert np.array_equal(a, b)
    assert not np.any(fast[1] == 4)  # the duplicate never wins over its first copy
    assert np.any(fast[1] == 1)


@pytest.mark.parametrize(
    "centres", [np.arange(0, 30), np.array([0, 1, 5, 6, 25, 29]), np.array([3])]
)
def test_sliding_percentile_matches_a_percentile_per_window(centres):
    """The temporal background of each frame, numba's sliding window against NumPy's
    percentile of each window (edges, gaps that restart the window, ties in integer counts)."""
    from sparseloc.detect import temporal_background, temporal_backgrounds

    chunk = np.random.default_rng(4).poisson(6.0, (30, 9, 11)).astype(float)
    numba_bg, numpy_bg = _both(None, lambda: temporal_backgrounds(chunk, centres, 5))
    assert np.array_equal(numba_bg, numpy_bg)
    for k, c in enumerate(centres):
        assert np.array_equal(numpy_bg[k], temporal_background(chunk[max(c - 5, 0) : c + 6]))


def test_the_compiled_fit_loop_is_loaded_from_numbas_cache_in_a_new_process(tmp_path):
    """The loop was a closure over the engine's operations; numba keys a closure's cache by its
    pickled cells, which differ in every process, so each process compiled it again (2.4 s,
    also in every pool worker) and added one more entry (490 kB) to the cache."""
    import os
    import subprocess
    import sys

    script = (
        "from sparseloc.solvers import _fit_numba as F\n"
        "F.warm_up()\n"
        "s = F._levenberg_marquardt.stats\n"
        "print(sum(s.cache_hits.values()), sum(s.cache_misses.values()))\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    runs = [
        subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
        for _ in range(2)
    ]
    for run in runs:
        assert run.returncode == 0, run.stderr
    hits, misses = (int(v) for v in runs[1].stdout.split())
    assert hits == 1 and misses == 0, runs[1].stdout


@pytest.mark.parametrize("noise", ["poisson", "scmos"])
def test_censored_pixels_leave_the_fit_on_both_engines(table, noise):
    # A bright emitter clipped at its peak, the clipped pixels censored: both engines take
    # the same steps, the values at those pixels do not matter, and the fit lands near the
    # unclipped window's where the clipped window's fit, taken at face value, does not.
    rng = np.random.default_rng(5)
    truth = np.array([[1050.0, 1000.0, 250.0, 60000.0]])
    img = rng.poisson(table.render(*truth.T, (21, 21), PX) + 10.0).astype(float)
    clip = np.sort(img.ravel())[-30]  # the 30 brightest pixels clipped
    censored = img >= clip
    clipped = np.minimum(img, clip)
    kw = dict(pixel_size=PX, noise=noise)
    if noise == "scmos":
        kw["read_variance"] = np.full((21, 21), 3.0)
    start = Emitters.from_array(truth + np.array([40.0, -30.0, 80.0, -5000.0]))

    def fit(y, cens=censored):
        return fit_emitters(y, table, start, censored=cens, **kw)

    a, b = _both(table, lambda: fit(clipped))
    assert a.n_iter == b.n_iter and a.converged == b.converged
    np.testing.assert_allclose(a.emitters.as_array(), b.emitters.as_array(), atol=1e-6)
    np.testing.assert_allclose(a.log_likelihood, b.log_likelihood, rtol=1e-10)
    np.testing.assert_allclose(a.sigma, b.sigma, rtol=1e-6)
    assert np.isfinite(a.deviance_per_dof) and 0.5 < a.deviance_per_dof < 1.5
    other = fit(np.where(censored, 1e6, clipped))  # the same optimum, to the fit's tolerance
    np.testing.assert_allclose(
        other.emitters.as_array(), a.emitters.as_array(), rtol=1e-5, atol=0.01
    )
    whole, flat = fit(img, None), fit(clipped, None)
    # measured: within 0.84 / 0.18 / 0.38 nm and 180 photons of the unclipped fit (sigma
    # 0.8 / 0.8 / 1.1 nm, 424 photons); at face value 16,650 photons short, deviance 12.4
    err = np.abs(a.emitters.as_array()[0] - whole.emitters.as_array()[0])
    assert np.all(err < 3 * a.sigma[0])
    short = whole.emitters.photons[0] - flat.emitters.photons[0]
    assert short > 10 * a.sigma[0, 3] and flat.deviance_per_dof > 3.0
