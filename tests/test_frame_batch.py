"""Whole-frame fits in lockstep over frames, with batched maximum-likelihood fits.

The reference is :func:`frame_fit`: where the colouring leaves the order of the groups as
``frame_fit`` visits them (one colour, or one group per colour in order of brightness), the
two must agree to rounding; elsewhere both must find the truth about as well. The PSF is a
spline table of the cheap analytic double helix (40 nm planes), as in ``test_batch_fit.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

import test_frame  # the keywords of the per-group solver's tests (tests/ is on sys.path)
from sparseloc.psf import make_psf
from sparseloc.psf.spline import SplinePSF
from sparseloc.solvers import Emitters
from sparseloc.solvers.batch_fit import fit_batch
from sparseloc.solvers.frame import _groups, frame_fit, frame_pursuit, frame_templates
from sparseloc.solvers.frame_batch import _box, _colours, frame_fit_batch

PX = 100.0  # nm

# Seven emitters in a 40 x 40 frame: two overlapping pairs (360-450 nm apart) and three alone.
TRUTH = np.array(
    [
        [1000.0, 1100.0, -300.0, 3000.0],
        [1350.0, 1300.0, 200.0, 2500.0],
        [2800.0, 900.0, 500.0, 3000.0],
        [2600.0, 2900.0, -600.0, 2000.0],
        [2950.0, 3150.0, 0.0, 3500.0],
        [900.0, 3000.0, 700.0, 2500.0],
        [2000.0, 2000.0, -100.0, 3000.0],
    ]
)


@pytest.fixture(scope="module")
def spline() -> SplinePSF:
    return SplinePSF.from_model(make_psf("dh-analytic"), PX, roi=31, z_step=40.0)


@pytest.fixture(scope="module")
def templates(spline):
    return frame_templates(spline, PX, dxy=50.0, dz=120.0)


def poisson_frame(model, truth, shape, background=10.0, seed=0):
    t = np.atleast_2d(truth)
    mu = model.render(t[:, 0], t[:, 1], t[:, 2], t[:, 3], shape, PX) + background
    return np.random.default_rng(seed).poisson(mu).astype(float)


def fit_kwargs(templates):
    """tests/test_frame.py's keywords (here 500 nm groups, 3 px pads, 750 nm reach)."""
    assert PX == test_frame.PX
    return test_frame.frame_fit_kwargs(templates)


def matched_errors(est, truth, tol=150.0):
    """Lateral error (nm) of the nearest estimate to each true emitter (inf beyond tol)."""
    if len(est) == 0:
        return np.full(len(truth), np.inf)
    d = np.hypot(est[:, None, 0] - truth[None, :, 0], est[:, None, 1] - truth[None, :, 1])
    err = d.min(axis=0)
    return np.where(err <= tol, err, np.inf)


def assert_same(a, b, tol):
    """Two FrameFits alike: emitters (nm, photons) within ``tol``, the rest to rounding."""
    ea, eb = a.emitters.as_array(), b.emitters.as_array()
    assert ea.shape == eb.shape
    assert np.max(np.abs(ea - eb), initial=0.0) <= tol
    assert np.allclose(a.sigma, b.sigma, rtol=1e-5, atol=1e-6, equal_nan=True)
    assert np.allclose(a.background, b.background, rtol=1e-6, atol=1e-8)
    assert np.allclose(a.gof, b.gof, rtol=1e-6, atol=1e-8)
    assert np.array_equal(a.flags, b.flags)
    assert np.array_equal(a.group, b.group)


@pytest.fixture(scope="module")
def crowded(spline, templates):
    frame = poisson_frame(spline, TRUTH, (40, 40), seed=1)
    return frame, frame_pursuit(frame, 10.0, templates)


def test_finds_the_emitters_as_well_as_frame_fit(spline, templates, crowded):
    frame, start = crowded
    kw = fit_kwargs(templates)
    ref = frame_fit(frame, spline, start, **kw)
    (got,) = frame_fit_batch([frame], spline, [start], **kw)
    assert len(start) > len(TRUTH)  # the pursuit's start has extras: count selection works
    assert abs(len(got.emitters) - len(ref.emitters)) <= 1
    assert abs(len(got.emitters) - len(TRUTH)) <= 1
    err_ref = matched_errors(ref.emitters.as_array(), TRUTH)
    err_got = matched_errors(got.emitters.as_array(), TRUTH)
    assert np.all(np.isfinite(err_got))  # every true emitter found
    assert np.all(err_got < 60.0)
    assert np.mean(err_got) <= np.mean(err_ref) + 15.0
    k = len(got.emitters)
    assert got.sigma.shape == (k, 4) and np.all(got.sigma > 0)
    assert got.background.shape == got.gof.shape == got.flags.shape == got.group.shape == (k,)
    assert np.all(np.abs(got.background - 10.0) < 2.0)
    assert np.all((got.gof > 0.5) & (got.gof < 2.0))
    e = got.emitters
    assert np.all((e.x >= 0) & (e.x < 40 * PX) & (e.y >= 0) & (e.y < 40 * PX))


