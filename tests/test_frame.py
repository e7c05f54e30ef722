"""Whole-frame solver: templates, FFT correlation, pursuit, grouped fits with offsets, pipeline."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from sparseloc.psf import make_psf
from sparseloc.psf.spline import SplinePSF
from sparseloc.solvers import Emitters
from sparseloc.solvers.frame import frame_fit, frame_pursuit, frame_templates
from sparseloc.solvers.frame_mp import Correlator
from sparseloc.solvers.refine import fit_emitters

PX = 100.0


@pytest.fixture(scope="module")
def analytic():
    return make_psf("dh-analytic")


@pytest.fixture(scope="module")
def dh_table():
    """The pupil double helix tabulated as the pipeline does for ``method="frame"``."""
    return SplinePSF.from_model(make_psf("dh"), PX, roi=45, z_step=10.0)


def poisson_frame(model, truth, shape, background=10.0, seed=0):
    t = np.atleast_2d(truth)
    mu = model.render(t[:, 0], t[:, 1], t[:, 2], t[:, 3], shape, PX) + background
    return np.random.default_rng(seed).poisson(mu).astype(float)


def frame_fit_kwargs(templates):
    """Groups within the radius of half the light, pads of 0.6 of it, reach of a template."""
    r50 = templates.core_radius
    return dict(
        pixel_size=PX,
        background=10.0,
        group_distance=r50 * PX,
        pad=int(np.ceil(0.6 * r50)),
        reach=0.5 * templates.images.shape[-1] * PX,
    )


# --- templates ---------------------------------------------------------------------------


@pytest.mark.parametrize(("dxy", "phases"), [(50.0, 2), (20.0, 5), (100.0, 1)])
def test_template_grid(analytic, dxy, phases):
    t = frame_templates(analytic, PX, dxy=dxy, dz=120.0)
    n_z = int(np.ceil(2000.0 / 120.0)) + 1
    j, side, side2 = t.images.shape
    assert j == phases**2 * n_z and side == side2 and side % 2 == 1
    assert t.dx.shape == t.dy.shape == t.z.shape == (j,)
    for off in (t.dx, t.dy):
        u = np.unique(off)
        assert len(u) == phases
        assert np.allclose(u, -u[::-1])  # symmetric about the pixel centre
        assert np.all(np.abs(u) < PX / 2)
        assert np.allclose(np.diff(u), dxy)
    # every (dx, dy, z) combination once
    assert len({(a, b, c) for a, b, c in zip(t.dx, t.dy, t.z, strict=True)}) == j
    assert t.z.min() == pytest.approx(-1000.0) and t.z.max() == pytest.approx(1000.0)
    assert np.all(np.diff(np.unique(t.z)) <= 120.0 + 1e-9)
    assert t.pixel_size == PX and t.core_radius > 0


def test_template_z_range_and_size(analytic):
    t = frame_templates(analytic, PX, dxy=50.0, dz=100.0, z_range=(-300.0, 300.0), size=9)
    assert t.images.shape == (4 * 7, 9, 9)
    assert np.allclose(np.unique(t.z), np.arange(-300.0, 301.0, 100.0))


def test_templates_are_centred_on_their_offsets():
    # A symmetric spot: each template's centroid is its emitter position, x along columns
    model = make_psf("astig-gauss")
    t = frame_templates(model, PX, dxy=25.0, dz=300.0, size=21)
    cols, rows = np.meshgrid((np.arange(21) + 0.5) * PX, (np.arange(21) + 0.5) * PX)
    centre = 10.5 * PX
    for img, dx, dy in zip(t.images, t.dx, t.dy, strict=True):
        s = img.sum()
        assert (img * cols).sum() / s == pytest.approx(centre + dx, abs=0.5)
        assert (img * rows).sum() / s == pytest.approx(centre + dy, abs=0.5)


def test_template_arguments_are_checked(analytic):
    for dxy in (30.0, 150.0, 300.0):
        with pytest.raises(ValueError, match="divide the pixel"):
            frame_templates(analytic, PX, dxy=dxy, dz=100.0)
    for dz in (0.0, -10.0):
        with pytest.raises(ValueError, match="axial step"):
            frame_templates(analytic, PX, dxy=50.0, dz=dz)
    with pytest.raises(ValueError, match="odd"):
        frame_templates(analytic, PX, dxy=50.0, dz=100.0, size=8)


# --- FFT correlation ---------------------------------------------------------------------


def dense_correlation(frame, t):
    """sum_{u,v} frame[r + u - h, c + v - h] * t[u, v], zero outside the frame, by loops."""
    rows, cols = frame.shape
    h = t.shape[0] // 2
    out = np.zeros((rows, cols))
    for r in range(rows):
        for c in range(cols):
            s = 0.0
            for u in range(t.shape[0]):
                for v in range(t.shape[1]):
                    rr, cc = r + u - h, c + v - h
                    if 0 <= rr < rows and 0 <= cc < cols:
                        s += frame[rr, cc] * t[u, v]
            out[r, c] = s
    return out


@pytest.mark.parametrize("side", [5, 9, 27])  # 27: wider than the 20 x 24 frame
def test_correlator_matches_a_dense_reference(analytic, side):
    rng = np.random.default_rng(7)
    # random, asymmetric templates: a flip or a transposition cannot go unseen
    imgs = rng.random((3, side, side))
    z = np.zeros(3)
    base = frame_templates(analytic, PX, dxy=PX, dz=2000.0, size=side)
    tmpl = replace(base, images=imgs, dx=z, dy=z, z=z)
    frame = rng.random((20, 24)) - 0.3
    cor = Correlator(tmpl, frame.shape)
    got = cor.correlate(frame)
    got2 = cor.correlate(frame, squared=True)
    assert got.shape == got2.shape == cor.norm2.shape == (3, 20, 24)
    for j, t in enumerate(imgs):
        for res, ref in (
            (got[j], dense_correlation(frame, t)),
            (got2[j], dense_correlation(frame, t**2)),
            (cor.norm2[j], dense_correlation(np.ones(frame.shape), t**2)),
        ):
            # spectra kept in single precision (memory): ~1e-7 relative
            assert np.max(np.abs(res - ref)) <= 1e-5 * np.max(np.abs(ref))
    # the batched best-template search (2 templates per batch) agrees with a dense argmax
    dense = np.array([dense_correlation(frame, t) for t in imgs])
    n2 = np.array([dense_correlation(np.ones(frame.shape), t**2) for t in imgs])
    score = dense / np.sqrt(n2)
    sb, jb, cb, nb = Correlator(tmpl, frame.shape, batch=2).best(frame)
    ok = np.sort(score, axis=0)[-1] - np.sort(score, axis=0)[-2] > 1e-4  # no near-ties
    assert ok.mean() > 0.9
    assert np.array_equal(jb[ok], np.argmax(score, axis=0)[ok])
    assert np.allclose(sb, score.max(axis=0), rtol=1e-5, atol=1e-6)
    assert np.allclose(cb[ok], np.take_along_axis(dense, jb[None], 0)[0][ok], rtol=1e-5, atol=1e-6)
    assert np.allclose(nb, np.take_along_axis(n2, jb[None], 0)[0], rtol=1e-5)


# --- pursuit -----------------------------------------------------------------------------


def test_pursuit_is_exact_on_the_grid_without_noise(analytic):
    t = frame_templates(analytic, PX, dxy=50.0, dz=250.0)
    # on the pursuit's grid: pixel centre +- 25 nm, z on a plane (x != y to catch a swap)
    truth = np.array([[1625.0, 2075.0, -250.0, 3000.0], [4775.0, 4325.0, 500.0, 2000.0]])
    mu = analytic.render(*truth.T, (64, 64), PX)
    est = frame_pursuit(mu + 10.0, 10.0, t)
    assert len(est) == 2
    got = est.as_array()[np.argsort(-est.photons)]
    assert np.allclose(got[:, :3], truth[:, :3], atol=1e-6)
    assert np.allclose(got[:, 3], truth[:, 3], rtol=1e-3)


@pytest.mark.parametrize("name", ["dh-analytic", "astig-gauss"])
def test_pursuit_finds_two_separated_emitters(name):
    model = make_psf(name)
    t = frame_templates(model, PX, dxy=50.0, dz=120.0)
    truth = np.array([[1630.0, 2040.0, -300.0, 3000.0], [4720.0, 4380.0, 400.0, 3000.0]])
    if name == "astig-gauss":
        truth[:, 2] = [-300.0, 250.0]
    for seed in range(3):
        frame = poisson_frame(model, truth, (64, 64), seed=seed)
        est = frame_pursuit(frame, 10.0, t)
        assert len(est) == 2
        for x, y in truth[:, :2]:
            assert np.min(np.hypot(est.x - x, est.y - y)) < 100.0
        assert np.all(np.abs(est.photons - 3000.0) < 600.0)


def test_pursuit_on_the_tabulated_double_helix(dh_table):
    t = frame_templates(dh_table, PX, dxy=50.0, dz=120.0)
    truth = np.array([[1630.0, 2040.0, -300.0, 3000.0], [4720.0, 4380.0, 400.0, 3000.0]])
    frame = poisson_frame(dh_table, truth, (64, 64), seed=1)
    cor = Correlator(t, frame.shape)
    # One atom per cycle: exactly the two emitters.
    est = frame_pursuit(frame, 10.0, t, correlator=cor, per_cycle=1)
    assert len(est) == 2
    for x, y in truth[:, :2]:
        assert np.min(np.hypot(est.x - x, est.y - y)) < 100.0
    # Default (many atoms per cycle): the two strongest atoms are the emitters. The pursuit
    # may add weak atoms near the frame's edges (seen on this PSF, left to the fit stage).
    est = frame_pursuit(frame, 10.0, t, correlator=cor)
    order = np.argsort(-est.photons)
    top = est.as_array()[order[:2]]
    for x, y in truth[:, :2]:
        assert np.min(np.hypot(top[:, 0] - x, top[:, 1] - y)) < 100.0
    assert np.all(est.photons[order[2:]] < 0.25 * top[:, 3].min())


def test_pursuit_finds_nothing_in_background(analytic, dh_table):
    for model in (analytic, dh_table):
        t = frame_templates(model, PX, dxy=50.0, dz=120.0)
        cor = Correlator(t, (64, 64))
        for seed in range(3):
            frame = np.random.default_rng(100 + seed).poisson(10.0, (64, 64)).astype(float)
            assert len(frame_pursuit(frame, 10.0, t, correlator=cor)) <= 1


def test_pursuit_arguments_are_checked(analytic):
    t = frame_templates(analytic, PX, dxy=50.0, dz=500.0)
    with pytest.raises(ValueError, match="2-D"):
        frame_pursuit(np.zeros((2, 20, 20)), 10.0, t)
    with pytest.raises(ValueError, match="correlator"):
        frame_pursuit(np.zeros((20, 20)), 10.0, t, correlator=Correlator(t, (20, 21)))


# --- fits with a fixed offset ------------------------------------------------------------


def test_fit_with_a_neighbour_as_offset_matches_the_joint_fit(analytic):
    w = 17
    truth = np.array([[700.0, 800.0, -100.0, 2500.0], [1050.0, 950.0, 300.0, 2500.0]])
    img = poisson_frame(analytic, truth, (w, w), seed=2)
    start = truth + np.array([[30.0, -20.0, 60.0, -300.0], [-20.0, 30.0, -50.0, 200.0]])
    joint = fit_emitters(img, analytic, Emitters.from_array(start), pixel_size=PX)
    offset = analytic.render(*truth[1:].T, (w, w), PX)  # B's exact expected image
    alone = fit_emitters(
        img, analytic, Emitters.from_array(start[:1]), pixel_size=PX, offset=offset
    )
    a_joint = joint.emitters.as_array()[0]
    a_alone = alone.emitters.as_array()[0]
    assert alone.converged and len(alone.emitters) == 1
    assert np.all(np.abs(a_alone[:3] - a_joint[:3]) < 5.0)
    assert abs(a_alone[3] - a_joint[3]) < 0.05 * a_joint[3]
    # the model image holds the offset: A's image + background + B's image
    own = analytic.render(*a_alone[:, None], (w, w), PX)
    assert np.allclose(alone.model_image, own + alone.background[0] + offset)
    # without the offset A's fit is pulled towards B's light: the offset is what helps
    blind = fit_emitters(img, analytic, Emitters.from_array(start[:1]), pixel_size=PX)
    assert np.hypot(*(blind.emitters.as_array()[0, :2] - truth[0, :2])) > 50.0


def test_linear_response_predicts_the_refit_after_a_neighbour_moves(analytic):
    """frame_fit skips a group when F^-1 J' (d / mu) says its emitters would not move."""
    from sparseloc.solvers.frame import _response

    w = 17
    a = np.array([[800.0, 850.0, 100.0, 2500.0]])
    b = np.array([[1250.0, 1000.0, -200.0, 3000.0]])
    img = poisson_frame(analytic, np.vstack([a, b]), (w, w), seed=4)
    kw = dict(pixel_size=PX, origin=(0.0, 0.0), tol=1e-14)
    off0 = analytic.render(*b.T, (w, w), PX)
    fit0 = fit_emitters(img, analytic, Emitters.from_array(a), offset=off0, **kw)
    resp = _response(analytic, img, fit0, {**kw, "offset": off0})
    assert resp.shape == (3, w * w)
    for move in ([10.0, 0.0, 0.0], [0.0, -8.0, 20.0]):
        moved = b + np.array([[*move, 0.0]])
        off1 = analytic.render(*moved.T, (w, w), PX)
        fit1 = fit_emitters(img, analytic, fit0.emitters, offset=off1, **kw)
        actual = fit1.emitters.as_array()[0, :3] - fit0.emitters.as_array()[0, :3]
        predicted = resp @ (off1 - off0).ravel()
        assert np.max(np.abs(actual)) > 0.3  # the neighbour's move matters
        assert np.all(np.abs(predicted - actual) < 0.25 * np.max(np.abs(actual)) + 0.02)


