"""Bright emitters' halos: their light beyond the frame solver's reach is known light."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from sparseloc.config import LocalizeParams
from sparseloc.evaluate import match_localizations
from sparseloc.pipeline import _FrameSolver, addition_bar, check_frame, localize, work_model_for
from sparseloc.psf import make_psf
from sparseloc.psf.spline import SplinePSF
from sparseloc.solvers.halo import Halo, halo_of
from sparseloc.solvers.two_tier import detection_planes

PX = 100.0
SHAPE = (72, 72)
BRIGHT = 250_000.0


@pytest.fixture(scope="module")
def dh():
    """The pupil double helix, its run's spline table and the halo measured on the pupil
    beyond the table's box."""
    model = make_psf("dh")
    p = LocalizeParams(pixel_size=PX)
    work = work_model_for(model, p)
    solver = _FrameSolver(work, p, SHAPE)
    planes = detection_planes(solver.templates)
    return model, work, p, solver, Halo.measure(model, work, PX, planes)


def _noise(background=10.0):
    return np.full(SHAPE, background)


def test_the_halo_is_the_models_light_beyond_the_reach(dh):
    """The rendered halo is the pupil model's image less the spline table's: nothing
    where the table holds the image, all of it beyond the table's box."""
    model, work, p, _, halo = dh
    em = np.array([[3600.0, 3600.0, 400.0, BRIGHT]])
    thr = p.min_snr
    light = halo_of(halo, model, work, em, _noise(), PX, thr)
    assert light is not None
    full = model.render(*em.T, SHAPE, PX)
    table = work.render(*em.T, SHAPE, PX)
    # the table's box: from the pixel before its extent begins
    ry, _ = work.zero_beyond(PX)  # a square table
    lo, n = int(np.floor((3600 - ry) / PX - 0.5)), int(np.floor(2 * ry / PX)) + 2
    inner = np.zeros(SHAPE, bool)
    inner[lo : lo + n, lo : lo + n] = True
    assert np.all(table[~inner] == 0)
    np.testing.assert_allclose(light, full - table, rtol=1e-9, atol=1e-9)
    # within 20 px the table holds the image to a few photons in 250,000
    core = np.zeros(SHAPE, bool)
    core[16:56, 16:56] = True
    assert np.abs(light[core]).max() < 5.0
    ring = ~inner & (full > 1.0)
    assert ring.sum() > 500  # tens of photons per pixel in rings far beyond the table


def test_ordinary_emitters_have_no_halo(dh):
    """At 2,000 photons on a background of 10 the halo is far below the detection."""
    model, work, p, _, halo = dh
    em = np.array([[3600.0, 3600.0, z, 2000.0] for z in (-900.0, 0.0, 900.0)])
    assert halo_of(halo, model, work, em, _noise(), PX, p.min_snr) is None


def test_a_spline_table_has_no_halo(dh):
    """A spline table (a bead calibration) renders nothing beyond its own box: no halo,
    however bright the emitter."""
    _, work, p, solver, _ = dh
    halo = Halo.measure(work, work, PX, detection_planes(solver.templates))
    assert halo.response.max() == 0
    em = np.array([[3600.0, 3600.0, 0.0, 1e7]])
    assert halo_of(halo, work, work, em, _noise(), PX, p.min_snr) is None


@pytest.mark.parametrize("given", ["pupil", "table"])
def test_a_bright_emitter_leaves_no_ring_of_false_emitters(dh, given):
    """A 250,000-photon double helix among ordinary emitters: its halo (up to a quarter of
    its light lies beyond the spline table) left unknown reads as a ring of emitters 2-3.5
    um around it; known, it leaves none."""
    model, table, p, _, _ = dh
    rng = np.random.default_rng(3)
    ordinary = np.column_stack(
        [
            rng.uniform(500, 6700, 8),
            rng.uniform(500, 6700, 8),
            rng.uniform(-800, 800, 8),
            rng.uniform(2000, 4000, 8),
        ]
    )
    bright = np.array([[3650.0, 3550.0, -450.0, BRIGHT]])
    truth = np.vstack([ordinary, bright])
    truth = truth[(np.hypot(truth[:, 0] - 3650, truth[:, 1] - 3550) > 1000) | (truth[:, 3] > 1e5)]
    mu = 10.0 + model.render(*truth.T, SHAPE, PX)
    frame = rng.poisson(mu).astype(float)[None]
    run_model = model if given == "pupil" else table  # a table made once, as the docs suggest
    locs = localize(frame, run_model, p, check=False).table
    ok = locs[locs["flag"] == "ok"]
    t = {"frame": 0, "x_nm": truth[:, 0], "y_nm": truth[:, 1], "z_nm": truth[:, 2]}
    m = match_localizations(ok, pd.DataFrame(t))
    assert len(ok) - len(m) <= 1
    assert len(m) >= len(truth) - 1
    # the frame check knows the same halo: no light left that an emitter would explain
    check = check_frame(frame, 0, locs, run_model, p)
    assert np.all(check.unexplained_snr < np.sqrt(addition_bar(p)))


def test_a_calibration_says_when_light_beyond_its_roi_would_stand_out(dh):
    """A table made from data (a bead calibration) holds no light beyond its ROI: a run says
    how many localizations are bright enough for that light to stand above the noise."""
    model, table, p, _, _ = dh
    work = SplinePSF(
        table.stack, PX, table.z, centre=table.centre, normalise=False, oversample=table.oversample
    )
    rng = np.random.default_rng(5)
    em = np.array([[3650.0, 3550.0, 200.0, BRIGHT], [1200.0, 1300.0, -300.0, 3000.0]])
    frame = rng.poisson(10.0 + model.render(*em.T, SHAPE, PX)).astype(float)[None]
    bright = localize(frame, work, p).metadata.get("beyond_roi")
    assert bright is not None and bright["count"] == 1
    assert bright["roi_half_nm"] == pytest.approx(work.roi_half(PX))
    dim = rng.poisson(10.0 + model.render(*em[1:].T, SHAPE, PX)).astype(float)[None]
    assert "beyond_roi" not in localize(dim, work, p).metadata
    # the pupil model and its table render that light: nothing to say
    assert "beyond_roi" not in localize(frame, model, p).metadata
    assert "beyond_roi" not in localize(frame, table, p).metadata
