"""The table model of Cycles' Principled BSDF (gbuffer_export.brdf_model): tables against independent
integrals and closed forms, limits, hard inputs, cache."""
from __future__ import annotations

import numpy as np
import pytest

from gbuffer_export import brdf, brdf_model
from gbuffer_export.brdf_model import ModelSpec, generate_model_tables, principled_albedo

SPEC = ModelSpec(n_rough=9, n_mu=9, n_z=5, samples=2048)


@pytest.fixture(scope="module")
def tables():
    return generate_model_tables(SPEC)


def fresnel_snell(cos_i, eta):
    """Unpolarised dielectric Fresnel from Snell's law and the s/p amplitudes (independent of the model's form)."""
    sin_t = np.sqrt(1 - cos_i ** 2) / eta
    cos_t = np.sqrt(1 - sin_t ** 2)
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return 0.5 * (rs ** 2 + rp ** 2)


def albedo_quadrature(mu, r, fresnel=None, n=600):
    """Directional albedo of GGX with height-correlated Smith G2 (alpha = r^2) on a dense grid of half vectors
    (tan theta_h = alpha tan u), written from the BRDF D G2 F / (4 NoL NoV)."""
    alpha = max(r * r, 1e-7)
    u = (np.arange(n) + 0.5) / n * (np.pi / 2)
    phi = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    th = np.arctan(alpha * np.tan(u))
    dth = alpha / np.cos(u) ** 2 / (1 + (alpha * np.tan(u)) ** 2) * (np.pi / 2 / n)
    t, p = np.meshgrid(th, phi, indexing="ij")
    h = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    v = np.array([np.sqrt(1 - mu * mu), 0, mu])
    voh = h @ v
    nol = (2 * voh[..., None] * h - v)[..., 2]
    noh = h[..., 2]

    def lam(c):
        c = np.maximum(c, 1e-9)
        return 0.5 * (np.sqrt(1 + alpha ** 2 * (1 / c ** 2 - 1)) - 1)

    d = alpha ** 2 / (np.pi * (noh ** 2 * (alpha ** 2 - 1) + 1) ** 2)
    g2 = 1 / (1 + lam(mu) + lam(nol))
    f = 1.0 if fresnel is None else fresnel(np.clip(voh, 1e-9, 1))
    ok = (nol > 0) & (voh > 0)
    integrand = np.where(ok, d * g2 * f / (4 * mu) * 4 * voh, 0.0)  # f_r cos(theta_l) dw_l, dw_l = 4 VoH dw_h
    return float(np.sum(integrand * np.sin(t) * dth[:, None] * (2 * np.pi / (2 * n))))


def test_albedo_tables_against_quadrature(tables):
    rough = brdf_model.grid(SPEC.n_rough)
    mu = brdf_model.grid(SPEC.n_mu, brdf_model.MU_MIN)
    for i, j in ((4, 4), (6, 2), (8, 8), (2, 6)):
        e = albedo_quadrature(mu[j], rough[i])
        assert abs(tables.e[i, j] - e) < 2e-3, (i, j, tables.e[i, j], e)
        e5 = albedo_quadrature(mu[j], rough[i], lambda c: (1 - c) ** 5)
        assert abs(tables.s5[i, j] * tables.e[i, j] - e5) < 2e-3
        k = 2  # a grid value of z = F0^(1/4)
        f0 = (k / (SPEC.n_z - 1)) ** 4
        eta = brdf_model.eta_from_f0(f0)
        ed = albedo_quadrature(mu[j], rough[i], lambda c: (fresnel_snell(c, eta) - f0) / (1 - f0))
        assert abs(tables.s_ior[i, j, k] * tables.e[i, j] - ed) < 2e-3
    # E(NoV = 1, r = 1) = 1 - ln 2 for height-correlated Smith GGX at alpha = 1
    assert abs(tables.e[-1, -1] - (1 - np.log(2))) < 1e-3
    # E_avg is the cosine-weighted mean of E: compare with the trapezoid rule over a fine quadrature in mu
    xg, wg = np.polynomial.legendre.leggauss(8)
    mus = 0.5 * (xg + 1)
    es = np.array([albedo_quadrature(m, 0.5, n=300) for m in mus])
    approx = float(np.sum(0.5 * wg * 2 * mus * es))
    assert abs(tables.e_avg[4] - approx) < 3e-3  # row 4 is roughness 0.5


def test_roughness_zero_is_exact_fresnel(tables):
    mu_grid = brdf_model.grid(SPEC.n_mu, brdf_model.MU_MIN)
    mu = mu_grid[[1, 3, 5, 8]]  # grid values: no interpolation error in NoV
    one = np.ones_like(mu)
    # black dielectric: the real Fresnel of the IOR that gives F0 (grid values of z = F0^(1/4): 0.5, 0.75)
    for f0, tol in ((0.0625, 1e-3), (0.31640625, 1e-3)):
        got = principled_albedo(np.zeros((4, 3)), 0 * one, 0 * one, f0 * one, mu, tables)[:, 0]
        want = fresnel_snell(mu, brdf_model.eta_from_f0(f0))
        np.testing.assert_allclose(got, want, atol=tol)
    # metal: Schlick with F0 = base colour
    c = np.array([0.9, 0.5, 0.1])
    got = principled_albedo(np.broadcast_to(c, (4, 3)), 0 * one, one, 0.04 * one, mu, tables)
    want = c + (1 - c) * (1 - mu[:, None]) ** 5
    np.testing.assert_allclose(got, want, atol=1e-3)


