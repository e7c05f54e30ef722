"""Scenes, rendering and the high-level simulator: reproducibility and coordinate convention."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from sparseloc.camera import Camera, to_photons
from sparseloc.io.tiff import write_tiff
from sparseloc.psf import DoubleHelixMask, PupilPSF
from sparseloc.simulate import (
    PATCH_FRACTION,
    SCENES,
    Simulation,
    cluster_scene,
    filament_scene,
    render_movie,
    simulate,
    uniform_scene,
)

PX = 100.0
FOV = (6400.0, 6400.0)


@pytest.fixture(scope="module")
def clear_model():
    return PupilPSF()


@pytest.fixture(scope="module")
def dh():
    return PupilPSF(DoubleHelixMask(0.35), z_range=(-1000.0, 1000.0))


# -- scenes ---------------------------------------------------------------------------------
def test_uniform_scene_density_and_bounds():
    rng = np.random.default_rng(0)
    n_frames, density, margin = 3000, 1.0, 200.0
    df = uniform_scene(rng, n_frames, FOV, density, (-600.0, 400.0), (1000.0, 5000.0), margin)
    assert list(df.columns) == ["frame", "x_nm", "y_nm", "z_nm", "photons"]
    counts = df.groupby("frame").size().reindex(range(n_frames), fill_value=0)
    expected = density * (FOV[0] - 2 * margin) * (FOV[1] - 2 * margin) / 1e6  # 36 per frame
    assert abs(counts.mean() / expected - 1) < 0.02
    assert abs(counts.var() / expected - 1) < 0.1  # Poisson
    assert df["x_nm"].between(margin, FOV[0] - margin).all()
    assert df["y_nm"].between(margin, FOV[1] - margin).all()
    assert df["z_nm"].between(-600.0, 400.0).all()
    assert df["photons"].between(1000.0, 5000.0).all()
    assert df["frame"].is_monotonic_increasing and df["frame"].dtype == np.int64
    fixed = uniform_scene(np.random.default_rng(1), 5, FOV, 1.0, (0.0, 0.0), 2000.0)
    assert (fixed["photons"] == 2000.0).all() and (fixed["z_nm"] == 0.0).all()


def test_cluster_scene_stays_in_its_box():
    rng = np.random.default_rng(2)
    box = (800.0, 600.0, 400.0)
    df = cluster_scene(rng, 200, FOV, 7, box_nm=box, z_centre=100.0, photons=3000.0)
    assert (df.groupby("frame").size() == 7).all()
    g = df.groupby("frame")
    assert (g["x_nm"].max() - g["x_nm"].min() <= box[0]).all()
    assert (g["y_nm"].max() - g["y_nm"].min() <= box[1]).all()
    assert df["z_nm"].between(100.0 - 200.0, 100.0 + 200.0).all()
    assert df["x_nm"].between(0, FOV[0]).all() and df["y_nm"].between(0, FOV[1]).all()
    # the box moves from frame to frame
    assert g["x_nm"].mean().std() > 500.0
    with pytest.raises(ValueError, match="z range"):
        cluster_scene(rng, 2, FOV, 3, box_nm=box, z_centre=900.0, z_range=(-1000.0, 1000.0))
    with pytest.raises(ValueError, match="box_nm"):
        cluster_scene(rng, 2, FOV, 3, box_nm=(8000.0, 100.0, 100.0))


def test_filament_scene_blinks_within_z_range():
    rng = np.random.default_rng(3)
    n_frames = 300
    df = filament_scene(rng, n_frames, FOV, z_range=(-500.0, 500.0))
    assert "emitter_id" in df.columns
    assert df["z_nm"].between(-500.0, 500.0).all()
    assert df["x_nm"].between(0, FOV[0]).all() and df["y_nm"].between(0, FOV[1]).all()
    per_id = df.groupby("emitter_id")["frame"]
    assert (per_id.size() > 1).mean() > 0.5  # fluorophores come back: emitter_id repeats
    n_fluor = df["emitter_id"].nunique()
    per_frame = df.groupby("frame").size()
    assert per_frame.max() < 0.2 * n_fluor  # never all on
    # ~1 active emitter per um^2 for the defaults (40 labels/um, p_on 0.025, p_off 0.5)
    assert 20 < per_frame.mean() < 70
    # blinking: on-runs last ~1/p_off = 2 frames, and fluorophores switch off and on again
    frames = df.sort_values(["emitter_id", "frame"])
    gaps = frames.groupby("emitter_id")["frame"].diff().dropna()
    assert (gaps == 1).any() and (gaps > 1).any()
    # a fluorophore keeps its position and z across frames
    spread = df.groupby("emitter_id")[["x_nm", "y_nm", "z_nm"]].std().fillna(0.0)
    assert (spread.to_numpy() < 1e-9).all()
    # filaments are smooth curves: every fluorophore has a neighbour within ~150 nm
    xy = df.drop_duplicates("emitter_id")[["x_nm", "y_nm"]].to_numpy()
    d = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    assert np.median(d.min(axis=1)) < 150.0


def test_filament_density_sets_active_emitters():
    rng = np.random.default_rng(4)
    df = filament_scene(rng, 400, FOV, density=0.5)
    target = 0.5 * FOV[0] * FOV[1] / 1e6
    assert abs(df.groupby("frame").size().mean() / target - 1) < 0.15


# -- rendering ------------------------------------------------------------------------------
def test_render_movie_places_patches_exactly(clear_model):
    """Each emitter's patch equals the model rendered over the whole frame (edge emitters too)."""
    shape = (48, 40)
    truth = pd.DataFrame(
        {
            "frame": [0, 1, 1, 2],
            "x_nm": [2000.0, 30.0, -150.0, 3950.0],  # interior, at the edge, outside, right edge
            "y_nm": [2370.0, 4100.0, 800.0, 4780.0],
            "z_nm": [0.0, 200.0, -300.0, 500.0],
            "photons": [1000.0, 2000.0, 1500.0, 500.0],
        }
    )
    movie = render_movie(clear_model, truth, 3, shape, PX, background=0.0)
    assert movie.shape == (3, *shape) and movie.dtype == np.float64
    half = int(np.ceil(clear_model.support_radius(PX, PATCH_FRACTION) / PX))
    for f in range(3):
        expected = np.zeros(shape)
        for r in truth[truth["frame"] == f].itertuples():
            full = clear_model.render(r.x_nm, r.y_nm, r.z_nm, r.photons, shape, PX)
            ci, ri = int(np.floor(r.x_nm / PX)), int(np.floor(r.y_nm / PX))
            mask = np.zeros(shape, bool)
            mask[max(ri - half, 0) : ri + half + 1, max(ci - half, 0) : ci + half + 1] = True
            expected += np.where(mask, full, 0.0)
        np.testing.assert_allclose(movie[f], expected, rtol=1e-9, atol=1e-9)
    # the interior emitter keeps nearly all its photons
    assert movie[0].sum() > 0.85 * 1000.0