# --- frame fit ---------------------------------------------------------------------------


def test_frame_fit_separates_overlapping_emitters(dh_table):
    t = frame_templates(dh_table, PX, dxy=50.0, dz=120.0)
    truth = np.array(
        [
            [2200.0, 2300.0, -250.0, 3000.0],
            [2650.0, 2550.0, 350.0, 2500.0],  # 515 nm from the first
            [3900.0, 700.0, 0.0, 3000.0],  # far from both: a group of its own
        ]
    )
    frame = poisson_frame(dh_table, truth, (48, 48), seed=0)
    start = truth + np.array(
        [[50.0, -40.0, 100.0, -500.0], [-40.0, 50.0, -100.0, 500.0], [-30.0, 40.0, 80.0, 0.0]]
    )
    fit = frame_fit(frame, dh_table, Emitters.from_array(start), **frame_fit_kwargs(t))
    est = fit.emitters.as_array()
    assert len(est) == 3
    match = [int(np.argmin(np.hypot(*(est[:, :2] - p[:2]).T))) for p in truth]
    assert sorted(match) == [0, 1, 2]
    for i, p in zip(match, truth, strict=True):
        assert np.hypot(*(est[i, :2] - p[:2])) < 40.0
        assert abs(est[i, 2] - p[2]) < 80.0
    assert fit.sigma.shape == (3, 4)
    assert np.all(np.isfinite(fit.sigma)) and np.all(fit.sigma > 0)
    assert fit.group.shape == fit.background.shape == fit.gof.shape == fit.flags.shape == (3,)
    assert fit.group[match[0]] == fit.group[match[1]] != fit.group[match[2]]
    assert np.all(np.abs(fit.background - 10.0) < 1.5)
    assert np.all(fit.flags == "ok")


