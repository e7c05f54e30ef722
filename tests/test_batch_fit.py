"""Batched maximum-likelihood fits (``fit_batch``) and the batched spline renderer.

The reference is ``fit_emitters`` run window by window: the batch solves the same problem from
the same start with the same steps, so the two must agree to rounding. The PSF is a spline
table of the cheap analytic double helix (coarse: 40 nm planes) to keep the tests fast.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from sparseloc.psf import make_psf
from sparseloc.psf.spline import SplinePSF
from sparseloc.solvers import Emitters
from sparseloc.solvers.batch_fit import BatchFitResult, fit_batch, spline_images
from sparseloc.solvers.refine import fit_emitters

PX = 100.0  # nm
W = 15  # px
K = 3


@pytest.fixture(scope="module")
def spline() -> SplinePSF:
    return SplinePSF.from_model(make_psf("dh-analytic"), PX, roi=31, z_step=40.0)


def simulate(spline, n, seed, *, offsets=False, shapes=None, n_min=1):
    """``n`` windows (W x W, or ``shapes`` padded to their largest) with ``n_min``-3
    emitters, background 10, Poisson noise; starts near the truth."""
    rng = np.random.default_rng(seed)
    shapes = [(W, W)] * n if shapes is None else shapes
    rows = max(r for r, _ in shapes)
    cols = max(c for _, c in shapes)
    ne = rng.integers(n_min, K + 1, n)
    origins = np.round(rng.uniform(0, 5000, (n, 2)))
    windows = np.zeros((n, rows, cols))
    mask = np.zeros((n, rows, cols), dtype=bool)
    offs = np.zeros((n, rows, cols))
    starts = np.full((n, K, 4), np.nan)
    for b, (r, c) in enumerate(shapes):
        k = ne[b]
        o = tuple(origins[b])
        t = np.column_stack(
            [
                origins[b, 0] + rng.uniform(0.3, 0.7, k) * c * PX,
                origins[b, 1] + rng.uniform(0.3, 0.7, k) * r * PX,
                rng.uniform(-700, 700, k),
                rng.uniform(1000, 5000, k),
            ]
        )
        mu = spline.render(*t.T, (r, c), PX, origin=o) + 10.0 if k else np.full((r, c), 10.0)
        if offsets and b % 2:
            # a neighbour just outside the window, fitted elsewhere
            offs[b, :r, :c] = spline.render(
                [o[0] - 150.0], [o[1] + 0.5 * r * PX], [200.0], [3000.0], (r, c), PX, origin=o
            )
            mu = mu + offs[b, :r, :c]
        windows[b, :r, :c] = rng.poisson(mu)
        mask[b, :r, :c] = True
        move = np.column_stack(
            [rng.normal(0, 30, (k, 2)), rng.normal(0, 60, k), rng.normal(0, 0.1, k) * t[:, 3]]
        )
        starts[b, :k] = t + move
    return {
        "windows": windows,
        "starts": starts,
        "n_emitters": ne,
        "origins": origins,
        "offsets": offs,
        "mask": mask,
        "shapes": shapes,
    }


def batch(spline, d, **kw) -> BatchFitResult:
    kw.setdefault("offsets", d["offsets"])
    return fit_batch(
        d["windows"],
        d["starts"],
        d["n_emitters"],
        spline,
        pixel_size=PX,
        origins=d["origins"],
        **kw,
    )


def loop(spline, d, read_variance=None, **kw):
    out = []
    for b, (r, c) in enumerate(d["shapes"]):
        k = d["n_emitters"][b]
        rv = read_variance
        if rv is not None and np.ndim(rv) == 3:
            rv = rv[b, :r, :c]
        out.append(
            fit_emitters(
                d["windows"][b, :r, :c],
                spline,
                Emitters.from_array(d["starts"][b, :k]),
                pixel_size=PX,
                origin=tuple(d["origins"][b]),
                offset=d["offsets"][b, :r, :c],
                read_variance=rv,
                **kw,
            )
        )
    return out


def assert_same_fits(ref, res: BatchFitResult, pos_nm=1e-6, photons=1e-8, nll=1e-10, sd=1e-6):
    for b, r in enumerate(ref):
        k = len(r.emitters)
        assert res.n_emitters[b] == k
        est = res.theta[b, :k]
        want = r.emitters.as_array().reshape(k, 4)
        np.testing.assert_allclose(est[:, :3], want[:, :3], rtol=0, atol=pos_nm)
        np.testing.assert_allclose(est[:, 3], want[:, 3], rtol=photons)
        np.testing.assert_allclose(res.log_likelihood[b], r.log_likelihood, rtol=nll)
        np.testing.assert_allclose(res.sigma[b, :k], r.sigma, rtol=sd)
        np.testing.assert_allclose(res.background_params[b], r.background, rtol=1e-3)
        np.testing.assert_allclose(res.deviance_per_dof[b], r.deviance_per_dof, rtol=1e-6)
        assert list(res.flags[b, :k]) == list(r.flags)
        assert res.converged[b] == r.converged
        assert res.n_iter[b] == r.n_iter  # the same steps
        assert np.all(np.isnan(res.theta[b, k:])) and np.all(res.flags[b, k:] == "")


# -- the renderer --------------------------------------------------------------------------------
def random_emitters(rng, b, k, shape):
    rows, cols = shape
    origins = rng.uniform(-3000, 3000, (b, 2))
    # inside, near the edges and beyond them (partial or empty images)
    x = origins[:, :1] + rng.uniform(-600, cols * PX + 600, (b, k))
    y = origins[:, 1:] + rng.uniform(-600, rows * PX + 600, (b, k))
    z = rng.uniform(-1000, 1000, (b, k))
    return x, y, z, origins


def test_renderer_matches_spline_images_and_gradients(spline):
    rng = np.random.default_rng(0)
    shape = (13, 17)
    x, y, z, origins = random_emitters(rng, 6, 4, shape)
    img, der = spline_images(spline, x, y, z, shape, origins, derivatives=True)
    assert img.shape == (6, 4, *shape) and der.shape == (6, 4, 3, *shape)
    plain = spline_images(spline, x, y, z, shape, origins)
    np.testing.assert_allclose(plain, img, rtol=0, atol=1e-14 * np.abs(img).max())
    photons = rng.uniform(500, 5000, (6, 4))
    for b in range(6):
        o = tuple(origins[b])
        ref, dref = spline.images(x[b], y[b], z[b], shape, PX, origin=o, derivatives=True)
        peak = np.abs(ref).max()
        np.testing.assert_allclose(img[b], ref, rtol=0, atol=1e-10 * peak)
        for j in range(3):
            np.testing.assert_allclose(
                der[b, :, j], dref[:, j], rtol=0, atol=1e-10 * np.abs(dref[:, j]).max()
            )
        rendered = spline.render(x[b], y[b], z[b], photons[b], shape, PX, origin=o)
        mine = np.tensordot(photons[b], img[b], axes=(0, 0))
        np.testing.assert_allclose(mine, rendered, rtol=0, atol=1e-10 * np.abs(rendered).max())
        grads = spline.gradients(x[b], y[b], z[b], photons[b], shape, PX, origin=o)
        np.testing.assert_allclose(
            der[b] * photons[b, :, None, None, None],
            grads[:, :3],
            rtol=0,
            atol=1e-10 * np.abs(grads[:, :3]).max(),
        )
    # far away: nothing
    far, dfar = spline_images(spline, x + 1e5, y, z, shape, origins, derivatives=True)
    assert not far.any() and not dfar.any()


def test_renderer_float32_is_close(spline):
    rng = np.random.default_rng(1)
    x, y, z, origins = random_emitters(rng, 4, 3, (W, W))
    ref = spline_images(spline, x, y, z, (W, W), origins)
    single = spline_images(spline, x, y, z, (W, W), origins, precision="float32")
    assert single.dtype == np.float32
    assert np.abs(single - ref).max() < 1e-6 * np.abs(ref).max()


def test_renderer_torch_matches_numpy(spline, torch_device):
    import torch

    rng = np.random.default_rng(2)
    x, y, z, origins = random_emitters(rng, 5, 3, (W, W))
    ref, dref = spline_images(spline, x, y, z, (W, W), origins, derivatives=True)
    img, der = spline_images(
        spline, x, y, z, (W, W), origins, derivatives=True, device=torch_device
    )
    assert isinstance(img, torch.Tensor) and img.dtype == torch.float64
    assert img.device.type == torch_device
    img, der = img.cpu().numpy(), der.cpu().numpy()
    np.testing.assert_allclose(img, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    np.testing.assert_allclose(der, dref, rtol=0, atol=1e-12 * np.abs(dref).max())


# -- the fit against fit_emitters ----------------------------------------------------------------
@pytest.mark.parametrize(
    ("noise", "offsets"), [("poisson", False), ("poisson", True), ("scmos", True)]
)
def test_batch_equals_fit_emitters_window_by_window(spline, noise, offsets):
    d = simulate(spline, 20, seed=3 + offsets, offsets=offsets)
    rv = None
    if noise == "scmos":
        rv = np.random.default_rng(5).uniform(1.0, 4.0, d["windows"].shape)
        d["windows"] = d["windows"] + np.random.default_rng(6).normal(0, 1.5, d["windows"].shape)
    res = batch(spline, d, noise=noise, read_variance=rv, background=10.0)
    ref = loop(spline, d, read_variance=rv, noise=noise, background=10.0)
    assert_same_fits(ref, res)
    assert res.converged.mean() > 0.9
    fr = res.fit_result(0)
    assert len(fr.emitters) == res.n_emitters[0] and fr.log_likelihood == res.log_likelihood[0]


def test_batch_options_equal_fit_emitters(spline):
    """EMCCD, a plane background, background estimated from the window, a window with no
    emitter (background only)."""
    d = simulate(spline, 8, seed=7, offsets=True, n_min=0)
    d["n_emitters"][0] = 0
    res = batch(spline, d, noise="emccd", plane=True)
    ref = loop(spline, d, noise="emccd", plane=True)
    assert_same_fits(ref, res)
    assert res.background_params.shape == (8, 3)


def test_torch_equals_numpy(spline, torch_device):
    import torch

    d = simulate(spline, 12, seed=8, offsets=True)
    ref = batch(spline, d, background=10.0)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        res = batch(spline, d, background=10.0, device=torch_device)
    finally:
        torch.set_num_threads(threads)
    assert res.device == torch_device and ref.device == "numpy"
    real = np.isfinite(ref.theta)
    np.testing.assert_allclose(res.theta[real], ref.theta[real], rtol=1e-8)
    np.testing.assert_allclose(res.log_likelihood, ref.log_likelihood, rtol=1e-10)
    np.testing.assert_allclose(res.sigma[real], ref.sigma[real], rtol=1e-8)
    np.testing.assert_allclose(res.model_image, ref.model_image, rtol=1e-8)
    np.testing.assert_array_equal(res.n_iter, ref.n_iter)


def test_float32_rendering_barely_moves_the_fit(spline):
    d = simulate(spline, 10, seed=9)
    ref = batch(spline, d, background=10.0)
    single = batch(spline, d, background=10.0, precision="float32")
    real = np.isfinite(ref.theta[..., 0])
    assert np.abs(single.theta[..., :3] - ref.theta[..., :3])[real].max() < 0.01  # nm
    np.testing.assert_allclose(single.log_likelihood, ref.log_likelihood, rtol=1e-8)


# -- padding ---------------------------------------------------------------------------------------
def test_padded_pixels_and_emitters_change_nothing(spline):
    shapes = [(11, 13), (15, 15), (12, 9), (15, 11), (9, 14), (13, 12)]
    d = simulate(spline, len(shapes), seed=10, offsets=True, shapes=shapes)
    # garbage on padded pixels and in padded emitter rows must be ignored
    d["windows"][~d["mask"]] = np.nan
    d["offsets"][~d["mask"]] = 1e6
    res = batch(spline, d, mask=d["mask"], background=10.0)
    ref = loop(spline, d, background=10.0)
    assert_same_fits(ref, res, pos_nm=1e-6, photons=1e-10, nll=1e-12, sd=1e-8)
    # the same windows, each alone and unpadded
    for b, (r, c) in enumerate(shapes):
        k = d["n_emitters"][b]
        one = fit_batch(
            d["windows"][b : b + 1, :r, :c],
            d["starts"][b : b + 1, :k],
            None,
            spline,
            pixel_size=PX,
            origins=d["origins"][b : b + 1],
            offsets=d["offsets"][b : b + 1, :r, :c],
            background=10.0,
        )
        np.testing.assert_allclose(one.theta[0], res.theta[b, :k], rtol=1e-12)
        np.testing.assert_allclose(one.log_likelihood[0], res.log_likelihood[b], rtol=1e-12)


def test_padding_before_the_window_with_a_shifted_origin(spline):
    """Real pixels need not start at (0, 0): the window's extent is its mask's bounding box."""
    d = simulate(spline, 4, seed=11)
    res = batch(spline, d, background=10.0)
    pad = 3
    big = np.zeros((4, W + pad, W + pad))
    big[:, pad:, pad:] = d["windows"]
    mask = np.zeros(big.shape, dtype=bool)
    mask[:, pad:, pad:] = True
    shifted = fit_batch(
        big,
        d["starts"],
        d["n_emitters"],
        spline,
        pixel_size=PX,
        origins=d["origins"] - pad * PX,
        mask=mask,
        background=10.0,
    )
    real = np.isfinite(res.theta)
    np.testing.assert_allclose(shifted.theta[real], res.theta[real], rtol=1e-10)
    np.testing.assert_allclose(shifted.log_likelihood, res.log_likelihood, rtol=1e-10)
    np.testing.assert_array_equal(shifted.flags, res.flags)


# -- bad input -------------------------------------------------------------------------------------
def test_bad_input_raises_clear_errors(spline):
    d = simulate(spline, 3, seed=12)
    y, st, ne, org = d["windows"], d["starts"], d["n_emitters"], d["origins"]

    def call(**kw):
        args = dict(windows=y, starts=st, n_emitters=ne, spline=spline)
        args.update({k: kw.pop(k) for k in list(kw) if k in args})
        kw.setdefault("pixel_size", PX)
        kw.setdefault("origins", org)
        return fit_batch(args["windows"], args["starts"], args["n_emitters"], args["spline"], **kw)

    with pytest.raises(ValueError, match="windows must be a"):
        call(windows=y[0])
    with pytest.raises(ValueError, match="starts must have shape"):
        call(starts=st[:2])
    with pytest.raises(ValueError, match="starts must have shape"):
        call(starts=st[..., :3])
    with pytest.raises(ValueError, match="n_emitters must lie between"):
        call(n_emitters=np.array([1, 2, 4]))
    with pytest.raises(ValueError, match="n_emitters must have shape"):
        call(n_emitters=np.array([1, 2]))
    with pytest.raises(ValueError, match="origins must have shape"):
        call(origins=org[:, :1])
    bad = y.copy()
    bad[1, 3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        call(windows=bad)
    with pytest.raises(ValueError, match="negative photon counts"):
        call(windows=y - 100.0)
    bad_st = st.copy()
    bad_st[0, 0, 2] = np.nan
    with pytest.raises(ValueError, match="starts must be finite"):
        call(starts=bad_st)
    with pytest.raises(ValueError, match="offsets must have the windows' shape"):
        call(offsets=np.zeros((3, W, W + 1)))
    with pytest.raises(ValueError, match="offsets must be finite"):
        call(offsets=np.full(y.shape, np.inf))
    with pytest.raises(ValueError, match="mask must have"):
        call(mask=np.ones((3, W, W - 1), dtype=bool))
    with pytest.raises(ValueError, match="no real pixel"):
        call(mask=np.zeros(y.shape, dtype=bool))
    with pytest.raises(ValueError, match="noise must be one of"):
        call(noise="gauss")
    with pytest.raises(ValueError, match="needs read_variance"):
        call(noise="scmos")
    with pytest.raises(ValueError, match="only used with noise='scmos'"):
        call(read_variance=2.0)
    with pytest.raises(ValueError, match="read_variance must be >= 0"):
        call(noise="scmos", read_variance=-1.0)
    with pytest.raises(ValueError, match="calibrated at 100 nm pixels"):
        call(pixel_size=160.0)
    with pytest.raises(ValueError, match="background must be"):
        call(background=np.ones(2))
    with pytest.raises(ValueError, match="precision must be"):
        call(precision="float16")
    with pytest.raises(TypeError, match="needs a SplinePSF"):
        call(spline=make_psf("dh-analytic"))


def test_module_imports_without_torch():
    code = (
        "import sys; import sparseloc.solvers.batch_fit as m; "
        "assert 'torch' not in sys.modules, 'torch imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("noise", ["poisson", "emccd", "scmos"])
def test_batch_equals_fit_emitters_with_a_quantum_efficiency(spline, noise):
    d = simulate(spline, 10, seed=11, offsets=True)
    rv = 2.0 if noise == "scmos" else None
    res = batch(spline, d, noise=noise, read_variance=rv, background=10.0, qe=0.7)
    ref = loop(spline, d, read_variance=rv, noise=noise, background=10.0, qe=0.7)
    assert_same_fits(ref, res)
    if noise == "poisson":
        # the same optimum; the Fisher information scaled by qe
        plain = batch(spline, d, background=10.0)
        real = np.isfinite(plain.sigma)
        np.testing.assert_allclose(res.theta[real], plain.theta[real], atol=1e-5)
        np.testing.assert_allclose(res.sigma[real], plain.sigma[real] / np.sqrt(0.7), rtol=1e-5)
    with pytest.raises(ValueError, match="qe"):
        batch(spline, d, qe=0.0)


def test_no_iterations_evaluate_the_starts(spline):
    """max_iter=0: the starts' likelihood, uncertainties and flags, as fit_emitters gives."""
    d = simulate(spline, 6, seed=12, offsets=True)
    res = batch(spline, d, background=10.0, max_iter=0)
    ref = loop(spline, d, background=10.0, max_iter=0)
    assert_same_fits(ref, res)
    assert not res.converged.any() and np.all(res.n_iter == 0)
    real = np.isfinite(res.theta)
    np.testing.assert_allclose(res.theta[real], d["starts"][real])
    with pytest.raises(ValueError, match="max_iter"):
        batch(spline, d, max_iter=-1)


def _assert_power_basis_weights(device):
    from sparseloc.psf.spline import bspline_weights
    from sparseloc.solvers.batch_fit import _as_numpy, _backend, _bspline

    f = np.random.default_rng(3).uniform(0.0, 1.0, 500)
    ref_w, ref_dw = bspline_weights(f)
    ops = _backend(device)
    w, dw = (np.asarray(_as_numpy(a)) for a in _bspline(ops.asarray(f), ops))
    np.testing.assert_allclose(w, ref_w, rtol=0, atol=1e-15)
    np.testing.assert_allclose(dw, ref_dw, rtol=0, atol=1e-15)


def test_power_basis_weights_equal_the_spline_definition():
    """The batched renderer's B-spline weights (Horner in the power basis) are
    ``bspline_weights``."""
    _assert_power_basis_weights(None)


def test_power_basis_weights_on_torch(torch_device):
    _assert_power_basis_weights(torch_device)
