"""Tests of the Fisher information and CRLB (sparseloc.crlb)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr

from sparseloc.crlb import crlb, crlb_from_fisher, crlb_single, fisher_information
from sparseloc.psf import DoubleHelixMask, PSFBase, PupilPSF

SQRT2PI = np.sqrt(2.0 * np.pi)


class PixelGaussian(PSFBase):
    """Isotropic Gaussian integrated over square pixels, with analytic derivatives.

    ``sigma(z) = sigma0`` or, with ``depth``, ``sigma0 * sqrt(1 + (z / depth)^2)`` (nm).
    """

    name = "pixel-gaussian"

    def __init__(self, sigma0: float = 130.0, depth: float | None = None) -> None:
        super().__init__()
        self.sigma0 = sigma0
        self.depth = depth
        self._z_range = (-1000.0, 1000.0)

    def _sigma(self, z):
        if self.depth is None:
            return np.full_like(z, self.sigma0), np.zeros_like(z)
        q = np.sqrt(1.0 + (z / self.depth) ** 2)
        return self.sigma0 * q, self.sigma0 * z / (self.depth**2 * q)

    @staticmethod
    def _axis(n, a, o, c, s):
        edges = o + np.arange(n + 1) * a  # (n+1,)
        t = (edges[None, :] - c[:, None]) / s[:, None]  # (K, n+1)
        cdf = ndtr(t)
        pdf = np.exp(-0.5 * t**2) / SQRT2PI
        e = np.diff(cdf, axis=1)
        de_dc = -np.diff(pdf, axis=1) / s[:, None]
        de_ds = -np.diff(t * pdf, axis=1) / s[:, None]
        return e, de_dc, de_ds

    def _images(self, x, y, z, shape, pixel_size, origin, derivatives):
        rows, cols = shape
        s, ds_dz = self._sigma(z)
        ex, dex, dexs = self._axis(cols, pixel_size, origin[0], x, s)
        ey, dey, deys = self._axis(rows, pixel_size, origin[1], y, s)
        img = ey[:, :, None] * ex[:, None, :]
        if not derivatives:
            return img
        der = np.empty((len(x), 3, rows, cols))
        der[:, 0] = ey[:, :, None] * dex[:, None, :]
        der[:, 1] = dey[:, :, None] * ex[:, None, :]
        der[:, 2] = (deys[:, :, None] * ex[:, None, :] + ey[:, :, None] * dexs[:, None, :]) * (
            ds_dz[:, None, None]
        )
        return img, der


@pytest.fixture(scope="module")
def dh():
    return PupilPSF(DoubleHelixMask(0.35), na=1.45, wavelength=670.0, z_range=(-1000, 1000))


def _fd_gradients(model, x, y, z, n, shape, px, h=0.05):
    """Central finite differences of ``model.render`` -> (K, 4, rows, cols)."""
    k = len(x)
    out = np.empty((k, 4, *shape))
    for e in range(k):
        for p in range(3):
            lo = [np.array(v, dtype=float) for v in (x, y, z)]
            hi = [v.copy() for v in lo]
            lo[p][e] -= h
            hi[p][e] += h
            out[e, p] = (model.render(*hi, n, shape, px) - model.render(*lo, n, shape, px)) / (
                2 * h
            )
        one = np.zeros(k)
        one[e] = 1.0
        out[e, 3] = model.render(x, y, z, one, shape, px)
    return out


def test_test_model_gradients_are_right():
    m = PixelGaussian(120.0, depth=400.0)
    x, y, z, n = np.array([810.0]), np.array([770.0]), np.array([250.0]), np.array([1000.0])
    g = m.gradients(x, y, z, n, (15, 15), 100.0)
    np.testing.assert_allclose(g, _fd_gradients(m, x, y, z, n, (15, 15), 100.0), atol=1e-6)
    assert m.render(x, y, z, n, (15, 15), 100.0).sum() == pytest.approx(1000.0, rel=1e-6)


# --------------------------------------------------------------------------------------------
# Gaussian limits
# --------------------------------------------------------------------------------------------
def test_mortensen_limit_high_photons_no_background():
    sigma, a, n = 130.0, 100.0, 1e5
    m = PixelGaussian(sigma)
    shape = (25, 25)
    c = 12.5 * a  # centre of the middle pixel
    bounds = crlb(m, c, c, 0.0, n, 1e-4, shape, a)
    sigma_a = np.sqrt(sigma**2 + a**2 / 12.0)
    limit = sigma_a / np.sqrt(n)
    assert bounds[0, 0] == pytest.approx(limit, rel=0.02)
    assert bounds[0, 1] == pytest.approx(bounds[0, 0], rel=1e-9)
    # z carries no information in a z-independent model: inf, the rest finite
    assert np.isinf(bounds[0, 2])
    assert np.isfinite(bounds[0, [0, 1, 3]]).all()
    # photons: Poisson limit sqrt(N) when the background is negligible
    assert bounds[0, 3] == pytest.approx(np.sqrt(n), rel=0.01)


def test_crlb_scales_as_inverse_sqrt_photons():
    m = PixelGaussian(110.0, depth=500.0)
    b1 = crlb(m, 1030.0, 990.0, 300.0, 1e4, 1e-6, (21, 21), 100.0)
    b2 = crlb(m, 1030.0, 990.0, 300.0, 1e6, 1e-6, (21, 21), 100.0)
    np.testing.assert_allclose(b1[0, :3] / b2[0, :3], 10.0, rtol=2e-3)


def test_emccd_is_sqrt2_times_poisson_and_scmos(dh):
    args = (dh, [1200.0, 1500.0], [1250.0, 1100.0], [-200.0, 350.0], [1500.0, 900.0], 5.0)
    p = crlb(*args, (15, 15), 160.0)
    e = crlb(*args, (15, 15), 160.0, noise="emccd")
    np.testing.assert_allclose(e, np.sqrt(2.0) * p, rtol=1e-9)
    s0 = crlb(*args, (15, 15), 160.0, noise="scmos", read_variance=0.0)
    np.testing.assert_allclose(s0, p, rtol=1e-9)
    rv = np.full((15, 15), 2.0)
    rv[0, 0] = 50.0
    s = crlb(*args, (15, 15), 160.0, noise="scmos", read_variance=rv)
    assert np.all(s > p)


def test_fisher_symmetric_positive_definite(dh):
    f = fisher_information(
        dh,
        [1200.0, 1500.0],
        [1250.0, 1100.0],
        [-200.0, 350.0],
        [1500.0, 900.0],
        5.0,
        (15, 15),
        160.0,
    )
    assert f.shape == (9, 9)
    np.testing.assert_array_equal(f, f.T)
    d = 1.0 / np.sqrt(np.diag(f))
    assert np.linalg.eigvalsh(f * d[:, None] * d[None, :]).min() > 1e-6


def test_fisher_analytic_equals_finite_difference(dh):
    x = np.array([1200.0, 1550.0])
    y = np.array([1250.0, 1050.0])
    z = np.array([-200.0, 350.0])
    n = np.array([1500.0, 900.0])
    shape, px, bg = (15, 15), 160.0, 5.0
    f = fisher_information(dh, x, y, z, n, bg, shape, px)
    g = _fd_gradients(dh, x, y, z, n, shape, px)
    mu = dh.render(x, y, z, n, shape, px) + bg
    gr = np.concatenate([g.reshape(8, -1), np.ones((1, mu.size))])
    f_fd = (gr / mu.ravel()) @ gr.T
    d = 1.0 / np.sqrt(np.diag(f))
    np.testing.assert_allclose(
        f_fd * d[:, None] * d[None, :], f * d[:, None] * d[None, :], atol=1e-4
    )


def test_crlb_single_matches_crlb(dh):
    zs = np.array([-400.0, 0.0, 250.0])
    s = crlb_single(dh, zs, 1100.0, 5.0, 160.0, window=15)
    assert s.shape == (3, 4)
    for i, zv in enumerate(zs):
        b = crlb(dh, 7.5 * 160.0, 7.5 * 160.0, zv, 1100.0, 5.0, (15, 15), 160.0)
        np.testing.assert_allclose(s[i], b[0], rtol=1e-9)
    # the default window holds the support radius and never loses information
    big = crlb_single(dh, zs, 1100.0, 5.0, 160.0)
    assert np.all(big <= s * (1 + 1e-9))


def test_background_bound_returned():
    m = PixelGaussian(130.0, depth=400.0)
    b, sb = crlb(m, 1000.0, 1000.0, 200.0, 2000.0, 10.0, (21, 21), 100.0, return_background=True)
    assert b.shape == (1, 4)
    # background alone over 441 pixels: sqrt(b / npix) is the floor
    assert sb >= np.sqrt(10.0 / 441) * 0.999


# --------------------------------------------------------------------------------------------
# Singular cases and validation
# --------------------------------------------------------------------------------------------
def test_coincident_emitters_singular():
    m = PixelGaussian(130.0, depth=400.0)
    args = (m, [1000.0, 1000.0], [1000.0, 1000.0], [200.0, 200.0], [1000.0, 1000.0], 5.0)
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        crlb(*args, (15, 15), 100.0)
    b = crlb(*args, (15, 15), 100.0, singular="pinv")
    assert np.isfinite(b).all()


def test_crlb_from_fisher_zero_rows_are_inf():
    f = np.diag([4.0, 0.0, 1.0])
    np.testing.assert_allclose(crlb_from_fisher(f), [0.5, np.inf, 1.0])


def test_validation(dh):
    args = (dh, 1000.0, 1000.0, 0.0, 1000.0, 5.0, (11, 11), 160.0)
    with pytest.raises(ValueError, match="poisson, emccd, scmos"):
        crlb(*args, noise="ccd")
    with pytest.raises(ValueError, match="read_variance"):
        crlb(*args, noise="scmos")
    with pytest.raises(ValueError, match="read_variance"):
        crlb(*args, read_variance=1.0)
    with pytest.raises(ValueError, match="background"):
        crlb(dh, 1000.0, 1000.0, 0.0, 1000.0, -1.0, (11, 11), 160.0)
    with pytest.raises(ValueError, match="> 0"):
        crlb(PixelGaussian(), 550.0, 550.0, 0.0, 1000.0, 0.0, (41, 41), 100.0)