def test_the_memo_keeps_only_the_last_sweeps_groups(dh_table, monkeypatch):
    """The sweeps' memo of groups left in place holds the groups of the last sweep only: kept
    for every sweep, its windows and fits piled up (gigabytes on a frame fitted with the
    wrong PSF)."""
    import sparseloc.solvers.frame as frame_module

    sizes = []

    class Sweep(frame_module._Sweep):
        def __call__(self, em):
            out = super().__call__(em)
            sizes.append((len(self.memo), len(set(i[4] for i in out[1]))))
            return out

    monkeypatch.setattr(frame_module, "_Sweep", Sweep)
    t = frame_templates(dh_table, PX, dxy=50.0, dz=120.0)
    rng = np.random.default_rng(4)
    truth = np.column_stack(
        [rng.uniform(500, 4300, 12), rng.uniform(500, 4300, 12), rng.uniform(-400, 400, 12),
         rng.uniform(2000, 4000, 12)]
    )  # fmt: skip
    frame = poisson_frame(dh_table, truth, (48, 48), seed=4)
    start = truth + rng.normal(0, [60.0, 60.0, 150.0, 500.0], truth.shape)
    frame_fit(frame, dh_table, Emitters.from_array(start), **frame_fit_kwargs(t))
    assert len(sizes) > 2
    assert all(memo <= groups for memo, groups in sizes), sizes