@pytest.mark.parametrize("noise", ["poisson", "emccd", "scmos"])
def test_one_colour_equals_frame_fit(spline, templates, noise):
    kw = fit_kwargs(templates)
    kw["noise"] = noise
    if noise == "scmos":  # a read-noise map, cropped to each window
        kw["read_variance"] = np.random.default_rng(0).uniform(1.0, 30.0, (40, 40))
    # Four emitters far apart: their windows are out of each other's reach, one colour.
    truth = np.array(
        [
            [700.0, 700.0, -200.0, 3000.0],
            [3300.0, 750.0, 300.0, 2500.0],
            [650.0, 3300.0, 600.0, 2000.0],
            [3350.0, 3250.0, -500.0, 3500.0],
        ]
    )
    frame = poisson_frame(spline, truth, (40, 40), seed=2)
    start = truth + np.array([40.0, -30.0, 80.0, -300.0])
    em = start.copy()
    groups = _groups(em[:, :2], kw["group_distance"])
    boxes = [_box(em[g], 40, 40, PX, kw["pad"]) for g in groups]
    assert len(groups) == 4
    assert np.all(_colours(em, groups, boxes, PX, kw["reach"]) == 0)
    opts = dict(sweeps=1, count_selection=False, z_flip=0, **kw)
    ref = frame_fit(frame, spline, Emitters.from_array(start), **opts)
    if noise == "scmos":  # the map changes the fit: a batch that dropped it would differ
        plain = frame_fit(
            frame,
            spline,
            Emitters.from_array(start),
            **{**opts, "noise": "poisson", "read_variance": None},
        )
        assert np.max(np.abs(plain.emitters.as_array() - ref.emitters.as_array())) > 0.1
    (got,) = frame_fit_batch([frame], spline, [Emitters.from_array(start)], **opts)
    assert_same(got, ref, 1e-3)
    # the fits moved the emitters (a start returned unchanged would also agree), brightest
    # group first
    moved = got.emitters.as_array()[:, :2] - start[np.argsort(-start[:, 3]), :2]
    assert np.all(np.hypot(*moved.T) > 10.0)
    assert np.all(matched_errors(got.emitters.as_array(), truth) < 40.0)


def test_one_group_per_colour_equals_frame_fit_with_everything_on(spline, templates):
    """Every group within reach of every other: one group per colour, in frame_fit's order,
    so the batched sweeps are frame_fit's (count selection, z flips, several sweeps)."""
    kw = {**fit_kwargs(templates), "reach": 3000.0}
    truth = np.array(
        [
            [800.0, 900.0, -850.0, 3000.0],  # near the end of the z range: z flips tried
            [1150.0, 1100.0, 300.0, 2500.0],
            [2200.0, 800.0, 100.0, 2000.0],
            [1500.0, 2300.0, 800.0, 3500.0],
        ]
    )
    frame = poisson_frame(spline, truth, (32, 32), seed=3)
    start = frame_pursuit(frame, 10.0, templates)
    em = start.as_array()
    groups = _groups(em[:, :2], kw["group_distance"])
    groups.sort(key=lambda g: -em[g, 3].sum())
    boxes = [_box(em[g], 32, 32, PX, kw["pad"]) for g in groups]
    assert len(groups) >= 3
    assert np.array_equal(_colours(em, groups, boxes, PX, kw["reach"]), np.arange(len(groups)))
    ref = frame_fit(frame, spline, start, skip_tolerance=0.0, **kw)
    (got,) = frame_fit_batch([frame], spline, [start], **kw)
    assert_same(got, ref, 1e-3)


def test_count_changes_and_z_flips_as_frame_fit(spline, templates):
    """Starts that need every rule: a pair at the wrong end of the z range, a pair started as
    one emitter (with ``max_emitters=1``: only the allowance of two more lets it grow), a
    spurious weak emitter; one group per colour, so the result is frame_fit's."""
    kw = {**fit_kwargs(templates), "reach": 3000.0, "max_emitters": 1}
    truth = np.array(
        [
            [800.0, 900.0, -850.0, 3000.0],
            [1150.0, 1150.0, -800.0, 2800.0],
            [2400.0, 800.0, 100.0, 3000.0],
            [2750.0, 1000.0, -300.0, 2500.0],
            [1600.0, 2500.0, 400.0, 3500.0],
        ]
    )
    frame = poisson_frame(spline, truth, (36, 36), seed=5)
    start = np.array(
        [
            [830.0, 870.0, 850.0, 3000.0],
            [1120.0, 1180.0, 800.0, 2800.0],
            [2450.0, 850.0, 0.0, 4500.0],
            [1600.0, 2450.0, 300.0, 3500.0],
            [1900.0, 2800.0, 0.0, 300.0],
        ]
    )
    ref = frame_fit(frame, spline, Emitters.from_array(start), skip_tolerance=0.0, **kw)
    (got,) = frame_fit_batch([frame], spline, [Emitters.from_array(start)], **kw)
    assert_same(got, ref, 1e-3)
    # the pair started as one emitter was found
    assert np.all(matched_errors(got.emitters.as_array(), truth[2:4]) < 40.0)