def test_render_movie_patch_radius(clear_model):
    n = 101
    truth = pd.DataFrame({"frame": [0], "x_nm": [5050.0], "y_nm": [5050.0], "z_nm": [0.0],
                          "photons": [1.0]})  # fmt: skip
    small = render_movie(clear_model, truth, 1, (n, n), PX, 0.0, radius_nm=300.0)
    default = render_movie(clear_model, truth, 1, (n, n), PX, 0.0)
    large = render_movie(clear_model, truth, 1, (n, n), PX, 0.0, radius_nm=5000.0)
    assert np.count_nonzero(small) == 7 * 7  # ceil(300 / 100) = 3 px each side
    assert small.sum() < default.sum() < large.sum() <= 1.0
    assert large.sum() > 0.97


def test_render_movie_background_and_validation(clear_model):
    bg = np.arange(12.0).reshape(3, 4)
    empty = pd.DataFrame(columns=["frame", "x_nm", "y_nm", "z_nm", "photons"])
    np.testing.assert_array_equal(render_movie(clear_model, empty, 2, (3, 4), PX, bg), [bg, bg])
    bad_frame = pd.DataFrame({"frame": [5], "x_nm": [0.0], "y_nm": [0.0], "z_nm": [0.0],
                              "photons": [1.0]})  # fmt: skip
    with pytest.raises(ValueError, match="frames"):
        render_movie(clear_model, bad_frame, 2, (3, 4), PX)
    with pytest.raises(ValueError, match="z"):
        render_movie(clear_model, bad_frame.assign(frame=0, z_nm=5000.0), 2, (3, 4), PX)
    with pytest.raises(ValueError, match="photons"):
        render_movie(clear_model, bad_frame.drop(columns="photons"), 2, (3, 4), PX)
    with pytest.raises(ValueError, match="background"):
        render_movie(clear_model, empty, 2, (3, 4), PX, np.ones((4, 3)))