def test_frame_fit_of_nothing(analytic):
    fit = frame_fit(
        np.full((30, 30), 10.0),
        analytic,
        Emitters.empty(),
        pixel_size=PX,
        background=10.0,
        group_distance=500.0,
        pad=5,
        reach=1000.0,
    )
    assert len(fit.emitters) == 0 and fit.sigma.shape == (0, 4) and fit.group.shape == (0,)


def test_z_flip_reaches_the_other_end_of_the_range(dh_table):
    t = frame_templates(dh_table, PX, dxy=50.0, dz=120.0)
    kw = frame_fit_kwargs(t)
    truth = np.array([[2030.0, 1970.0, -900.0, 3000.0]])
    frame = poisson_frame(dh_table, truth, (40, 40), seed=0)
    start = Emitters.from_array([[2030.0, 1970.0, 990.0, 3000.0]])  # the wrong end
    fit = frame_fit(frame, dh_table, start, **kw)
    assert abs(fit.emitters.z[0] - (-900.0)) < 60.0
    # Count selection and relocation can also get there (by adding an emitter and removing
    # the stuck one, or by moving it), so the flip is isolated with both off: without it the
    # fit stays at the wrong end, with it it reaches the right one.
    stuck = frame_fit(frame, dh_table, start, count_selection=False, z_flip=0, relocate=0, **kw)
    assert stuck.emitters.z[0] > 900.0
    flipped = frame_fit(frame, dh_table, start, count_selection=False, relocate=0, **kw)
    assert abs(flipped.emitters.z[0] - (-900.0)) < 60.0
    moved = frame_fit(frame, dh_table, start, count_selection=False, z_flip=0, **kw)
    assert abs(moved.emitters.z[0] - (-900.0)) < 60.0


def test_relocation_moves_an_emitter_stuck_in_the_wrong_place(dh_table):
    """Two emitters; the start has one right and the other 500 nm from its image at the
    wrong z, where the sweeps cannot pull it back (of 40 random wrong starts of this kind,
    26 stayed stuck and relocation freed 20). Relocation alone (count selection and z flips
    off) puts it on its image; without relocation it stays wrong."""
    from sparseloc.solvers.relocate import relocation_pass

    t = frame_templates(dh_table, PX, dxy=50.0, dz=120.0)
    kw = frame_fit_kwargs(t)
    truth = np.array([[2000.0, 2000.0, -300.0, 3000.0], [2600.0, 2300.0, 400.0, 3000.0]])
    frame = poisson_frame(dh_table, truth, (48, 48), seed=2)
    wrong = truth.copy()
    wrong[1, :3] = [2464.0, 1943.0, -872.0]
    start = Emitters.from_array(wrong)
    off = dict(count_selection=False, z_flip=0, **kw)

    def errors(e):
        e = np.asarray(e).reshape(-1, 4)
        return [np.min(np.hypot(e[:, 0] - p[0], e[:, 1] - p[1])) for p in truth]

    stuck = frame_fit(frame, dh_table, start, relocate=0, **off)
    assert len(stuck.emitters) == 2 and max(errors(stuck.emitters.as_array())) > 300.0
    fixed = frame_fit(frame, dh_table, start, **off)
    assert len(fixed.emitters) == 2 and max(errors(fixed.emitters.as_array())) < 40.0
    # one sweep at a time is enough for the passes to run
    brief = frame_fit(frame, dh_table, start, sweeps=1, **off)
    assert max(errors(brief.emitters.as_array())) < 40.0

    # a pass on the stuck solution keeps a relocation; on the fixed one none is left
    def one_pass(fit, failed):
        return relocation_pass(
            frame,
            dh_table,
            fit.emitters.as_array(),
            fit.background,
            px=PX,
            group_distance=kw["group_distance"],
            pad=kw["pad"],
            reach=kw["reach"],
            min_photons=200.0,
            failed=failed,
        )

    em, moved = one_pass(stuck, [])
    assert moved >= 1 and max(errors(em)) < 100.0
    again, moved2 = one_pass(fixed, [])  # a fresh memory: every emitter is tried
    assert moved2 == 0 and np.array_equal(again, fixed.emitters.as_array())


