"""The two-tier schedule of the frame solver: detection planes, units, promotion, crowds."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from tests.cli_checks import refused, run

from sparseloc.config import LocalizeParams
from sparseloc.detect import detect_candidates
from sparseloc.pipeline import _FrameSolver, localize, work_model_for
from sparseloc.psf import make_psf
from sparseloc.solvers.two_tier import (
    CROP_STEP,
    TierCounts,
    crowd_boxes,
    crowded,
    detection_planes,
    misfit,
    overlapping,
    solve_two_tier,
)

PX = 100.0
SHAPE = (64, 64)


@pytest.fixture(scope="module")
def astig():
    """The astigmatic pupil model tabulated as the pipeline does, and its frame solver."""
    p = LocalizeParams(pixel_size=PX, frame_schedule="two-tier")
    work = work_model_for(make_psf("astig"), p)
    return work, p, _FrameSolver(work, p, SHAPE)


def _frame(model, truth, seed=0, background=10.0):
    t = np.asarray(truth, float).reshape(-1, 4)
    mu = model.render(t[:, 0], t[:, 1], t[:, 2], t[:, 3], SHAPE, PX) + background
    return np.random.default_rng(seed).poisson(mu).astype(float)


def _solve(solver, frame, counts=None, background=10.0):
    return solve_two_tier(
        frame,
        np.full(SHAPE, background),
        solver.model,
        solver.templates,
        pursuit=solver.start,
        fit_options=solver.fit_kwargs(),
        min_snr=5.0,
        noise_factor=1.0,
        counts=counts,
    )


def test_detection_with_one_plane_is_the_single_template_test():
    """A stack of one template gives what one template gives; the plane index comes along."""
    rng = np.random.default_rng(1)
    t = np.exp(-((np.arange(9) - 4)[:, None] ** 2 + (np.arange(9) - 4)[None, :] ** 2) / 4.0)
    img = rng.poisson(10.0, (40, 44)).astype(float)
    img[20, 20] += 400.0
    a = detect_candidates(img, 10.0, t)
    b, plane = detect_candidates(img, 10.0, t[None], return_plane=True)
    assert np.array_equal(a, b) and len(a) >= 1 and np.all(plane == 0)
    wide = np.exp(-((np.arange(9) - 4)[:, None] ** 2 + (np.arange(9) - 4)[None, :] ** 2) / 20.0)
    _, plane = detect_candidates(img, 10.0, np.stack([wide, t]), return_plane=True)
    assert plane[0] == 1  # the sharp spot correlates best with the sharp template


def test_detection_planes_span_the_z_range(astig):
    _, _, solver = astig
    planes = detection_planes(solver.templates)
    n_z = len(np.unique(solver.templates.z))
    assert 2 <= len(planes) < n_z
    unit = planes.reshape(len(planes), -1)
    unit = unit / np.linalg.norm(unit, axis=1)[:, None]
    # neighbouring kept planes are distinct images, not repeats
    assert np.all(np.sum(unit[1:] * unit[:-1], axis=1) < 0.999)


def test_crowd_boxes_merge_and_snap_inside_the_frame():
    boxes = crowd_boxes(np.array([[10.0, 10.0], [14.0, 12.0], [50.0, 90.0]]), 5, (64, 100))
    assert len(boxes) == 2
    for r0, r1, c0, c1 in boxes:
        assert 0 <= r0 < r1 <= 64 and 0 <= c0 < c1 <= 100
        assert (r1 - r0) % CROP_STEP == 0 and (c1 - c0) % CROP_STEP == 0
    # a box holds its points with the margin (inside the frame)
    r0, r1, c0, c1 = boxes[0]
    assert r0 <= 5 and r1 >= 20 and c0 <= 5 and c1 >= 18


def test_misfit_is_near_zero_for_the_true_model_and_large_for_a_missing_emitter():
    rng = np.random.default_rng(3)
    mu = np.full((25, 25), 10.0)
    mu[10:14, 10:14] += 50.0
    scores = [misfit(rng.poisson(mu).astype(float), mu, None, 1.0, 0.0) for _ in range(200)]
    assert abs(np.mean(scores)) < 0.3 and 0.7 < np.std(scores) < 1.4
    y = rng.poisson(mu).astype(float)
    y[2:5, 2:5] += 40.0  # light the model does not have
    assert misfit(y, mu, None, 1.0, 0.0) > 5.0


def test_isolated_emitters_are_fitted_alone(astig):
    work, _, solver = astig
    truth = [[1500.0, 1600.0, -200.0, 3000.0], [4800.0, 4500.0, 250.0, 2500.0]]
    counts = TierCounts()
    fit = _solve(solver, _frame(work, truth), counts)
    em = fit.emitters.as_array().reshape(-1, 4)
    assert len(em) == 2 and counts.singles == 2 and counts.frames_with_crowds == 0
    for t in truth:
        d = np.hypot(em[:, 0] - t[0], em[:, 1] - t[1])
        k = int(np.argmin(d))
        assert d[k] < 30.0 and abs(em[k, 2] - t[2]) < 60.0


def test_a_close_pair_is_promoted_and_both_are_found(astig):
    work, _, solver = astig
    truth = [[3000.0, 3000.0, 0.0, 3000.0], [3350.0, 3050.0, 200.0, 3000.0]]
    counts = TierCounts()
    fit = _solve(solver, _frame(work, truth, seed=2), counts)
    em = fit.emitters.as_array().reshape(-1, 4)
    assert counts.frames_with_crowds == 1
    assert len(em) == 2
    for t in truth:
        assert np.min(np.hypot(em[:, 0] - t[0], em[:, 1] - t[1])) < 60.0


def test_two_tier_matches_the_whole_frame_schedule_on_a_sparse_movie(astig):
    """Same emitters, to a few nm, where the images do not overlap."""
    work, p, _ = astig
    rng = np.random.default_rng(5)
    frames = []
    for i in range(3):
        xy = np.array([[1200.0, 1300.0], [4900.0, 1500.0], [1700.0, 5000.0], [5000.0, 5100.0]])
        xy += rng.uniform(-200, 200, xy.shape)
        z = rng.uniform(-400, 400, 4)
        truth = np.column_stack([xy, z, rng.uniform(1500, 4000, 4)])
        frames.append(_frame(work, truth, seed=i))
    frames = np.array(frames)
    whole = localize(frames, work, replace(p, frame_schedule="whole-frame", background="spatial"))
    tiers = localize(frames, work, replace(p, background="spatial"))
    assert len(tiers.table) == len(whole.table) == 12
    a = whole.table.sort_values(["frame", "x_nm"])[["x_nm", "y_nm", "z_nm"]].to_numpy()
    b = tiers.table.sort_values(["frame", "x_nm"])[["x_nm", "y_nm", "z_nm"]].to_numpy()
    assert np.max(np.abs(a[:, :2] - b[:, :2])) < 3.0 and np.max(np.abs(a[:, 2] - b[:, 2])) < 8.0


def _crowd(centre, n, spread, seed):
    """``n`` emitters within ``spread`` nm of ``centre`` (nm), 3000 photons, z in +-300 nm."""
    rng = np.random.default_rng(seed)
    xy = np.asarray(centre, float) + rng.uniform(-spread, spread, (n, 2))
    return np.column_stack([xy, rng.uniform(-300, 300, n), np.full(n, 3000.0)])


def test_the_auto_rule_solves_whole_where_crowds_outnumber_the_singles_or_one_is_large():
    px, reach = 100.0, 1000.0  # starts within 10 px of each other form one crowd

    def starts(*xy_px):
        xy = np.asarray(xy_px, float).reshape(-1, 2) * px
        return np.column_stack([xy, np.zeros(len(xy)), np.full(len(xy), 1e3)])

    assert not crowded(starts(), 0, px, reach)
    pair = starts((10, 10), (14, 10))
    assert not crowded(pair, 2, px, reach)  # a small crowd beside as many singles
    assert crowded(pair, 1, px, reach)  # (a) more crowd starts than singles
    apart = starts((10, 10), (40, 10), (10, 40), (40, 40))
    assert not crowded(apart, 4, px, reach)  # four small crowds, not one large
    chain = starts((10, 10), (18, 10), (26, 10), (34, 10))  # linked one to the next
    assert crowded(chain, 20, px, reach)  # (b) one crowd of more than SMALL_CROWD
    # (a) counts only in a frame where most emitters' images overlap another's: three crowd
    # starts beside two singles send a 32 x 32 px frame whole, not a 256 x 256 px one
    three = starts((5, 5), (25, 5), (5, 25))
    assert overlapping(5, (32, 32), px, reach) > 0.5 > overlapping(5, (256, 256), px, reach)
    assert crowded(three, 2, px, reach, (32, 32))
    assert not crowded(three, 2, px, reach, (256, 256))


def test_auto_solves_a_large_crowd_with_the_whole_frame_solver_on_its_crop(astig):
    """``auto``: the two-tier solver's result where its crowds are small (a close pair among
    singles here); where the count selection grows a crowd large, that crowd's crop is
    solved by the whole-frame solver with the units' light known, and the frame is not
    sent whole: its emitters are the whole-frame solver's to a few nm (the singles are the
    units' fits), and not those of the two-tier schedule's fits of the crowd."""
    work, p, _ = astig
    singles = [[1200.0, 1300.0, -200.0, 3000.0], [5000.0, 5100.0, 250.0, 2500.0],
               [1300.0, 5000.0, 100.0, 3000.0]]  # fmt: skip
    pair = [[4600.0, 1500.0, 0.0, 3000.0], [4900.0, 1550.0, 200.0, 3000.0]]
    sparse = np.vstack([singles, pair])
    crowded_frame = np.vstack([singles[:2], _crowd((3200.0, 3200.0), 8, 450.0, seed=4)])
    bg = np.full(SHAPE, 10.0)
    solvers = {
        s: _FrameSolver(work, replace(p, frame_schedule=s), SHAPE)
        for s in ("auto", "two-tier", "whole-frame")
    }

    def emitters(schedule, frame):
        e = solvers[schedule](frame, bg).emitters.as_array().reshape(-1, 4)
        return e[np.argsort(e[:, 0])]

    frame = _frame(work, sparse, seed=1)
    counts = TierCounts()
    _solve(solvers["two-tier"], frame, counts)
    assert counts.frames_with_crowds == 1 and counts.frames_whole == 0
    np.testing.assert_allclose(emitters("auto", frame), emitters("two-tier", frame))

    frame = _frame(work, crowded_frame, seed=1)
    counts = TierCounts()
    auto = solvers["auto"]
    solve_two_tier(
        frame, bg, auto.model, auto.templates, pursuit=auto.start,
        fit_options=auto.fit_kwargs(), min_snr=5.0, noise_factor=1.0, counts=counts,
        whole_when_crowded=True, whole=auto.whole,
    )  # fmt: skip
    assert counts.frames_whole == 0 and counts.frames_with_crowds == 1
    a, w, t = (emitters(s, frame) for s in ("auto", "whole-frame", "two-tier"))
    assert len(a) == len(w) >= 6
    assert np.max(np.abs(a[:, :3] - w[:, :3])) < 3.0
    np.testing.assert_allclose(a[:, 3], w[:, 3], rtol=0.02)
    assert len(t) != len(a) or np.max(np.abs(t[:, :3] - a[:, :3])) > 3.0


def test_a_crowds_crop_takes_its_part_of_an_scmos_read_noise_map(astig, monkeypatch):
    """The crop of a large crowd is solved with its own part of a read-variance map: the same
    emitters as the whole-frame schedule with that map, to a few nm."""
    import sparseloc.solvers.two_tier as two_tier

    work, _, _ = astig
    crops = []
    solve_crop = two_tier._pursuit_crop
    monkeypatch.setattr(
        two_tier, "_pursuit_crop", lambda *a, **k: crops.append(1) or solve_crop(*a, **k)
    )
    p = LocalizeParams(pixel_size=PX, noise="scmos", background="spatial")
    truth = np.vstack([[[1200.0, 1300.0, -200.0, 3000.0], [5000.0, 5100.0, 250.0, 2500.0]],
                       _crowd((3200.0, 3200.0), 8, 450.0, seed=4)])  # fmt: skip
    frames = _frame(work, truth, seed=1)[None]
    rv = np.random.default_rng(0).uniform(1.0, 9.0, SHAPE)
    a = localize(frames, work, p, read_variance=rv, check=False).table
    w = localize(
        frames, work, replace(p, frame_schedule="whole-frame"), read_variance=rv, check=False
    ).table
    assert crops and len(a) == len(w) >= 6
    cols = ["x_nm", "y_nm", "z_nm"]
    a, w = (t.sort_values("x_nm")[cols].to_numpy() for t in (a, w))
    assert np.max(np.abs(a - w)) < 3.0


def test_an_unknown_schedule_is_refused(tmp_path):
    with pytest.raises(ValueError, match="frame_schedule"):
        LocalizeParams(pixel_size=PX, frame_schedule="fast")
    movie = tmp_path / "m.tif"
    import tifffile

    tifffile.imwrite(movie, np.full((2, 40, 40), 110, np.uint16))
    res = run("localize", movie, "-o", tmp_path / "l.csv", "--pixel-size", 100, "--psf", "dh",
              "--frame-schedule", "fast")  # fmt: skip
    refused(res, "--frame-schedule")
    assert not (tmp_path / "l.csv").exists()


def test_a_unit_too_weak_for_the_count_selection_is_dropped(astig):
    """The units obey the frame solver's removal test: an emitter of 150 photons (below the
    count selection's minimum) that the detection still finds is not reported."""
    work, _, solver = astig
    frame = _frame(work, [[3200.0, 3200.0, 0.0, 150.0]], seed=1, background=0.2)
    assert len(detect_candidates(frame, 0.2, solver.templates.images[:1], threshold=5.0))
    fit = _solve(solver, frame, background=0.2)
    assert len(fit.emitters) == 0