def test_energy_conservation_and_layering(tables):
    rng = np.random.default_rng(1)
    n = 200
    r, mu, f0 = rng.random(n), rng.random(n), rng.random(n) * 0.2
    # white dielectric and white metal reflect everything (multiple-scattering compensation)
    np.testing.assert_allclose(principled_albedo(np.ones((n, 3)), r, 0 * r, f0, mu, tables), 1.0, atol=1e-6)
    np.testing.assert_allclose(principled_albedo(np.ones((n, 3)), r, 0 * r + 1, f0, mu, tables), 1.0, atol=1e-6)
    # the diffuse sits under the specular: F is affine in c with slope (1 - spec), and metallic mixes linearly
    a0 = principled_albedo(np.zeros((n, 3)), r, 0 * r, f0, mu, tables)
    a1 = principled_albedo(np.full((n, 3), 0.5), r, 0 * r, f0, mu, tables)
    assert np.all(a1 > a0) and np.all(a1 <= 1.0)
    np.testing.assert_allclose(a1, a0 + 0.5 * (1 - a0), atol=1e-9)
    m = principled_albedo(np.full((n, 3), 0.5), r, 0 * r + 1, f0, mu, tables)
    half = principled_albedo(np.full((n, 3), 0.5), r, 0 * r + 0.5, f0, mu, tables)
    np.testing.assert_allclose(half, 0.5 * (a1 + m), atol=1e-9)
    # multiple scattering only adds: a metal's albedo lies between E * F0 (single scattering at F0) and 1
    e = brdf_model.lookup2(tables.e, r, mu)[:, None]
    assert np.all(m >= e * 0.5 - 1e-9) and np.all(m <= 1.0)
    # no specular at F0 = 0 (IOR 1 or specular level 0): F = c exactly, 0 for black
    np.testing.assert_array_equal(principled_albedo(np.zeros((n, 3)), r, 0 * r, 0 * r, mu, tables), 0.0)


def test_hard_inputs_finite(tables):
    vals = np.array([np.nan, -1.0, 0.0, 1e-6, 0.5, 1.0, 2.0, np.inf])
    c = np.stack([vals, vals, vals], -1)
    for arr in (vals, vals[::-1]):
        out = principled_albedo(np.nan_to_num(c, nan=0.0, posinf=1.0), np.nan_to_num(arr, nan=0.0),
                                np.clip(np.nan_to_num(arr[::-1], nan=0.0), 0, 1), np.nan_to_num(arr, nan=0.0),
                                arr, tables)
        assert np.all(np.isfinite(out)) and np.all(out >= 0)


def test_model_source_through_compute_fbeta(tables, monkeypatch):
    monkeypatch.setattr(brdf_model, "load_or_generate_model_tables", lambda spec=None: tables)
    h, w = 6, 8
    k = (8.0, 8.0, 4.0, 3.0)
    g = {"albedo": np.full((h, w, 3), 0.3, np.float32), "normal": np.zeros((h, w, 3), np.float32),
         "roughness": np.full((h, w, 1), 0.4, np.float32), "metallic": np.zeros((h, w, 1), np.float32),
         "specular": np.full((h, w, 1), 0.04, np.float32), "flags": np.zeros((h, w, 1), np.uint32)}
    g["normal"][..., 2] = 1.0
    g["flags"][0] = 1
    f = brdf.compute_fbeta("model", g, k)
    assert f.shape == (h, w, 3) and f.dtype == np.float32 and np.all(np.isfinite(f))
    np.testing.assert_array_equal(f[0], 1.0)
    nov = brdf.compute_nov(g["normal"], k)
    want = principled_albedo(np.full((h, w, 3), 0.3), np.full((h, w), 0.4), np.zeros((h, w)),
                             np.full((h, w), 0.04), nov, tables)
    np.testing.assert_allclose(f[1:], want[1:], atol=1e-6)


def test_model_cache(tmp_path, monkeypatch, tables):
    monkeypatch.setenv("BLENDSR_CACHE", str(tmp_path))
    brdf_model._load_or_generate.cache_clear()
    spec = ModelSpec(n_rough=4, n_mu=4, n_z=3, samples=64)
    t = brdf_model.load_or_generate_model_tables(spec)
    path = tmp_path / f"{spec.key}.npz"
    assert path.is_file() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    brdf_model._load_or_generate.cache_clear()
    again = brdf_model.load_or_generate_model_tables(spec)
    np.testing.assert_array_equal(again.s_ior, t.s_ior)
    with pytest.raises(ValueError):
        brdf_model.load_model_tables(path, ModelSpec(n_rough=5, n_mu=4, n_z=3, samples=64))
    path.write_bytes(b"junk")
    brdf_model._load_or_generate.cache_clear()
    np.testing.assert_array_equal(brdf_model.load_or_generate_model_tables(spec).e, t.e)
    brdf_model._load_or_generate.cache_clear()