def test_memo_entries_are_reused_only_when_nothing_would_move():
    from sparseloc.solvers.frame import _Memo, _unmoved

    shape, origin = (4, 5), (100.0, 200.0)
    old = np.zeros(shape)
    resp = np.zeros((3, 20))
    resp[0, 7] = 2.0  # x moves 2 nm per photon added at pixel 7
    entry = _Memo(old, 0.1, None, None, origin, [resp], 1.0)
    small = np.zeros(shape)
    small.flat[3] = 0.05
    assert _unmoved(entry, small, origin, 1.0)  # within the plain tolerance
    assert not _unmoved(entry, small, (0.0, 0.0), 1.0)  # another window
    assert not _unmoved(entry, np.zeros((5, 5)), origin, 1.0)
    d = np.zeros(shape)
    d.flat[3] = 0.8  # above the tolerance, below the cap, no response there: skipped
    assert _unmoved(entry, d, origin, 1.0)
    assert not _unmoved(entry, d, origin, 0.0)  # the response test switched off
    d.flat[7] = 0.6  # predicted shift 1.2 nm > 1 nm: refitted
    assert not _unmoved(entry, d, origin, 1.0)
    assert _unmoved(entry, d, origin, 1.5)
    assert not _unmoved(entry, d * 2.0, origin, 5.0)  # above the cap
    calls = []
    lazy = _Memo(old, 0.1, None, None, origin, [lambda: calls.append(1) or resp], 1.0)
    assert _unmoved(lazy, small, origin, 1.0) and not calls  # not computed when not needed
    assert not _unmoved(lazy, d, origin, 1.0) and _unmoved(lazy, d, origin, 1.5)
    assert calls == [1]  # computed once
    singular = _Memo(old, 0.1, None, None, origin, [None], 1.0)
    assert not _unmoved(singular, d, origin, 1.0)


def test_a_failed_z_flip_is_not_tried_again_nearby(dh_table, monkeypatch):
    import sparseloc.solvers.frame as frame_mod

    truth = np.array([[2030.0, 1970.0, -900.0, 3000.0]])  # truly near the low end
    frame = poisson_frame(dh_table, truth, (40, 40), seed=0)
    kw = dict(pixel_size=PX, origin=(0.0, 0.0), background=10.0)
    fit = fit_emitters(frame, dh_table, Emitters.from_array(truth), **kw)
    calls = {"n": 0}
    real = frame_mod.fit_emitters

    def counting(*a, **k):
        calls["n"] += 1
        return real(*a, **k)

    monkeypatch.setattr(frame_mod, "fit_emitters", counting)
    failed: list = []
    same = frame_mod._try_z_flips(frame, dh_table, fit, kw, 0.15, failed)
    assert same is fit and calls["n"] == 1 and len(failed) == 1  # tried, lost, remembered
    # 10 nm away laterally, 20 nm in z: not tried again
    near = fit.emitters.as_array() + np.array([[10.0, 0.0, 20.0, 0.0]])
    moved = replace(fit, emitters=Emitters.from_array(near))
    assert frame_mod._try_z_flips(frame, dh_table, moved, kw, 0.15, failed) is moved
    assert calls["n"] == 1
    # 100 nm away: tried
    far = fit.emitters.as_array() + np.array([[100.0, 0.0, 0.0, 0.0]])
    frame_mod._try_z_flips(
        frame, dh_table, replace(fit, emitters=Emitters.from_array(far)), kw, 0.15, failed
    )
    assert calls["n"] == 2


# --- pipeline ----------------------------------------------------------------------------