def test_a_unit_is_refitted_only_where_the_frame_solvers_rule_says_it_would_move(astig):
    """A neighbour's light that changes a unit's window beyond the skip tolerance but moves
    its emitter by less than the shift tolerance (the frame solver's linear response) leaves
    the unit as it is; a bright, near neighbour makes it refit."""
    from sparseloc.solvers.frame import SHIFT_TOLERANCE, _unmoved
    from sparseloc.solvers.two_tier import _Tier1

    work, _, solver = astig
    a = np.array([[3200.0, 3200.0, 0.0, 3000.0]])
    f = _frame(work, a, seed=3)
    tier = _Tier1(f, np.full(SHAPE, 10.0), work, solver.fit_kwargs(), 1.0, np.zeros(SHAPE), 0.15)
    unit = tier.fit(tier.fit(a).rows)  # started where it ends: its window stays
    box = unit.box
    assert tier.box(unit.rows) == box
    origin = (box[2] * PX, box[0] * PX)
    kept = moved = 0
    for photons in (100.0, 300.0, 1000.0, 3000.0, 10000.0):
        for dx in (1100.0, 1500.0, 2000.0):
            other = np.array([[3200.0 + dx, 3200.0, 0.0, photons]])
            offset = tier.light.window(other, box)
            beyond_tol = np.max(np.abs(offset - unit.memo.offset)) > unit.memo.tol
            stays = _unmoved(unit.memo, offset, origin, SHIFT_TOLERANCE)
            again = tier.refit(unit, [other])
            assert (again is unit) == stays
            kept += beyond_tol and stays
            moved += not stays
    assert kept and moved  # both branches of the rule were taken


