"""Maximum-likelihood refinement: accuracy, uncertainties, count selection, flags."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.crlb import crlb
from sparseloc.psf import make_psf
from sparseloc.solvers import Emitters
from sparseloc.solvers.refine import LR_THRESHOLD, fit_emitters, fit_with_count_selection

PX, W = 100.0, 17


@pytest.fixture(scope="module")
def analytic():
    return make_psf("dh-analytic")


def window(model, truth, background=10.0, seed=0, plane=None):
    t = np.atleast_2d(truth)
    mu = model.render(t[:, 0], t[:, 1], t[:, 2], t[:, 3], (W, W), PX) + background
    if plane is not None:
        mu = mu + plane
    return np.random.default_rng(seed).poisson(mu).astype(float)


def test_isolated_fit_is_unbiased_and_reaches_the_crlb(analytic):
    rng = np.random.default_rng(1)
    truth = np.array([860.0, 830.0, 250.0, 3000.0])
    bound = crlb(analytic, *truth, 10.0, (W, W), PX)[0]
    errs, sds = [], []
    for seed in range(150):
        img = window(analytic, truth, seed=seed)
        start = Emitters.from_array(
            [truth + np.array([rng.normal(0, 30), rng.normal(0, 30), rng.normal(0, 50), 300.0])]
        )
        fit = fit_emitters(img, analytic, start, pixel_size=PX)
        assert fit.converged and fit.flags[0] == "ok"
        errs.append(fit.emitters.as_array()[0] - truth)
        sds.append(fit.sigma[0])
    errs, sds = np.array(errs), np.array(sds)
    rmse = np.sqrt(np.mean(errs**2, axis=0))
    # 150 samples: the RMSE is known to about +-6 %
    assert np.all(rmse[:3] / bound[:3] > 0.8) and np.all(rmse[:3] / bound[:3] < 1.25)
    assert np.all(np.abs(errs[:, :3].mean(axis=0)) < 3 * rmse[:3] / np.sqrt(len(errs)) + 0.5)
    # reported standard errors equal the bound at the fit
    assert np.allclose(np.median(sds, axis=0)[:3], bound[:3], rtol=0.05)
    within = np.mean(np.abs(errs[:, :3]) <= sds[:, :3], axis=0)
    assert np.all((within > 0.55) & (within < 0.8))


def test_pupil_model_fit(dh_model):
    truth = np.array([[820.0, 880.0, -200.0, 2000.0]])
    img = window(dh_model, truth, seed=3)
    start = Emitters.from_array(truth + np.array([[40.0, -30.0, 60.0, -300.0]]))
    fit = fit_emitters(img, dh_model, start, pixel_size=PX)
    err = fit.emitters.as_array()[0] - truth[0]
    bound = crlb(dh_model, *truth[0], 10.0, (W, W), PX)[0]
    assert np.all(np.abs(err[:3]) < 4 * bound[:3])
    assert 0.7 < fit.deviance_per_dof < 1.4


def test_count_selection_adds_a_missing_emitter(analytic):
    truth = np.array([[700.0, 800.0, -100.0, 2500.0], [1050.0, 950.0, 300.0, 2500.0]])
    img = window(analytic, truth, seed=4)
    fit = fit_with_count_selection(img, analytic, Emitters.from_array(truth[:1]), pixel_size=PX)
    est = fit.emitters.as_array()
    assert len(est) == 2
    for t in truth:
        assert np.linalg.norm(est[:, :3] - t[:3], axis=1).min() < 40.0
    assert any("added" in h for h in fit.history)


def test_count_selection_removes_a_spurious_emitter(analytic):
    truth = np.array([[850.0, 850.0, 0.0, 3000.0]])
    img = window(analytic, truth, seed=5)
    start = Emitters.from_array(np.vstack([truth, [[400.0, 1300.0, 500.0, 300.0]]]))
    fit = fit_with_count_selection(img, analytic, start, pixel_size=PX)
    assert len(fit.emitters) == 1
    assert any("removed" in h for h in fit.history)


def count_fits(monkeypatch) -> list[int]:
    """Record the emitter count of every fit_emitters call made by the count selection."""
    import sparseloc.solvers.refine as refine

    calls: list[int] = []
    real = refine.fit_emitters

    def counting(y, model, em, **kw):
        calls.append(len(em))
        return real(y, model, em, **kw)

    monkeypatch.setattr(refine, "fit_emitters", counting)
    return calls


def test_removal_is_refitted_only_below_the_wald_threshold(analytic, monkeypatch):
    """A real faint emitter whose Wald statistic (N / sigma_N)^2 lies between the threshold
    and four times it is not refitted without (REMOVE_SKIP_FACTOR 1); with the old factor 4
    it was."""
    import sparseloc.solvers.refine as refine

    truth = np.array([[850.0, 850.0, 0.0, 3000.0], [400.0, 1300.0, 300.0, 250.0]])
    img = window(analytic, truth, seed=5)
    start = Emitters.from_array(truth)
    fit = fit_emitters(img, analytic, start, pixel_size=PX)
    wald = (fit.emitters.photons / fit.sigma[:, 3]) ** 2
    assert refine.LR_THRESHOLD < wald[1] < 4 * refine.LR_THRESHOLD  # the case this tests
    calls = count_fits(monkeypatch)
    fit_with_count_selection(img, analytic, start, pixel_size=PX)
    assert 1 not in calls  # no refit with an emitter removed
    calls.clear()
    monkeypatch.setattr(refine, "REMOVE_SKIP_FACTOR", 4.0)
    fit_with_count_selection(img, analytic, start, pixel_size=PX)
    assert calls[:2] == [2, 1]  # the fit, then the refit without the faint one


def test_both_addition_candidates_are_refitted_and_the_likelier_kept(analytic, monkeypatch):
    """Two missing emitters, one change allowed: both candidates are refitted, and the one
    kept is the likelier of the two (the frame solver's and the windows' rule)."""
    import sparseloc.solvers.refine as refine

    truth = np.array(
        [[850.0, 850.0, 0.0, 3000.0], [400.0, 1300.0, 300.0, 3000.0], [1300, 400.0, -200, 2000]]
    )
    img = window(analytic, truth, seed=7)
    start = Emitters.from_array(truth[:1])
    cands, _ = refine.residual_candidates(
        img, fit_emitters(img, analytic, start, pixel_size=PX).model_image, analytic, PX, (0, 0)
    )
    assert len(cands) == 2  # both missing emitters are candidates
    trials = [
        fit_emitters(img, analytic, Emitters.from_array(np.vstack([truth[:1], c])), pixel_size=PX)
        for c in cands
    ]
    calls = count_fits(monkeypatch)
    fit = fit_with_count_selection(img, analytic, start, pixel_size=PX, max_changes=1)
    assert calls == [1, 2, 2]  # the fit, then both addition trials
    likelier = max(trials, key=lambda t: t.log_likelihood).emitters.as_array()[1]
    added = fit.emitters.as_array()[1]
    assert np.linalg.norm(added[:2] - likelier[:2]) < 5.0
    assert np.linalg.norm(truth[1:, :2] - added[:2], axis=1).min() < 60.0


def test_z_outside_the_range_is_flagged(dh_model):
    narrow = make_psf("dh", z_range=(-300.0, 300.0))
    truth = np.array([[850.0, 850.0, 700.0, 3000.0]])
    img = window(dh_model, truth, seed=6)
    fit = fit_emitters(
        img, narrow, Emitters.from_array([[850.0, 850.0, 200.0, 3000.0]]), pixel_size=PX
    )
    assert fit.flags[0] == "z_edge"
    assert fit.emitters.z[0] == pytest.approx(300.0, abs=1.0)


def test_emccd_uncertainties_are_sqrt2_larger(analytic):
    truth = np.array([[850.0, 850.0, 0.0, 3000.0]])
    img = window(analytic, truth, seed=7)
    start = Emitters.from_array(truth)
    a = fit_emitters(img, analytic, start, pixel_size=PX)
    b = fit_emitters(img, analytic, start, pixel_size=PX, noise="emccd")
    assert np.allclose(b.emitters.as_array(), a.emitters.as_array(), rtol=1e-4, atol=0.05)
    assert np.allclose(b.sigma, np.sqrt(2) * a.sigma, rtol=1e-3)


def test_scmos_and_plane_background(analytic):
    _rows, cols = np.mgrid[0:W, 0:W]
    plane = 0.4 * (cols - W / 2)  # a tilt of +-3.4 photons/pixel across the window
    truth = np.array([[850.0, 850.0, 100.0, 3000.0]])
    img = window(analytic, truth, background=12.0, seed=8, plane=plane)
    start = Emitters.from_array(truth)
    const = fit_emitters(img, analytic, start, pixel_size=PX)
    tilted = fit_emitters(img, analytic, start, pixel_size=PX, plane=True)
    assert tilted.log_likelihood > const.log_likelihood + 10
    # the tilt in the fit's units (per half window), within 3 reported standard errors
    assert abs(tilted.background[1] - 0.4 * W / 2) < 3 * tilted.background_sigma[1]
    sc = fit_emitters(
        img,
        analytic,
        start,
        pixel_size=PX,
        plane=True,
        noise="scmos",
        read_variance=np.full((W, W), 4.0),
    )
    assert np.all(sc.sigma[0, :3] > tilted.sigma[0, :3])


def test_bad_arguments(analytic):
    img = np.full((W, W), 10.0)
    start = Emitters.from_array([[850.0, 850.0, 0.0, 1000.0]])
    with pytest.raises(ValueError, match="noise must be one of"):
        fit_emitters(img, analytic, start, pixel_size=PX, noise="gaussian")
    with pytest.raises(ValueError, match="read_variance"):
        fit_emitters(img, analytic, start, pixel_size=PX, noise="scmos")
    with pytest.raises(ValueError, match="negative photon"):
        fit_emitters(img - 50, analytic, start, pixel_size=PX)


@pytest.mark.parametrize("shape", [(17, 17), (14, 23)])
def test_residual_candidates_score_equals_direct_correlation(analytic, shape):
    """The FFT correlations behind the candidate search equal sums over the window."""
    from sparseloc.solvers.refine import residual_candidates

    rows, cols = shape
    rng = np.random.default_rng(5)
    truth = np.array([[700.0, 650.0, 200.0, 2500.0], [1100.0, 900.0, -300.0, 2000.0]])
    origin, n_planes = (300.0, -200.0), 5
    # the fit missed the second emitter
    mu = analytic.render(*truth[:1].T, shape, PX, origin=origin) + 10.0
    y = rng.poisson(analytic.render(*truth.T, shape, PX, origin=origin) + 10.0).astype(float)
    cands, stat = residual_candidates(y, mu, analytic, PX, origin, n_planes=n_planes)
    zs = np.linspace(*analytic.z_range, n_planes)
    best = 0.0
    for r in range(rows):
        for c in range(cols):
            x0, y0 = origin[0] + (c + 0.5) * PX, origin[1] + (r + 0.5) * PX
            ims = analytic.images(
                np.full(n_planes, x0), np.full(n_planes, y0), zs, shape, PX, origin=origin
            )
            corr = np.sum(ims * (y - mu), axis=(1, 2))
            var = np.sum(ims**2 * mu, axis=(1, 2))
            best = max(best, float(np.max(np.where(corr > 0, corr**2 / var, 0.0))))
    assert stat == pytest.approx(best, rel=1e-4)  # single-precision FFTs
    # the best candidate is the missing emitter (within a pixel laterally)
    assert np.hypot(cands[0][0] - truth[1, 0], cands[0][1] - truth[1, 1]) < PX
    # without the score, the same candidates and no statistic
    bare, nostat = residual_candidates(y, mu, analytic, PX, origin, n_planes=n_planes, score=False)
    assert bare == cands and np.isnan(nostat)


# -- quantum efficiency --------------------------------------------------------------------------
@pytest.mark.parametrize("noise", ["poisson", "emccd", "scmos"])
def test_qe_fits_photons_as_their_photoelectrons(analytic, noise):
    """A frame in photons holds photoelectrons / qe: fitting it with ``qe`` is fitting the
    photoelectrons themselves (same positions and position errors, photons scaled by qe,
    same deviance)."""
    q, v_e = 0.6, 4.0
    truth = np.array([[800.0, 900.0, 150.0, 2500.0], [1000.0, 700.0, -300.0, 1500.0]])
    t = truth.T
    mu = analytic.render(t[0], t[1], t[2], t[3], (W, W), PX) + 10.0
    rng = np.random.default_rng(21)
    electrons = rng.poisson(q * mu).astype(float)
    if noise == "scmos":
        electrons = electrons + rng.normal(0.0, np.sqrt(v_e), electrons.shape)
    start = truth + np.array([[30.0, -20.0, 60.0, 200.0], [-25.0, 30.0, -50.0, -150.0]])
    kw = dict(pixel_size=PX, noise=noise)
    rv_e = {"read_variance": v_e} if noise == "scmos" else {}
    rv_ph = {"read_variance": v_e / q**2} if noise == "scmos" else {}
    scale = np.array([1.0, 1.0, 1.0, q])
    ref = fit_emitters(electrons, analytic, Emitters.from_array(start * scale), **kw, **rv_e)
    got = fit_emitters(electrons / q, analytic, Emitters.from_array(start), **kw, **rv_ph, qe=q)
    assert ref.converged and got.converged
    np.testing.assert_allclose(got.emitters.as_array() * scale, ref.emitters.as_array(), atol=1e-4)
    np.testing.assert_allclose(got.sigma * scale, ref.sigma, rtol=1e-5)
    assert got.deviance_per_dof == pytest.approx(ref.deviance_per_dof, rel=1e-6)
    plain = fit_emitters(electrons / q, analytic, Emitters.from_array(start), **kw, **rv_ph)
    # the photon-counting model claims more precision than the photoelectrons carry
    assert np.all(plain.sigma[:, :3] < got.sigma[:, :3])


def test_qe_makes_the_uncertainties_honest(analytic):
    """Isolated emitters recorded with qe = 0.5: the errors match the standard errors
    reported with ``qe`` and exceed those of the photon-counting model by about sqrt(2)."""
    q = 0.5
    truth = np.array([860.0, 830.0, 250.0, 3000.0])
    mu = analytic.render(*truth[:, None], (W, W), PX) + 10.0
    rng = np.random.default_rng(22)
    errs, sd_q, sd_1 = [], [], []
    for _ in range(120):
        img = rng.poisson(q * mu) / q
        start = Emitters.from_array(
            [truth + np.array([rng.normal(0, 20), rng.normal(0, 20), 40.0, 0])]
        )
        fit = fit_emitters(img, analytic, start, pixel_size=PX, qe=q)
        naive = fit_emitters(img, analytic, start, pixel_size=PX)
        errs.append(fit.emitters.as_array()[0, :3] - truth[:3])
        sd_q.append(fit.sigma[0, :3])
        sd_1.append(naive.sigma[0, :3])
    rmse = np.sqrt(np.mean(np.square(errs), axis=0))
    ratio = rmse / np.median(sd_q, axis=0)
    # 120 samples: the RMSE is known to about +-7 %
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    assert np.all(rmse / np.median(sd_1, axis=0) > 1.2)


def test_qe_is_checked(analytic):
    img = window(analytic, [850.0, 850.0, 0.0, 2000.0])
    start = Emitters.from_array([[850.0, 850.0, 0.0, 2000.0]])
    for bad in (0.0, 1.5, float("nan"), "high"):
        with pytest.raises(ValueError, match="qe"):
            fit_emitters(img, analytic, start, pixel_size=PX, qe=bad)


def _merged_start(truth: np.ndarray) -> Emitters:
    """The closest pair of ``truth`` merged at its photon-weighted centre, plus the rest: the
    start of a fit in which two overlapping emitters were found as one."""
    d = np.linalg.norm(truth[:, None, :3] - truth[None, :, :3], axis=2) + 1e9 * np.eye(len(truth))
    i, j = np.unravel_index(np.argmin(d), d.shape)
    merged = truth[[i, j]].T @ truth[[i, j], 3] / truth[[i, j], 3].sum()
    merged[3] = truth[[i, j], 3].sum()
    return Emitters.from_array(np.vstack([merged, np.delete(truth, [i, j], axis=0)]))


def _max_error(est: np.ndarray, truth: np.ndarray) -> float:
    d = np.linalg.norm(est[:, None, :3] - truth[None, :, :3], axis=2)
    return float(d.min(axis=0).max())


@pytest.mark.parametrize(
    "truth, seed, found_by_count_selection",
    [
        # two emitters 128 nm apart laterally fitted as one: the count selection adds nothing
        ([[682, 713, 143, 2072], [654, 588, 254, 2007], [829, 679, -136, 1575]], 55, 2),
        # it adds a spurious fourth emitter instead of splitting the pair
        ([[1074, 947, 42, 2428], [629, 1057, -213, 2052], [1117, 1092, -185, 1681]], 6, 4),
    ],
)
def test_split_merge_search_leaves_the_count_selections_optimum(
    analytic, truth, seed, found_by_count_selection
):
    from sparseloc.solvers.refine import split_merge_search

    truth = np.array(truth, dtype=float)
    img = window(analytic, truth, seed=seed)
    cs = fit_with_count_selection(img, analytic, _merged_start(truth), pixel_size=PX)
    # the case this test is about: the count selection alone ends on a wrong count
    assert len(cs.emitters) == found_by_count_selection
    fit = split_merge_search(img, analytic, cs, pixel_size=PX, search_model=analytic)
    assert len(fit.emitters) == 3
    assert _max_error(fit.emitters.as_array(), truth) < 60.0
    assert fit.log_likelihood > cs.log_likelihood - LR_THRESHOLD / 2
    assert any("one" in h for h in fit.history[len(cs.history) :])
    assert np.all(fit.flags == "ok") and np.all(np.isfinite(fit.sigma))


def test_split_merge_search_keeps_right_fits_and_adds_no_emitter(analytic):
    from sparseloc.solvers.refine import split_merge_search

    rng = np.random.default_rng(5)
    for seed in range(12):
        shift = [rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-500, 500), 0.0]
        truth = np.array([[850.0, 850.0, 0.0, 2000.0]]) + np.array(shift)
        img = window(analytic, truth, seed=100 + seed)
        cs = fit_with_count_selection(img, analytic, Emitters.from_array(truth), pixel_size=PX)
        fit = split_merge_search(img, analytic, cs, pixel_size=PX, search_model=analytic)
        assert len(fit.emitters) == 1, fit.history
        assert fit is cs  # no move taken: the same fit comes back
    empty = fit_emitters(
        window(analytic, np.zeros((0, 4))), analytic, Emitters.empty(), pixel_size=PX
    )
    assert split_merge_search(np.zeros((W, W)) + 10, analytic, empty, pixel_size=PX) is empty


def test_search_model_is_a_cached_table_of_a_slow_model(analytic):
    from sparseloc.psf.spline import SplinePSF
    from sparseloc.solvers.refine import search_model_for

    table = SplinePSF.from_model(analytic, PX, roi=15, z_step=40.0)
    assert search_model_for(table, PX, (11, 11)) is table
    a = search_model_for(analytic, PX, (5, 5))
    assert isinstance(a, SplinePSF) and a.z_range == analytic.z_range
    assert search_model_for(analytic, PX, (5, 5)) is a
    assert search_model_for(analytic, PX, (6, 6)) is not a


def test_split_merge_search_result_is_checked_on_the_model_itself(analytic, caplog, monkeypatch):
    """Moves found on the search model are refitted with the model and kept only if they pass
    there."""
    import logging

    from sparseloc.psf.spline import SplinePSF
    from sparseloc.solvers import refine

    truth = np.array([[682, 713, 143, 2072], [654, 588, 254, 2007], [829, 679, -136, 1575]], float)
    img = window(analytic, truth, seed=55)
    cs = fit_with_count_selection(img, analytic, _merged_start(truth), pixel_size=PX)
    assert len(cs.emitters) == 2
    # a faithful table of the model: the split survives the check on the model
    table = SplinePSF.from_model(analytic, PX, roi=2 * W + 3, z_step=10.0)
    out = refine.split_merge_search(img, analytic, cs, pixel_size=PX, search_model=table)
    assert len(out.emitters) == 3 and _max_error(out.emitters.as_array(), truth) < 60.0
    direct = fit_emitters(
        img, analytic, out.emitters, pixel_size=PX, background=float(out.background[0])
    )
    assert out.log_likelihood == pytest.approx(direct.log_likelihood, abs=0.05)

    # a search whose last count selection comes back with one emitter only: on the model that
    # is far less likely than the two-emitter fit it started from, so that fit comes back
    real = refine.fit_with_count_selection

    def padded(y, model, emitters, **kw):
        arr = real(y, model, emitters, **kw).emitters.as_array()
        kw = {
            k: v for k, v in kw.items() if k not in ("lr_threshold", "min_photons", "max_emitters")
        }
        brightest = arr[[np.argmax(arr[:, 3])]]
        return refine.fit_emitters(y, model, Emitters.from_array(brightest), **kw)

    monkeypatch.setattr(refine, "fit_with_count_selection", padded)
    with caplog.at_level(logging.DEBUG, logger="sparseloc.solvers.refine"):
        out = refine.split_merge_search(img, analytic, cs, pixel_size=PX, search_model=table)
    assert out is cs
    assert "not kept" in caplog.text


def _relative_misfit(true_model, used_model, row) -> float:
    """The relative rms misfit of ``used_model``'s best least-squares image of an emitter
    drawn by ``true_model`` (noise free): the model error a calibration would measure."""
    img = true_model.render(row[:1], row[1:2], row[2:3], row[3:4], (W, W), PX)
    fit = fit_emitters(img + 10.0, used_model, Emitters.from_array(row[None]), pixel_size=PX)
    signal = fit.model_image - fit.background[0]
    return float(np.linalg.norm(img + 10.0 - fit.model_image) / np.linalg.norm(signal))


def test_model_error_stops_additions_that_explain_only_the_model_misfit():
    # Bright emitters drawn with wider lobes than the model: with an exact-model threshold the
    # misfit reads as a second emitter; with the measured model error it does not, while a
    # real second emitter is still added.
    true_model = make_psf("dh-analytic", lobe_sigma=175.0)
    row = np.array([850.0, 850.0, 0.0, 20000.0])
    exact = make_psf("dh-analytic")
    known = make_psf("dh-analytic")
    known.model_error = _relative_misfit(true_model, exact, row)
    assert 0.05 < known.model_error < 0.5
    n_exact, n_known = [], []
    for seed in range(4):
        img = window(true_model, row, seed=seed)
        for model, out in ((exact, n_exact), (known, n_known)):
            fit = fit_with_count_selection(
                img, model, Emitters.from_array(row[None]), pixel_size=PX
            )
            out.append(len(fit.emitters))
    assert max(n_exact) > 1  # the misfit is read as more emitters
    assert n_known == [1, 1, 1, 1]
    second = np.vstack([row, [1250.0, 1000.0, 200.0, 5000.0]])
    img = window(true_model, second, seed=9)
    fit = fit_with_count_selection(img, known, Emitters.from_array(row[None]), pixel_size=PX)
    assert len(fit.emitters) == 2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_count_selection_removes_a_duplicate_before_testing_a_dim_emitter(analytic, seed):
    """Two emitters on one image share its light: each one's photons are poorly determined,
    so the removal test takes one of them first (the least determined by its Wald
    statistic), not the dim emitter elsewhere, which would stay and end the removals."""
    truth = np.array([[500.0, 600.0, -200.0, 6000.0], [1150.0, 1150.0, 300.0, 1500.0]])
    img = window(analytic, truth, seed=seed)
    twins = [[510.0, 600.0, -200.0, 3000.0], [490.0, 610.0, -180.0, 3000.0]]
    start = Emitters.from_array(np.vstack([twins, truth[1:]]))
    fit = fit_with_count_selection(img, analytic, start, pixel_size=PX, lr_threshold=80.0)
    arr = fit.emitters.as_array()
    assert len(arr) == 2
    d = np.hypot(arr[:, None, 0] - truth[None, :, 0], arr[:, None, 1] - truth[None, :, 1])
    assert np.all(d.min(axis=0) < 50.0)


def test_the_allowance_sums_the_error_table_where_the_model_has_one(analytic):
    """With an error table the model error's variance is the table rendered for the fit's
    emitters (photons squared), not ``(e * signal)^2``: the allowance is its sum over the
    camera's variance, whatever ``e`` says."""
    from sparseloc.psf.spline import SplinePSF
    from sparseloc.solvers.refine import error_allowance_at

    table_model = SplinePSF.from_model(analytic, PX, roi=W, z_step=20.0, oversample=1)
    truth = np.array([[850.0, 850.0, 0.0, 5000.0]])
    kw = dict(pixel_size=PX, origin=(0.0, 0.0))
    fit = fit_emitters(window(analytic, truth), analytic, Emitters.from_array(truth), **kw)
    model = make_psf("dh-analytic")
    model.model_error = 0.1
    by_e = error_allowance_at(fit, model, kw)
    signal = fit.model_image - fit.background[0]
    assert by_e == pytest.approx(np.sum((0.1 * signal) ** 2 / fit.model_image))
    c = 1e-3  # error variance per photon squared, as a share of the unit image
    model.error_table = SplinePSF(c * table_model.stack, PX, table_model.z, normalise=False,
                                  centre=table_model.centre)  # fmt: skip
    em = fit.emitters.as_array()
    var = c * analytic.render(em[:, 0], em[:, 1], em[:, 2], em[:, 3] ** 2, (W, W), PX)
    by_table = error_allowance_at(fit, model, kw)
    assert by_table == pytest.approx(np.sum(var / fit.model_image), rel=0.05)
    assert not by_table == pytest.approx(by_e, rel=0.5)  # not the rule of e