def test_localize_with_the_frame_method():
    from sparseloc.evaluate import evaluate
    from sparseloc.io.tables import LOCS_COLUMNS
    from sparseloc.pipeline import LocalizeParams, localize
    from sparseloc.simulate import simulate

    model = make_psf("dh")  # the pipeline tabulates it
    shape = (48, 48)
    sim = simulate(
        model,
        scene="uniform",
        n_frames=2,
        shape=shape,
        pixel_size=PX,
        density=0.3,
        photons=(2000.0, 5000.0),
        background=10.0,
        seed=1,
    )
    frames = sim.movie.astype(float) - sim.camera.offset
    done = []
    params = LocalizeParams(pixel_size=PX, method="frame")
    res = localize(frames, model, params, progress=done.append)
    tab = res.table
    assert sum(done) == 2
    assert list(tab.columns) == list(LOCS_COLUMNS)
    assert len(tab) > 0 and set(tab["frame"]) <= {0, 1}
    assert np.all((tab["x_nm"] >= 0) & (tab["x_nm"] < shape[1] * PX))
    assert np.all((tab["y_nm"] >= 0) & (tab["y_nm"] < shape[0] * PX))
    assert not tab.duplicated(["frame", "x_nm", "y_nm"]).any()
    assert np.all(np.isfinite(tab[["sigma_x_nm", "sigma_y_nm", "sigma_z_nm"]].to_numpy()))
    # window ids are the groups: never shared between frames
    assert tab.groupby("window_id")["frame"].nunique().max() == 1
    assert res.n_windows == tab["window_id"].nunique()
    ev = evaluate(tab, sim.truth)
    assert ev.recall >= 0.6 and ev.precision >= 0.6


def test_two_worker_processes_give_the_same_table():
    from sparseloc.pipeline import LocalizeParams, localize
    from sparseloc.psf import make_psf
    from sparseloc.simulate import simulate

    model = make_psf("dh-analytic")
    sim = simulate(
        model,
        scene="uniform",
        n_frames=6,
        shape=(40, 40),
        pixel_size=100.0,
        density=0.5,
        photons=(2000.0, 5000.0),
        background=10.0,
        seed=5,
    )
    frames = sim.movie.astype(float) - sim.camera.offset
    params = LocalizeParams(pixel_size=100.0)
    one = localize(frames, model, params)
    two = localize(frames, model, params, workers=2)
    assert len(one.table) > 5
    pd.testing.assert_frame_equal(one.table, two.table)
    with pytest.raises(ValueError, match="workers"):
        localize(frames, model, params, workers=0)


def test_frame_fit_accepts_read_noise_below_zero(analytic):
    """EMCCD/sCMOS frames in photons have pixels below zero; the fit clips them."""
    px = 100.0
    truth = np.array([[1650.0, 1550.0, 100.0, 3000.0]])
    mu = 10.0 + analytic.render(*truth.T, (32, 32), px)
    frame = np.random.default_rng(3).poisson(mu).astype(float) - 10.5
    frame[0, 0] = -4.0
    out = frame_fit(
        frame,
        analytic,
        Emitters.from_array(np.add(truth, [40.0, -30.0, 50.0, 0.0])),
        pixel_size=px,
        background=1.0,
        group_distance=500.0,
        pad=6,
        reach=2000.0,
        noise="emccd",
    )
    assert len(out.emitters) == 1
    assert abs(out.emitters.x[0] - truth[0, 0]) < 40.0


def test_projections_take_a_truth_table_with_a_missing_z(tmp_path):
    from sparseloc.render import plot_projections

    t = pd.DataFrame(
        {
            "frame": [0, 0, 1],
            "x_nm": [500.0, 1500.0, 900.0],
            "y_nm": [500.0, 800.0, 1200.0],
            "z_nm": [0.0, np.nan, 300.0],
        }
    )
    path = plot_projections(t, tmp_path / "r.png", truth=t, z_range=(-500.0, 500.0))
    assert path.stat().st_size > 5000


def test_table_outside_the_model_range_is_refused(analytic):
    with pytest.raises(ValueError, match="must lie within"):
        SplinePSF.from_model(analytic, 100.0, roi=15, z_range=(-5000.0, 0.0))


def test_tiled_pursuit_finds_what_the_whole_frame_finds(analytic):
    from sparseloc.solvers.frame import tiled_pursuit

    px = 100.0
    truth = np.array(
        [
            [1250.0, 1350.0, -200.0, 3000.0],
            [5150.0, 1450.0, 100.0, 2500.0],
            [3050.0, 4150.0, 300.0, 3500.0],
            [8350.0, 8650.0, 0.0, 3000.0],
            [4650.0, 8250.0, -300.0, 2800.0],
        ]
    )
    mu = 10.0 + analytic.render(*truth.T, (96, 96), px)
    frame = np.random.default_rng(11).poisson(mu).astype(float)
    t = frame_templates(analytic, px, dxy=50.0, dz=100.0)
    whole = tiled_pursuit(frame, 10.0, t)
    cache: dict = {}
    tiled = tiled_pursuit(frame, 10.0, t, max_pixels=1000, core=40, correlators=cache)
    assert list(cache) == [(70, 70)]  # tiles of 40 + 2 x 15 px, one shape for all
    # the strong atoms (the emitters; weak extras are the fit's to prune) agree
    a, b = (e.as_array() for e in (whole, tiled))
    a, b = (v[v[:, 3] > 1000.0] for v in (a, b))
    a, b = (v[np.lexsort(v[:, :2].T)] for v in (a, b))
    assert len(a) == len(b) == 5
    assert np.allclose(a[:, :3], b[:, :3]) and np.allclose(a[:, 3], b[:, 3], rtol=0.05)
    assert np.all(np.hypot(*(a[:, :2] - truth[np.lexsort(truth[:, :2].T), :2]).T) < 100.0)