def test_the_detections_correlations_are_exact_with_templates_nearly_as_wide_as_the_frame():
    # shorter circular FFTs than the linear results (detect.circular_shape): direct sums
    # as the reference
    from scipy.signal import fftconvolve

    from sparseloc.detect import _correlations

    rng = np.random.default_rng(4)
    for width in (13, 12):  # odd and even
        stack, d = rng.random((2, width, width)), rng.random((10, 17))
        # the documented centring: fftconvolve's "same" with the flipped template
        want = np.stack([fftconvolve(d, stack[j, ::-1, ::-1], mode="same") for j in range(2)])
        assert np.allclose(_correlations(d, stack, {}), want, rtol=1e-4, atol=1e-4)
        # the variance map's double precision
        exact = _correlations(d, stack, {}, np.float64)
        assert exact.dtype == np.float64 and np.allclose(exact, want, rtol=1e-12, atol=1e-12)


def test_units_refitted_after_the_crowds_see_each_emitters_light_once(astig, monkeypatch):
    """After the crowds are solved, a kept unit is refitted with the kept units' and the
    crowds' emitters: a promoted unit's emitter is the crowd's now and is not counted
    twice (its first fit and the crowd's would both add light to the unit's window)."""
    from sparseloc.solvers import two_tier

    work, _, solver = astig
    truth = [[3000.0, 3000.0, 0.0, 6000.0], [3300.0, 3050.0, 200.0, 6000.0],
             [3100.0, 5000.0, -300.0, 3000.0]]  # fmt: skip
    seen = []
    refit = two_tier._Tier1.refit

    def spy(self, unit, others):
        seen.append(np.vstack([np.reshape(o, (-1, 4)) for o in others] or [np.zeros((0, 4))]))
        return refit(self, unit, others)

    monkeypatch.setattr(two_tier._Tier1, "refit", spy)
    counts = TierCounts()
    fit = _solve(solver, _frame(work, truth, seed=0), counts)
    assert counts.frames_with_crowds == 1 and counts.singles == 1  # the pair, and one unit
    assert len(fit.emitters) == 3
    last = seen[-1]  # the refit with the crowds' light
    assert len(last) == 2  # the crowd's two emitters, each once
    d = np.hypot(*(last[:, None, :2] - last[None, :, :2]).transpose(2, 0, 1))
    assert np.min(d[np.triu_indices(len(last), 1)]) > 100.0