def test_lost_z_flips_are_not_tried_again(spline, templates, monkeypatch):
    """As frame_fit: a flip that lost is not tried again near where it lost; the same
    result with fewer fits than without that memory."""
    import sparseloc.solvers.frame_batch as fb

    kw = fit_kwargs(templates)
    truth = np.array([[1500.0, 1500.0, -880.0, 3000.0], [2700.0, 2600.0, 870.0, 2500.0]])
    frame = poisson_frame(spline, truth, (40, 40), seed=6)
    start = Emitters.from_array(truth + np.array([30.0, -30.0, 40.0, 200.0]))
    fitted = []

    def counting(windows, *args, **kwargs):
        fitted.append(len(windows))
        return fit_batch(windows, *args, **kwargs)

    monkeypatch.setattr(fb, "fit_batch", counting)
    (with_memory,) = frame_fit_batch([frame], spline, [start], sweeps=3, **kw)
    n_with = sum(fitted)
    fitted.clear()
    import sparseloc.solvers.frame as frame_mod

    monkeypatch.setattr(frame_mod, "FLIP_MEMORY_NM", (-1.0, -1.0))
    (without,) = frame_fit_batch([frame], spline, [start], sweeps=3, **kw)
    assert_same(with_memory, without, 1e-6)
    assert n_with < sum(fitted)


def test_frames_in_lockstep_do_not_mix(spline, templates, crowded):
    frame_a, start_a = crowded
    # another frame, of another shape, with emitters where frame A has none
    truth_b = np.array(
        [
            [1500.0, 700.0, 0.0, 3000.0],
            [1800.0, 900.0, 400.0, 2500.0],
            [700.0, 2600.0, -500.0, 3000.0],
        ]
    )
    frame_b = poisson_frame(spline, truth_b, (36, 44), seed=4)
    start_b = frame_pursuit(frame_b, 10.0, templates)
    kw = fit_kwargs(templates)
    kw["background"] = [10.0, np.full((36, 44), 10.0)]
    both = frame_fit_batch([frame_a, frame_b], spline, [start_a, start_b], **kw)
    kw["background"] = 10.0
    (alone_a,) = frame_fit_batch([frame_a], spline, [start_a], **kw)
    (alone_b,) = frame_fit_batch([frame_b], spline, [start_b], **kw)
    assert_same(both[0], alone_a, 1e-6)
    assert_same(both[1], alone_b, 1e-6)
    assert len(alone_b.emitters) == len(truth_b)
    assert np.all(matched_errors(alone_b.emitters.as_array(), truth_b) < 60.0)


def test_torch_equals_numpy(spline, templates, crowded, torch_device):
    import torch

    frame, start = crowded
    kw = fit_kwargs(templates)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small tensors: threads only add overhead on a shared machine
    try:
        (got,) = frame_fit_batch([frame], spline, [start], device=torch_device, **kw)
    finally:
        torch.set_num_threads(threads)
    (ref,) = frame_fit_batch([frame], spline, [start], **kw)
    assert_same(got, ref, 1e-6)


def test_no_emitters(spline):
    frames = [np.full((20, 20), 10.0), np.full((24, 20), 10.0)]
    out = frame_fit_batch(
        frames,
        spline,
        [Emitters.empty(), Emitters.empty()],
        pixel_size=PX,
        background=10.0,
        group_distance=500.0,
        pad=3,
        reach=750.0,
    )
    assert len(out) == 2
    for fit in out:
        assert len(fit.emitters) == 0 and fit.sigma.shape == (0, 4) and fit.group.shape == (0,)


def test_arguments_are_checked(spline):
    kw = dict(pixel_size=PX, background=10.0, group_distance=500.0, pad=3, reach=750.0)
    frame = np.full((20, 20), 10.0)
    start = Emitters.from_array([[1000.0, 1000.0, 0.0, 2000.0]])
    with pytest.raises(ValueError, match="SplinePSF"):
        frame_fit_batch([frame], make_psf("dh-analytic"), [start], **kw)
    with pytest.raises(ValueError, match="frames"):
        frame_fit_batch([frame, frame], spline, [start], **kw)
    with pytest.raises(ValueError, match="background"):
        frame_fit_batch([frame], spline, [start], **{**kw, "background": [10.0, 10.0]})
    with pytest.raises(ValueError, match="colouring"):
        frame_fit_batch([frame], spline, [start], colouring="random", **kw)
    with pytest.raises(ValueError, match="2-D"):
        frame_fit_batch([frame[0]], spline, [start], **kw)