def _centroids(image: np.ndarray, truth: pd.DataFrame, half: int = 2) -> np.ndarray:
    """Centroid (nm) in a (2*half+1)^2 window around the brightest pixel near each emitter."""
    out = []
    for r in truth.itertuples():
        c, rr = int(r.x_nm // PX), int(r.y_nm // PX)
        near = image[rr - 3 : rr + 4, c - 3 : c + 4]
        i, j = np.unravel_index(np.argmax(near), near.shape)
        pr, pc = rr - 3 + i, c - 3 + j
        win = image[pr - half : pr + half + 1, pc - half : pc + half + 1]
        xs = (np.arange(pc - half, pc + half + 1) + 0.5) * PX  # native: pixel centre at c + 0.5
        ys = (np.arange(pr - half, pr + half + 1) + 0.5) * PX
        s = win.sum()
        out.append(((win.sum(axis=0) * xs).sum() / s, (win.sum(axis=1) * ys).sum() / s))
    return np.array(out)


def test_coordinate_convention_centroid(clear_model):
    """Bright in-focus emitters with a symmetric PSF are found where the truth says (< 5 nm).

    A half-pixel (50 nm) or row/column mix-up in the simulator would fail this test.
    """
    rng = np.random.default_rng(11)
    cells = np.arange(8, 64, 16)  # 16 px (1.6 um) between emitters, one per cell
    rows = []
    for f in range(2):
        for gy in cells:
            for gx in cells:
                x = (gx + rng.uniform()) * PX  # random sub-pixel positions, x != y
                y = (gy + rng.uniform()) * PX
                rows.append((f, x, y, 0.0, 20000.0))
    truth = pd.DataFrame(rows, columns=["frame", "x_nm", "y_nm", "z_nm", "photons"])
    bg = 1.0
    sim = simulate(clear_model, scene=truth, n_frames=2, shape=(72, 64), background=bg, seed=5)
    photons = to_photons(sim.movie, sim.camera) - bg
    errors = []
    for f in range(2):
        t = truth[truth["frame"] == f]
        errors.append(_centroids(photons[f], t) - t[["x_nm", "y_nm"]].to_numpy())
    err = np.concatenate(errors)
    dist = np.hypot(err[:, 0], err[:, 1])
    assert dist.mean() < 5.0, f"mean distance {dist.mean():.1f} nm"
    assert np.all(np.abs(err.mean(axis=0)) < 2.0), f"bias {err.mean(axis=0)} nm"


# -- high level -----------------------------------------------------------------------------
def test_simulate_same_seed_same_bytes(dh, tmp_path):
    kw = {"n_frames": 3, "shape": (32, 32), "density": 1.5, "seed": 7}
    a = simulate(dh, **kw)
    b = simulate(dh, **kw)
    c = simulate(dh, **{**kw, "seed": 8})
    assert isinstance(a, Simulation)
    assert a.movie.dtype == np.uint16 and a.movie.shape == (3, 32, 32)
    assert a.expected.dtype == np.float64 and a.expected.shape == (3, 32, 32)
    paths = []
    for name, sim in (("a", a), ("b", b), ("c", c)):
        p = tmp_path / f"{name}.tif"
        write_tiff(p, sim.movie, pixel_size=sim.pixel_size)
        paths.append(p.read_bytes())
    assert paths[0] == paths[1]
    assert paths[0] != paths[2]
    pd.testing.assert_frame_equal(a.truth, b.truth)
    assert not a.truth.equals(c.truth)


@pytest.mark.parametrize("scene", ["uniform", "cluster", "filament", "clusters", "filaments"])
def test_simulate_scenes(dh, scene):
    sim = simulate(dh, scene=scene, n_frames=2, shape=(24, 24), seed=1)
    assert sim.movie.shape == (2, 24, 24)
    assert set(sim.truth.columns) >= {"frame", "x_nm", "y_nm", "z_nm", "photons"}
    assert sim.truth["z_nm"].between(*dh.z_range).all()
    assert sim.params["scene"] in SCENES
    # the movie is camera counts of the expected image (default ideal camera: offset 100)
    assert sim.camera == Camera()
    assert abs(to_photons(sim.movie, sim.camera).mean() / sim.expected.mean() - 1) < 0.05


def test_simulate_unknown_scene_lists_names(dh):
    with pytest.raises(ValueError, match=r"uniform.*cluster.*filament"):
        simulate(dh, scene="spiral")