def test_an_emitter_hidden_by_the_detections_neighbour_suppression_is_a_unit(astig):
    """A dimmer emitter about a micrometre from a brighter one gives no local maximum of its
    own in the detection (the brighter one's correlation is larger around it); the peak the
    units leave unexplained is tried as a unit, and both are fitted alone (neither goes to the
    crowds)."""
    work, _, solver = astig
    truth = [[3000.0, 3000.0, 300.0, 5000.0], [3000.0, 3850.0, -200.0, 1200.0]]
    planes = detection_planes(solver.templates)
    for seed in range(3):
        frame = _frame(work, truth, seed=seed)
        assert len(detect_candidates(frame, 10.0, planes, threshold=5.0)) == 1  # hidden
        counts = TierCounts()
        fit = _solve(solver, frame, counts)
        em = fit.emitters.as_array().reshape(-1, 4)
        assert counts.singles == 2 and counts.promoted == 0  # both fitted alone
        assert len(em) == 2
        for t in truth:
            assert np.min(np.hypot(em[:, 0] - t[0], em[:, 1] - t[1])) < 40.0


def test_a_unit_started_from_unexplained_light_must_pass_the_addition_bar(astig):
    """A start from the light the units leave unexplained is an addition: it is kept only
    above the count selection's addition threshold, as the frame solver's additions are; a
    detected start, as the pursuit's, above the lower bar of an emitter alone. An emitter
    of 300 photons on a background of 100 lies between the two."""
    from sparseloc.solvers.two_tier import _Tier1

    work, _, solver = astig
    a = np.array([[3200.0, 3200.0, 0.0, 300.0]])
    bg = np.full(SHAPE, 100.0)
    for seed in range(3):
        f = _frame(work, a, seed=seed, background=100.0)
        tier = _Tier1(f, bg, work, solver.fit_kwargs(), 1.0, np.zeros(SHAPE), 0.15)
        assert len(tier.fit(a).rows) == 1
        assert len(tier.fit(a, added=True).rows) == 0