# --- the pipeline's batched path (LocalizeParams.device) ------------------------------------


def _small_movie(spline, n_frames=3, shape=(40, 40)):
    rng = np.random.default_rng(11)
    frames, truth = [], []
    for f in range(n_frames):
        t = TRUTH[rng.permutation(len(TRUTH))[:5]]
        frames.append(poisson_frame(spline, t, shape, seed=20 + f))
        truth.append(np.c_[np.full(len(t), f), t])
    import pandas as pd

    tab = pd.DataFrame(np.vstack(truth), columns=["frame", "x_nm", "y_nm", "z_nm", "photons"])
    tab["frame"] = tab["frame"].astype(int)
    return np.array(frames), tab


def test_localize_on_a_batched_device_finds_what_the_default_finds(spline):
    from sparseloc.evaluate import evaluate
    from sparseloc.pipeline import LocalizeParams, localize

    frames, truth = _small_movie(spline)
    done = []
    batched = localize(
        frames,
        spline,
        LocalizeParams(pixel_size=PX, device="numpy", background="spatial"),
        block=2,  # two blocks: 2 frames in lockstep, then 1
        progress=done.append,
    )
    default = localize(frames, spline, LocalizeParams(pixel_size=PX, background="spatial"))
    assert sum(done) == 3
    assert list(batched.table.columns) == list(default.table.columns)
    assert set(batched.table["frame"]) == {0, 1, 2}  # both blocks were solved
    assert batched.table.groupby("window_id")["frame"].nunique().max() == 1
    ev_b, ev_d = evaluate(batched.table, truth), evaluate(default.table, truth)
    assert ev_b.recall >= 0.9 and ev_b.precision >= 0.9
    assert abs(ev_b.jaccard - ev_d.jaccard) <= 10.0
    assert ev_b.rmse_lateral < 40.0
    assert batched.metadata["params"]["device"] == "numpy"


def test_batched_device_arguments_are_checked(spline, monkeypatch, tmp_path):
    import sys

    from sparseloc.pipeline import LocalizeParams, localize

    with pytest.raises(ValueError, match="frame solver"):
        LocalizeParams(pixel_size=PX, method="hybrid", device="cpu")
    for bad in ("tpu", "cuda:", "cuda:abc", "cuda:-1", "cuda:1 "):
        with pytest.raises(ValueError, match="numpy, cpu, cuda"):
            LocalizeParams(pixel_size=PX, device=bad)
    frames = np.full((2, 40, 40), 10.0)
    with pytest.raises(ValueError, match="one worker"):
        localize(frames, spline, LocalizeParams(pixel_size=PX, device="numpy"), workers=2)
    from sparseloc.distributed import localize_chunked

    with pytest.raises(ValueError, match="one after another"):
        localize_chunked(
            frames,
            spline,
            LocalizeParams(pixel_size=PX, device="numpy"),
            tmp_path / "run",
            scheduler="threads",
        )
    monkeypatch.setitem(sys.modules, "torch", None)  # as if PyTorch were not installed
    with pytest.raises(ValueError, match="needs PyTorch"):
        localize(frames, spline, LocalizeParams(pixel_size=PX, device="cpu"))


def test_a_cuda_device_without_a_gpu_is_refused():
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("a CUDA GPU is present")
    from sparseloc.pipeline import check_device

    with pytest.raises(ValueError, match="no CUDA GPU"):
        check_device("cuda:0")


def test_the_add_threshold_stays_on_the_photon_counting_scale(spline, templates, crowded):
    """With a quantum efficiency the likelihood ratios shrink by qe and so does the threshold
    (checked directly: on this frame no ratio lies between the two scales). Both solvers take
    qe and select the same emitters as for photon counts, at the same places."""
    from sparseloc.solvers.frame import ADD_THRESHOLD, add_threshold

    assert add_threshold(None, 0.5) == ADD_THRESHOLD / 2 and add_threshold(100.0, 0.8) == 80.0
    with pytest.raises(ValueError, match="qe"):
        add_threshold(None, 0.0)
    frame, start = crowded
    kw = fit_kwargs(templates)
    ref = frame_fit(frame, spline, start, **kw)
    for got in (
        frame_fit(frame, spline, start, **kw, qe=0.3),
        frame_fit_batch([frame], spline, [start], **kw, qe=0.3)[0],
    ):
        # the same emitters; positions within the fits' stopping tolerance (rounding differs)
        assert len(got.emitters) == len(ref.emitters)
        np.testing.assert_allclose(got.emitters.as_array(), ref.emitters.as_array(), atol=1.0)
