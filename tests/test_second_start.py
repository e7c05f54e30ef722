"""The frame solver's second start: L1 deconvolution, the fit from it, the likelier per region."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.psf import make_psf
from sparseloc.solvers import Emitters
from sparseloc.solvers.frame import frame_fit, frame_templates
from sparseloc.solvers.frame_compose import crowded_boxes, likelier_per_region
from sparseloc.solvers.frame_l1 import Convolver, l1_starts, l1_templates, tiled_l1_starts
from sparseloc.solvers.frame_windows import inside

PX = 100.0
TRUTH = np.array(
    [
        [1250.0, 1350.0, -200.0, 3000.0],
        [5150.0, 1450.0, 100.0, 2500.0],
        [3050.0, 4150.0, 300.0, 3500.0],
        [8350.0, 8650.0, 0.0, 3000.0],
        [4650.0, 8250.0, -300.0, 2800.0],
    ]
)


@pytest.fixture(scope="module")
def analytic():
    return make_psf("dh-analytic")


@pytest.fixture(scope="module")
def l1(analytic):
    return l1_templates(analytic, frame_templates(analytic, PX, dxy=50.0, dz=100.0))


def frame_of(model, truth, shape, background=10.0, seed=0):
    mu = background + model.render(*np.atleast_2d(truth).T, shape, PX)
    return np.random.default_rng(seed).poisson(mu).astype(float)


def fit_options(templates):
    r50 = templates.core_radius
    return dict(
        pixel_size=PX,
        group_distance=2 * r50 * PX,
        pad=int(np.ceil(templates.radius90)),
        reach=0.5 * templates.images.shape[-1] * PX,
    )


def test_the_convolver_is_the_dictionary_and_its_adjoint():
    rng = np.random.default_rng(1)
    t = rng.random((3, 7, 7))
    conv = Convolver(t, (20, 24))
    x, img = rng.random((3, 20, 24)), rng.random((20, 24))
    assert np.isclose(np.sum(conv.forward(x) * img), np.sum(x * conv.adjoint(img)), rtol=1e-5)
    delta = np.zeros((3, 20, 24))
    delta[1, 5, 6] = 2.0
    out = conv.forward(delta)
    assert np.allclose(out[2:9, 3:10], 2.0 * t[1], atol=1e-5)
    assert np.isclose(out.sum(), 2.0 * t[1].sum(), rtol=1e-5)  # all inside the frame


def test_the_convolver_is_exact_with_templates_nearly_as_wide_as_the_frame():
    # its circular FFTs are shorter than the linear results: what wraps must fall outside
    # the frame's pixels (direct sums as the reference)
    from scipy.signal import convolve2d, correlate2d

    rng = np.random.default_rng(2)
    for width in (15, 14):  # odd and even
        t = rng.random((2, width, width))
        conv = Convolver(t, (12, 20))
        assert conv.fshape[0] < 12 + width - 1  # shorter than the linear length
        x, img = rng.random((2, 12, 20)), rng.random((12, 20))
        fwd = conv.forward(x)
        if width % 2:
            want = sum(convolve2d(x[j], t[j], mode="same") for j in range(2))
            assert np.allclose(fwd, want, rtol=1e-4, atol=1e-4)
            want = np.stack([correlate2d(img, t[j], mode="same") for j in range(2)])
            assert np.allclose(conv.adjoint(img), want, rtol=1e-4, atol=1e-4)
        # the adjoint is the forward's, whatever the width
        assert np.isclose(np.sum(fwd * img), np.sum(x * conv.adjoint(img)), rtol=1e-5)


def test_the_l1_dictionary_has_one_phase_and_planes_twice_as_far_apart(analytic, l1):
    pursuit = frame_templates(analytic, PX, dxy=50.0, dz=100.0)
    assert np.all(l1.dx == 0) and np.all(l1.dy == 0)
    assert np.isclose(np.min(np.diff(np.unique(l1.z))), 200.0)
    assert l1.z.min() == pursuit.z.min() and l1.z.max() == pursuit.z.max()
    assert l1.images.shape[-1] == pursuit.images.shape[-1]


def test_l1_starts_find_separated_emitters_and_nothing_in_background(analytic, l1):
    frame = frame_of(analytic, TRUTH, (96, 96), seed=11)
    r50 = frame_templates(analytic, PX, dxy=50.0, dz=100.0).typical_radius
    found = l1_starts(frame, 10.0, l1, peak_radius=r50).as_array()
    strong = found[found[:, 3] > 1000.0]
    assert len(strong) == len(TRUTH)
    d = np.hypot(strong[:, None, 0] - TRUTH[None, :, 0], strong[:, None, 1] - TRUTH[None, :, 1])
    assert np.all(d.min(axis=0) < 100.0)
    dz = np.abs(strong[np.argmin(d, axis=0), 2] - TRUTH[:, 2])
    assert np.all(dz < 200.0)
    empty = np.random.default_rng(2).poisson(np.full((64, 64), 10.0)).astype(float)
    assert len(l1_starts(empty, 10.0, l1, peak_radius=r50)) == 0


def test_tiled_l1_starts_find_what_the_whole_frame_finds(analytic, l1):
    frame = frame_of(analytic, TRUTH, (96, 96), seed=11)
    r50 = frame_templates(analytic, PX, dxy=50.0, dz=100.0).typical_radius
    whole = tiled_l1_starts(frame, 10.0, l1, peak_radius=r50).as_array()
    cache: dict = {}
    tiled = tiled_l1_starts(
        frame, 10.0, l1, peak_radius=r50, max_pixels=1000, core=40, convolvers=cache
    ).as_array()
    assert len(cache) == 1  # one tile shape serves them all
    a, b = (v[v[:, 3] > 1000.0] for v in (whole, tiled))
    a, b = (v[np.lexsort(v[:, :2].T)] for v in (a, b))
    assert len(a) == len(b) == len(TRUTH)
    assert np.allclose(a[:, :3], b[:, :3], atol=30.0)


def test_only_the_crowded_parts_of_a_frame_get_a_second_start(analytic):
    t = frame_templates(analytic, PX, dxy=50.0, dz=100.0)
    frame = frame_of(analytic, TRUTH, (96, 96), seed=3)
    alone = frame_fit(
        frame, analytic, Emitters.from_array(TRUTH), background=10.0, **fit_options(t)
    )
    assert len(alone.emitters) == len(TRUTH)
    assert crowded_boxes(alone, frame.shape, PX, 7) == []
    pair = np.vstack([TRUTH, TRUTH[:1] + np.array([300.0, 0.0, 0.0, 0.0])])
    frame2 = frame_of(analytic, pair, (96, 96), seed=4)
    two = frame_fit(frame2, analytic, Emitters.from_array(pair), background=10.0, **fit_options(t))
    boxes = crowded_boxes(two, frame2.shape, PX, 7)
    assert len(boxes) == 1
    held = inside(two.emitters.as_array(), boxes[0], PX)
    near_pair = np.hypot(*(two.emitters.as_array()[:, :2] - [1400.0, 1350.0]).T) < 500.0
    assert np.array_equal(held, near_pair) and held.sum() == 2


def test_the_frame_solver_refits_a_crowd_from_the_deconvolution_in_frame_coordinates(analytic):
    """The pipeline's second start on a frame with a pair and lone emitters: the lone ones
    stay as the first fit has them, the pair is found where it is."""
    from sparseloc.config import LocalizeParams
    from sparseloc.pipeline import _FrameSolver

    pair = np.array([[6000.0, 5000.0, 0.0, 4000.0], [6400.0, 5000.0, 200.0, 4000.0]])
    truth = np.vstack([TRUTH, pair])
    frame = frame_of(analytic, truth, (96, 96), seed=6)
    solver = _FrameSolver(analytic, LocalizeParams(pixel_size=PX), frame.shape)
    bg = np.full(frame.shape, 10.0)
    first = frame_fit(
        frame, analytic, Emitters.from_array(truth), background=bg, **solver.fit_kwargs()
    )
    out = solver.second(frame, bg, first).emitters.as_array()
    a = first.emitters.as_array()
    lone = ~np.isin(
        np.arange(len(a)), np.nonzero(np.hypot(a[:, 0] - 6200.0, a[:, 1] - 5000.0) < 1000)[0]
    )
    for row in a[lone]:
        assert np.any(np.all(out == row, axis=1))
    found = out[np.hypot(out[:, 0] - 6200.0, out[:, 1] - 5000.0) < 1000.0]
    d = np.hypot(found[:, None, 0] - pair[None, :, 0], found[:, None, 1] - pair[None, :, 1])
    assert len(found) == 2 and np.all(d.min(axis=0) < 60.0)


@pytest.mark.parametrize("order", ["wrong first", "right first"])
def test_the_likelier_arrangement_of_a_region_is_kept(analytic, order):
    """Two emitters 500 nm apart: one fit holds them as one emitter between them, the other
    as the two; whichever comes first, the two are kept, and an emitter only one fit has
    stays as that fit has it."""
    t = frame_templates(analytic, PX, dxy=50.0, dz=100.0)
    pair = np.array([[3000.0, 3000.0, 0.0, 4000.0], [3500.0, 3000.0, 200.0, 4000.0]])
    lone = np.array([[8000.0, 8000.0, -100.0, 3000.0]])
    frame = frame_of(analytic, np.vstack([pair, lone]), (96, 96), seed=5)
    opts = {**fit_options(t), "count_selection": False}
    merged = np.array([[3250.0, 3000.0, 100.0, 8000.0]])
    wrong = frame_fit(
        frame, analytic, Emitters.from_array(np.vstack([merged, lone])), background=10.0, **opts
    )
    right = frame_fit(frame, analytic, Emitters.from_array(pair), background=10.0, **opts)
    assert len(wrong.emitters) == 2 and len(right.emitters) == 2  # right lacks the lone one
    first, second = (wrong, right) if order == "wrong first" else (right, wrong)
    out = likelier_per_region(
        frame,
        np.full(frame.shape, 10.0),
        first,
        second,
        analytic,
        pixel_size=PX,
        group_distance=opts["group_distance"],
        pad=opts["pad"],
        penalty=80.0,
        fit_kwargs={"noise": "poisson"},
    )
    arr = out.emitters.as_array()
    near_pair = arr[np.hypot(arr[:, 0] - 3250.0, arr[:, 1] - 3000.0) < 1000.0]
    assert len(near_pair) == 2
    d = np.hypot(near_pair[:, None, 0] - pair[None, :, 0], near_pair[:, None, 1] - pair[None, :, 1])
    assert np.all(d.min(axis=0) < 60.0)
    lone_kept = arr[np.hypot(arr[:, 0] - 8000.0, arr[:, 1] - 8000.0) < 200.0]
    assert len(lone_kept) == (1 if order == "wrong first" else 0)
    assert len(out.sigma) == len(out.flags) == len(out.group) == len(arr)


def test_a_region_too_costly_to_compare_keeps_the_first_fit(analytic, monkeypatch):
    """A region whose joint fit would hold more Jacobian entries than the bound (a wrong PSF's
    hundreds of emitters over a whole frame: gigabytes) is not fitted: the first fit stays."""
    import sparseloc.solvers.frame_compose as compose

    pair = np.array([[3000.0, 3000.0, 0.0, 4000.0], [3500.0, 3000.0, 200.0, 4000.0]])
    frame = frame_of(analytic, pair, (64, 64), seed=5)
    first = _frame_fit_of([[3250.0, 3000.0, 100.0, 8000.0]])
    second = _frame_fit_of(pair)
    fits = []
    monkeypatch.setattr(compose, "fit_emitters", lambda *a, **k: fits.append(1))
    monkeypatch.setattr(compose, "REGION_MAX_ENTRIES", 9 * 10 * 10)  # 2 emitters, 10 x 10 px
    out = likelier_per_region(
        frame, np.full(frame.shape, 10.0), first, second, analytic, pixel_size=PX,
        group_distance=1000.0, pad=5, penalty=80.0, fit_kwargs={"noise": "poisson"},
    )  # fmt: skip
    assert fits == [] and np.array_equal(out.emitters.as_array(), first.emitters.as_array())


def _frame_fit_of(arr):
    from sparseloc.solvers.frame import FrameFit

    arr = np.asarray(arr, float)
    k = len(arr)
    return FrameFit(
        Emitters.from_array(arr),
        np.ones((k, 4)),
        np.full(k, 10.0),
        np.ones(k),
        np.full(k, "ok", dtype="<U16"),
        np.zeros(k, dtype=np.int64),
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_where_each_fit_is_half_right_the_union_is_kept(analytic, seed):
    """Two pairs in one region: the first fit holds the upper pair and the lower one merged,
    the second the reverse. Neither alone is right; their union, settled by the count
    selection, holds the four true emitters."""
    upper = np.array([[3000.0, 3000.0, 0.0, 4000.0], [3600.0, 3000.0, 200.0, 4000.0]])
    lower = np.array([[3100.0, 3900.0, -200.0, 4000.0], [3700.0, 3900.0, 100.0, 4000.0]])
    upper_merged = np.array([[3300.0, 3000.0, 100.0, 8000.0]])
    lower_merged = np.array([[3400.0, 3900.0, -50.0, 8000.0]])
    truth = np.vstack([upper, lower])
    frame = frame_of(analytic, truth, (64, 64), seed=seed)
    out = likelier_per_region(
        frame,
        np.full(frame.shape, 10.0),
        _frame_fit_of(np.vstack([upper, lower_merged])),
        _frame_fit_of(np.vstack([upper_merged, lower])),
        analytic,
        pixel_size=PX,
        group_distance=1000.0,
        pad=7,
        penalty=80.0,
        fit_kwargs={"noise": "poisson"},
    )
    arr = out.emitters.as_array()
    d = np.hypot(arr[:, None, 0] - truth[None, :, 0], arr[:, None, 1] - truth[None, :, 1])
    assert len(arr) == 4 and np.all(d.min(axis=0) < 30.0)
    assert len(out.sigma) == len(out.flags) == len(out.group) == 4


def test_the_second_start_is_a_parameter_of_the_run():
    from sparseloc.config import LocalizeParams
    from sparseloc.pipeline import _FrameSolver

    model = make_psf("dh-analytic")
    on = _FrameSolver(model, LocalizeParams(pixel_size=PX), (48, 48))
    off = _FrameSolver(model, LocalizeParams(pixel_size=PX, second_start=False), (48, 48))
    assert on.l1 is not None and off.l1 is None


def test_tied_maxima_give_one_start():
    """A lone atom's 3 x 3 sum is flat: every pixel of it tied as a maximum, and rounding
    decided how many starts came from one place."""
    from sparseloc.solvers.frame_l1 import _separated_maxima

    total = np.zeros((20, 20))
    total[4:7, 4:7] = 500.0  # a flat plateau: one peak, its first pixel
    total[14, 14] = total[14, 16] = 300.0  # two equal maxima 2 px apart: one
    total[15, 4] = 50.0  # below the floor
    peaks = _separated_maxima(total, 5, 100.0)
    assert peaks.tolist() == [[4, 4], [14, 14]]
    total[14, 16] += 1e-9  # rounding: the other of the two, still one
    assert _separated_maxima(total, 5, 100.0).tolist() == [[4, 4], [14, 16]]
    total[14, 19] = 200.0  # outside the window of both: a peak of its own
    assert len(_separated_maxima(total, 5, 100.0)) == 3