def test_a_units_misfit_reads_the_models_error_table(astig):
    """A calibration's error table says where its model errs (a double helix errs most in its
    dim wings, where ``(e * signal)^2`` is small). The misfit that promotes a unit must use
    it, as the count selection's allowance does: else a unit whose data hold only that
    known error looks like two emitters and goes to the crowds."""
    import copy

    from sparseloc.psf.spline import SplinePSF
    from sparseloc.solvers.two_tier import _Tier1

    work, _, solver = astig
    model = copy.copy(work)
    photons, c = 3000.0, 4e-6  # error variance per photon squared on each pixel of the table
    lo, hi = work.z_range
    model.error_table = SplinePSF(
        c * np.ones((8, 21, 21)), PX, np.linspace(lo, hi, 8), normalise=False, name="error"
    )
    model.model_error = 0.0  # the scalar says nothing: the table alone holds the error
    a = np.array([[3200.0, 3200.0, 0.0, photons]])
    error_var = model.error_table.render(a[:, 0], a[:, 1], a[:, 2], a[:, 3] ** 2, SHAPE, PX)
    assert 20.0 < error_var.max() < 60.0  # a few times the background's noise variance
    scores = []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        f = _frame(work, a, seed=seed) + rng.normal(0.0, np.sqrt(np.maximum(error_var, 0.0)))
        f = np.maximum(f, 0.0)  # photon counts (a pixel below zero is rare here)
        tier = _Tier1(
            f, np.full(SHAPE, 10.0), model, solver.fit_kwargs(), 1.0, np.zeros(SHAPE), 0.15
        )
        scores.append(tier.fit(a).misfit)
    assert abs(np.mean(scores)) < 1.0 and max(scores) < 3.0


def test_a_units_removal_test_and_misfit_read_one_rendering_of_the_error(astig, monkeypatch):
    """The removal test's allowance and the promotion's misfit use the same model error of
    the same fit: the error table is rendered once for them, not once each."""
    import copy

    from sparseloc.psf.spline import SplinePSF
    from sparseloc.solvers.two_tier import _Tier1

    work, _, solver = astig
    model = copy.copy(work)
    lo, hi = work.z_range
    model.error_table = SplinePSF(
        1e-6 * np.ones((8, 21, 21)), PX, np.linspace(lo, hi, 8), normalise=False, name="error"
    )
    calls = []
    render = model.error_table.render
    monkeypatch.setattr(
        model.error_table, "render", lambda *a, **k: calls.append(1) or render(*a, **k)
    )
    a = np.array([[3200.0, 3200.0, 0.0, 3000.0]])
    tier = _Tier1(
        _frame(work, a), np.full(SHAPE, 10.0), model, solver.fit_kwargs(), 1.0,
        np.zeros(SHAPE), 0.0,
    )  # fmt: skip
    unit = tier.fit(a)
    assert len(unit.rows) == 1 and np.isfinite(unit.misfit)
    assert len(calls) == 1