def test_light_is_each_emitters_image_within_reach(dh_table):
    """The relocation's frame light: each emitter's image on the pixels within reach of it."""
    from sparseloc.solvers.frame_windows import light_pieces, sum_pieces

    def _light(model, em, shape, px, origin, reach):
        return sum_pieces(
            light_pieces(model, em, shape, px, origin, reach), (0, shape[0], 0, shape[1])
        )

    em = np.array([[1000.0, 1200.0, -200.0, 3000.0], [2500.0, 1800.0, 300.0, 2000.0]])
    shape, origin = (30, 35), (-200.0, 300.0)
    full = dh_table.render(*em.T, shape, PX, origin=origin)
    np.testing.assert_allclose(_light(dh_table, em, shape, PX, origin, 1e6), full, atol=1e-12)
    near = _light(dh_table, em[:1], shape, PX, origin, 500.0)
    alone = dh_table.render(*em[:1].T, shape, PX, origin=origin)
    cx = origin[0] + (np.arange(shape[1]) + 0.5) * PX
    cy = origin[1] + (np.arange(shape[0]) + 0.5) * PX
    inside = (np.abs(cy[:, None] - em[0, 1]) <= 450.0) & (np.abs(cx[None, :] - em[0, 0]) <= 450.0)
    outside = (np.abs(cy[:, None] - em[0, 1]) > 650.0) | (np.abs(cx[None, :] - em[0, 0]) > 650.0)
    np.testing.assert_allclose(near[inside], alone[inside], atol=1e-12)
    assert np.all(near[outside] == 0.0) and alone[outside].max() > 0.1
    # an emitter out of the window's reach adds nothing
    far = np.array([[9000.0, 9000.0, 0.0, 3000.0]])
    assert not _light(dh_table, far, shape, PX, origin, 500.0).any()
    # the pieces summed over a box are that box of the light (what the relocation trials use)
    both = np.vstack([em, far])
    pieces = light_pieces(dh_table, both, shape, PX, origin, 500.0)
    assert pieces[2] is None
    box = (4, 21, 9, 33)
    np.testing.assert_allclose(
        sum_pieces(pieces, box), _light(dh_table, both, shape, PX, origin, 500.0)[4:21, 9:33]
    )
    assert sum_pieces(pieces[1:2], box).max() > 0.1


def test_neighbour_light_from_pieces_equals_rendering_into_the_window(dh_table, analytic):
    """The sweeps' offsets: one image per emitter over the box where the spline is non-zero,
    cropped into windows, gives what rendering the emitters into each window gives."""
    from sparseloc.solvers.frame_windows import NeighbourLight

    ry, rx = dh_table.zero_beyond(PX)
    rng = np.random.default_rng(5)
    for _ in range(10):  # the extent is tight: nothing lit beyond it, something just inside
        x, y = rng.uniform(3000.0, 3100.0, 2)
        img = dh_table.render([x], [y], [rng.uniform(-800, 800)], [1.0], (61, 61), PX)
        c = (np.arange(61) + 0.5) * PX
        beyond = (np.abs(c - y)[:, None] > ry) | (np.abs(c - x)[None, :] > rx)
        assert np.all(img[beyond] == 0.0)
        assert np.abs(c - x)[img.any(axis=0)].max() > rx - 1.5 * PX
    shape = (40, 50)
    em = np.array(
        [
            [1000.0, 1200.0, -200.0, 3000.0],
            [2500.0, 1800.0, 300.0, 2000.0],
            [-150.0, 3900.0, 0.0, 2500.0],  # outside the frame, light inside it
            [4960.0, 20.0, 600.0, 1500.0],  # at a corner
        ]
    )
    for model in (dh_table, analytic):  # analytic: no table, rendered into the window
        light = NeighbourLight(model, shape, PX)
        for box in [(0, 40, 0, 50), (3, 27, 11, 44), (30, 40, 0, 8)]:
            r0, r1, c0, c1 = box
            ref = model.render(*em.T, (r1 - r0, c1 - c0), PX, origin=(c0 * PX, r0 * PX))
            got = light.window(em, box)
            np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)
            got = light.window(em[::-1], box)  # the images are reused, in any order
            np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)
        light.keep(em[:1])
        if model is dh_table:
            assert len(light._pieces) == 1


def test_neighbour_light_renders_only_emitters_that_reach_the_window(dh_table):
    """An emitter whose light cannot reach a window adds exactly zero there: it is neither
    rendered nor summed, and a window out of every emitter's reach is all zeros."""
    from sparseloc.solvers.frame_windows import NeighbourLight

    _, rx = dh_table.zero_beyond(PX)
    shape = (200, 200)
    near = [2000.0, 2000.0, 0.0, 3000.0]
    far = [2000.0 + 2 * rx + 20 * PX, 2000.0, 0.0, 3000.0]
    light = NeighbourLight(dh_table, shape, PX)
    box = (15, 26, 15, 26)
    got = light.window(np.array([near, far]), box)
    ref = dh_table.render([near[0]], [near[1]], [0.0], [3000.0], (11, 11), PX, origin=(1500, 1500))
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)
    assert len(light._pieces) == 1  # the far emitter was not rendered
    c = int((far[0] + rx) / PX) + 3  # beyond the far emitter's reach too
    empty = light.window(np.array([near, far]), (0, 5, c, c + 5))
    assert empty.shape == (5, 5) and not empty.any()
    assert len(light._pieces) == 1


# --- count selection's thresholds --------------------------------------------------------


def test_the_removal_threshold_is_the_chi_square_one_for_a_lone_emitter():
    from sparseloc.solvers.refine import LR_THRESHOLD, removal_threshold

    assert removal_threshold(1, 80.0, LR_THRESHOLD) == LR_THRESHOLD
    assert removal_threshold(2, 80.0, LR_THRESHOLD) == 80.0
    assert removal_threshold(1, 10.0, LR_THRESHOLD) == 10.0
    assert removal_threshold(1, 80.0, None) == 80.0


def test_a_lone_dim_emitter_at_high_background_is_kept(analytic):
    """1,000 photons on 300 photons/px: a likelihood ratio of about 53, between the chi-square
    threshold (18.47) and the frame's addition threshold (80). Alone in its group it stays."""
    shape, b, n = (48, 48), 300.0, 1000.0
    img = analytic.render(
        np.array([2400.0]), np.array([2400.0]), np.zeros(1), np.ones(1), shape, PX
    )
    expected_ratio = float(np.sum((n * img) ** 2 / (b + n * img)))
    assert 40 < expected_ratio < 70
    t = frame_templates(analytic, PX, dxy=50.0, dz=100.0)
    # a window holding 90 % of the light, as the pipeline pads it
    kw = {**frame_fit_kwargs(t), "background": b, "pad": int(np.ceil(t.radius90))}
    kept = 0
    for seed in range(10):
        f = np.random.default_rng(seed).poisson(n * img + b).astype(float)
        start = Emitters.from_array(np.array([[2400.0, 2400.0, 0.0, n]]))
        fit = frame_fit(f, analytic, start, **kw)
        kept += len(fit.emitters) == 1
    assert kept >= 8


def test_localize_from_given_starts_keeps_the_true_emitters():
    """Started from the truth, the frame solver keeps it (the fits' ceiling); started from
    nothing, it finds nothing; bad starts are refused in one sentence."""
    from sparseloc.evaluate import evaluate
    from sparseloc.pipeline import LocalizeParams, localize

    truth_rows = np.array([[1500.0, 1600.0, -200.0, 3000.0], [3300.0, 3100.0, 300.0, 4000.0]])
    frames = np.stack(
        [poisson_frame(analytic_model(), truth_rows, (48, 48), seed=s) for s in (0, 1)]
    )
    truth = pd.DataFrame(
        {
            "frame": [0, 0, 1, 1],
            "x_nm": np.tile(truth_rows[:, 0], 2),
            "y_nm": np.tile(truth_rows[:, 1], 2),
            "z_nm": np.tile(truth_rows[:, 2], 2),
            "photons": np.tile(truth_rows[:, 3], 2),
        }
    )
    params = LocalizeParams(pixel_size=PX, method="frame")
    res = localize(frames, analytic_model(), params, starts=truth.drop(columns="photons"))
    ev = evaluate(res.table, truth)
    assert ev.recall == 1.0 and ev.precision == 1.0
    assert ev.rmse_lateral < 30.0
    empty = localize(frames, analytic_model(), params, starts=truth.iloc[:0])
    assert len(empty.table) == 0
    with pytest.raises(ValueError, match="no column z_nm"):
        localize(frames, analytic_model(), params, starts=truth.drop(columns="z_nm"))
    with pytest.raises(ValueError, match="need method='frame'"):
        params = LocalizeParams(pixel_size=PX, method="hybrid")
        localize(frames, analytic_model(), params, starts=truth)


def analytic_model():
    return make_psf("dh-analytic")


def test_groups_left_empty_by_removals_are_not_counted(monkeypatch):
    """The third walk-through: a dense frame printed "1 frames, 492 groups, 294 localizations":
    groups whose emitters were all removed were counted, and their ids left gaps."""
    from types import SimpleNamespace

    from sparseloc.pipeline import LocalizeParams, LocalizeResult, _FrameWork

    k = 3
    fit = SimpleNamespace(
        emitters=Emitters(np.zeros(k), np.zeros(k), np.zeros(k), np.ones(k)),
        background=np.zeros(k),
        sigma=np.ones((k, 4)),
        gof=np.ones(k),
        flags=np.array(["ok"] * k),
        group=np.array([0, 4, 4]),  # groups 1-3 lost all their emitters
    )
    work = _FrameWork.__new__(_FrameWork)
    work.p = LocalizeParams(pixel_size=PX, method="frame")
    work.solver = lambda frame, bg, start, censored: fit
    rows, n_groups = work(0, np.zeros((8, 8)), np.zeros((8, 8)))
    assert n_groups == 2 and list(rows[0]["window_id"]) == [0, 1, 1]
    res = LocalizeResult(pd.DataFrame({"x_nm": np.zeros(k)}), 1, n_groups, 1.0)
    assert res.summary().startswith("1 frame, 2 groups, 3 localizations")
