"""A table-based model of the directional albedo of Cycles' Principled BSDF (Blender 4.x/5.x, 'Multiscatter GGX'),
evaluated from G-buffers alone: F_beta source ``model`` (pure numpy; see docs/brdf.md).

What Cycles does for an opaque Principled BSDF (white specular tint, no coat, sheen or transmission), as read from
its kernel and re-derived here:

* GGX with alpha = roughness^2, height-correlated Smith masking-shadowing G2 = 1 / (1 + Lambda(i) + Lambda(o)).
* Energy compensation (Kulla-Conty style albedo scaling): a lobe of single-scattering albedo E_F(mu) is scaled
  so that its albedo becomes  E_F(mu) / E(mu) * (E(mu) + Fms (1 - E(mu))),  where E is the albedo with F = 1,
  Fms = Fss E_avg / (1 - Fss (1 - E_avg)), E_avg = 2 int E(mu) mu dmu and Fss the cosine-weighted mean Fresnel.
* The Fresnel of each lobe is linear in (F0, 1): F = mix(F0, 1, s(VoH)), so E_F = E mix(F0, 1, S(mu)) with
  S = int s(VoH) D G2 / (4 mu) / E. Metals (F82-tint with white tint = Schlick): s = (1 - VoH)^5, F0 = base colour,
  Fss = mix(F0, 1, 1/21). Dielectric specular: s = (F_real(VoH, eta) - F0) / (1 - F0) with the real dielectric
  Fresnel of the IOR eta that gives F0 (the clip's ``specular`` buffer, which already holds the
  specular-IOR-level adjustment), Fss = clamp(fit(eta), F0, 1), fit(eta) = (eta - 1) / (4.08567 + 1.00071 eta)
  (Kulla-Conty's fit of the mean dielectric Fresnel, as Cycles uses it).
* Layering: the diffuse (Lambert, albedo = base colour) lies under the dielectric specular and gets the weight
  1 - min(1, specular albedo); metallic m mixes:  F = m metal + (1 - m) (spec + c (1 - spec)).

Tables (computed once, cached as .npz next to the split-sum LUT): E(r, mu), E_avg(r), S5(r, mu) and
S_ior(r, mu, z) with z = F0^(1/4) (= sqrt((eta-1)/(eta+1)), Cycles' own parametrisation), on grids with end
points (r = i/(N-1), mu = j/(N-1), mu clamped to >= MU_MIN), by GGX visible-normal (VNDF) sampling of a Hammersley
set, so every sample weight G2/G1 lies in [0, 1].

Not modelled (the G-buffers do not carry them): transmission/glass, coat, sheen, subsurface, anisotropy,
specular tint, thin film, alpha, the non-multiscatter 'GGX' distribution, Oren-Nayar diffuse roughness.
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from .errors import BlendSRError

#: Bump when the model tables change.
MODEL_VERSION = 1
MU_MIN = 1e-3


@dataclass(frozen=True)
class ModelSpec:
    """Grid sizes (n_rough x n_mu, n_z for the dielectric Fresnel axis) and Hammersley samples per cell."""

    n_rough: int = 64
    n_mu: int = 64
    n_z: int = 33
    samples: int = 4096

    def __post_init__(self):
        for name in ("n_rough", "n_mu", "n_z"):
            if not 2 <= getattr(self, name) <= 1024:
                raise BlendSRError(f"model table {name} must be in [2, 1024]")
        if not 16 <= self.samples <= 1 << 20:
            raise BlendSRError("model table samples must be in [16, 2^20]")

    @property
    def key(self) -> str:
        return f"brdf_model_v{MODEL_VERSION}_{self.n_rough}x{self.n_mu}x{self.n_z}_{self.samples}spp"


@dataclass(frozen=True)
class ModelTables:
    spec: ModelSpec
    e: np.ndarray       # n_rough x n_mu, albedo with F = 1
    e_avg: np.ndarray   # n_rough, cosine-weighted mean of E
    s5: np.ndarray      # n_rough x n_mu, Schlick interpolation factor (normalised by E)
    s_ior: np.ndarray   # n_rough x n_mu x n_z, real-dielectric interpolation factor (normalised by E)


# ----------------------------------------------------------------------------------------------
# Physics helpers
# ----------------------------------------------------------------------------------------------

def fresnel_dielectric(cos_i: np.ndarray, eta) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a dielectric interface of relative IOR eta >= 1 at cos(theta_i)."""
    c = np.abs(cos_i)
    g2 = eta * eta - 1.0 + c * c
    g = np.sqrt(np.maximum(g2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (g - c) / (g + c)
        b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
        f = 0.5 * a * a * (1.0 + b * b)
    return np.where(g2 > 0, np.nan_to_num(f, nan=1.0), 1.0)


def eta_from_f0(f0) -> np.ndarray:
    """IOR whose normal-incidence reflectance is F0 (F0 clamped below 1)."""
    r = np.sqrt(np.clip(f0, 0.0, 0.999999))
    return (1.0 + r) / (1.0 - r)


def dielectric_fss_fit(eta) -> np.ndarray:
    """Kulla-Conty's fit of the cosine-weighted mean dielectric Fresnel, eta >= 1."""
    eta = np.asarray(eta, dtype=np.float64)
    return (eta - 1.0) / (4.08567 + 1.00071 * eta)


def smith_lambda(alpha, cos_t) -> np.ndarray:
    """GGX Smith Lambda for a direction at cos(theta) = cos_t."""
    c2 = np.maximum(cos_t * cos_t, 1e-12)
    return 0.5 * (np.sqrt(1.0 + alpha * alpha * np.maximum(1.0 / c2 - 1.0, 0.0)) - 1.0)


# ----------------------------------------------------------------------------------------------
# Table generation
# ----------------------------------------------------------------------------------------------

def _vndf_row(alpha: float, mu: np.ndarray, u1: np.ndarray, u2: np.ndarray):
    """VoH (n_mu x S) and sample weights G2/G1 (0 where the reflected direction is below the surface)."""
    vx = np.sqrt(np.maximum(0.0, 1.0 - mu * mu))[:, None]
    vz = mu[:, None]
    # stretched view direction and its basis
    hx, hz = alpha * vx, vz
    norm = np.sqrt(hx * hx + hz * hz)
    hx, hz = hx / norm, hz / norm
    degenerate = hx < 1e-7
    # T1 = (0, 1, 0), T2 = (-hz, 0, hx); degenerate (V = N): T1 = (1, 0, 0), T2 = (0, 1, 0)
    rr = np.sqrt(u1)[None, :]
    phi = (2.0 * np.pi * u2)[None, :]
    t1, t2 = rr * np.cos(phi), rr * np.sin(phi)
    s = 0.5 * (1.0 + hz)
    t2 = (1.0 - s) * np.sqrt(np.maximum(0.0, 1.0 - t1 * t1)) + s * t2
    tz = np.sqrt(np.maximum(0.0, 1.0 - t1 * t1 - t2 * t2))
    nx = np.where(degenerate, t1, -t2 * hz + tz * hx)
    ny = np.where(degenerate, t2, t1)
    nz = np.where(degenerate, tz, t2 * hx + tz * hz)
    mx, my, mz = alpha * nx, alpha * ny, np.maximum(nz, 1e-9)
    inv = 1.0 / np.sqrt(mx * mx + my * my + mz * mz)
    mx, mz = mx * inv, mz * inv
    voh = vx * mx + vz * mz
    nol = 2.0 * voh * mz - vz
    lam_v = smith_lambda(alpha, mu)[:, None]
    lam_l = smith_lambda(alpha, np.maximum(nol, 1e-6))
    w = np.where(nol > 0, (1.0 + lam_v) / (1.0 + lam_v + lam_l), 0.0)
    return np.clip(voh, 0.0, 1.0), w


def _hammersley(n: int):
    from .brdf_common import hammersley

    return hammersley(n)


def grid(n: int, lo: float = 0.0) -> np.ndarray:
    """n end-point-inclusive values i/(n-1), clamped below at ``lo``."""
    return np.maximum(np.linspace(0.0, 1.0, n), lo)


def generate_model_tables(spec: ModelSpec = ModelSpec()) -> ModelTables:
    """Integrate E, S5 and S_ior on the grids of ``spec`` (seconds; threads over roughness rows)."""
    import concurrent.futures

    u1, u2 = _hammersley(spec.samples)
    # shift the Hammersley set by half a cell in u1 so that u1 = 0 (a disk-centre sample) is not over-weighted
    u1 = u1 + 0.5 / spec.samples
    rough = grid(spec.n_rough)
    mu = grid(spec.n_mu, MU_MIN)
    z = np.linspace(0.0, 1.0, spec.n_z)
    f0z = np.minimum(z ** 4, 0.999999)
    etaz = eta_from_f0(f0z)
    e = np.zeros((spec.n_rough, spec.n_mu))
    s5 = np.zeros_like(e)
    s_ior = np.zeros((spec.n_rough, spec.n_mu, spec.n_z))

    def row(i):
        alpha = rough[i] ** 2
        voh, w = _vndf_row(alpha, mu, u1, u2)
        ei = w.mean(axis=1)
        safe = np.maximum(ei, 1e-12)
        e[i] = ei
        t = 1.0 - voh
        s5[i] = (w * (t * t) * (t * t) * t).mean(axis=1) / safe
        for k in range(spec.n_z):
            if f0z[k] <= 0:
                continue  # eta = 1: no specular reflection, s = 0
            f = fresnel_dielectric(voh, etaz[k])
            sk = np.clip((f - f0z[k]) / (1.0 - f0z[k]), 0.0, 1.0)
            s_ior[i, :, k] = (w * sk).mean(axis=1) / safe

    with concurrent.futures.ThreadPoolExecutor(os.cpu_count() or 1) as ex:
        list(ex.map(row, range(spec.n_rough)))
    # E_avg = 2 int_0^1 E(mu) mu dmu by Gauss-Legendre on fresh E evaluations (not the grid)
    xg, wg = np.polynomial.legendre.leggauss(48)
    mug = 0.5 * (xg + 1.0)
    e_avg = np.empty(spec.n_rough)
    for i in range(spec.n_rough):
        _, w = _vndf_row(rough[i] ** 2, mug, u1, u2)
        e_avg[i] = np.sum(0.5 * wg * 2.0 * mug * w.mean(axis=1))
    return ModelTables(spec, e.astype(np.float32), e_avg.astype(np.float32), s5.astype(np.float32),
                       s_ior.astype(np.float32))


# ----------------------------------------------------------------------------------------------
# Cache
# ----------------------------------------------------------------------------------------------

def save_model_tables(path: str | os.PathLike, t: ModelTables) -> None:
    """Write the tables as .npz atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.npz")
    try:
        np.savez(tmp, e=t.e, e_avg=t.e_avg, s5=t.s5, s_ior=t.s_ior, version=MODEL_VERSION)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def load_model_tables(path: str | os.PathLike, spec: ModelSpec) -> ModelTables:
    """Read tables written by ``save_model_tables``; ValueError when they do not match ``spec``."""
    try:
        with np.load(path) as z:
            t = ModelTables(spec, z["e"], z["e_avg"], z["s5"], z["s_ior"])
            version = int(z["version"])
    except (OSError, KeyError, ValueError, EOFError) as exc:
        raise BlendSRError(f"{path}: unreadable model tables ({exc})") from None
    if (version != MODEL_VERSION or t.e.shape != (spec.n_rough, spec.n_mu)
            or t.s_ior.shape != (spec.n_rough, spec.n_mu, spec.n_z) or t.e_avg.shape != (spec.n_rough,)):
        raise BlendSRError(f"{path}: model tables do not match {spec}")
    if not all(np.all(np.isfinite(a)) for a in (t.e, t.e_avg, t.s5, t.s_ior)):
        raise BlendSRError(f"{path}: model tables hold non-finite values")
    return t


def load_or_generate_model_tables(spec: ModelSpec = ModelSpec()) -> ModelTables:
    """The model tables from the disk cache (``brdf.cache_dir()``), generated and written when absent."""
    from .brdf_common import cache_dir

    return _load_or_generate(spec, str(cache_dir()))


@functools.lru_cache(maxsize=4)
def _load_or_generate(spec: ModelSpec, cache: str) -> ModelTables:
    from .brdf_common import load_or_generate_file

    return load_or_generate_file(Path(cache) / f"{spec.key}.npz", lambda p: load_model_tables(p, spec),
                                 lambda: generate_model_tables(spec), save_model_tables, (ValueError,))


# ----------------------------------------------------------------------------------------------
# Lookup and evaluation
# ----------------------------------------------------------------------------------------------

def _axis(u: np.ndarray, n: int, lo: float = 0.0):
    """Indices and weight for linear interpolation on the end-point grid max(i/(n-1), lo)."""
    x = np.clip(np.nan_to_num(np.asarray(u, dtype=np.float64), nan=0.0), 0.0, 1.0)
    g = grid(n, lo)
    i1 = np.clip(np.searchsorted(g, x, side="right"), 1, n - 1)
    i0 = i1 - 1
    w = np.clip((x - g[i0]) / np.maximum(g[i1] - g[i0], 1e-12), 0.0, 1.0)
    return i0, i1, w


def lookup2(table: np.ndarray, rough, mu) -> np.ndarray:
    """Bilinear lookup of an n_rough x n_mu table."""
    i0, i1, wr = _axis(rough, table.shape[0])
    j0, j1, wm = _axis(mu, table.shape[1], MU_MIN)
    t = table.astype(np.float64)
    return ((t[i0, j0] * (1 - wm) + t[i0, j1] * wm) * (1 - wr) + (t[i1, j0] * (1 - wm) + t[i1, j1] * wm) * wr)


def lookup3(table: np.ndarray, rough, mu, z) -> np.ndarray:
    """Trilinear lookup of an n_rough x n_mu x n_z table."""
    k0, k1, wz = _axis(z, table.shape[2])
    return _lookup2_slices(table, rough, mu, k0) * (1 - wz) + _lookup2_slices(table, rough, mu, k1) * wz


def _lookup2_slices(table, rough, mu, k):
    i0, i1, wr = _axis(rough, table.shape[0])
    j0, j1, wm = _axis(mu, table.shape[1], MU_MIN)
    t = table.astype(np.float64)
    return ((t[i0, j0, k] * (1 - wm) + t[i0, j1, k] * wm) * (1 - wr)
            + (t[i1, j0, k] * (1 - wm) + t[i1, j1, k] * wm) * wr)


def lookup1(table: np.ndarray, rough) -> np.ndarray:
    i0, i1, w = _axis(rough, table.shape[0])
    t = table.astype(np.float64)
    return t[i0] * (1 - w) + t[i1] * w


def fms(fss, e_avg):
    """Kulla-Conty multiple-scattering Fresnel factor."""
    return fss * e_avg / np.maximum(1.0 - fss * (1.0 - e_avg), 1e-12)


def principled_albedo(c, roughness, metallic, f0_dielectric, nov, tables: ModelTables | None = None) -> np.ndarray:
    """Directional albedo of an opaque Principled BSDF. c: ... x 3 (>= 0), the rest ... (same leading shape).
    Returns float64 ... x 3."""
    t = tables if tables is not None else load_or_generate_model_tables()
    r = np.clip(roughness, 0.0, 1.0)
    mu = np.clip(nov, 0.0, 1.0)
    m = np.clip(metallic, 0.0, 1.0)[..., None]
    f0d = np.clip(f0_dielectric, 0.0, 1.0)
    c = np.maximum(c, 0.0)
    e = lookup2(t.e, r, mu)[..., None]
    e_avg = lookup1(t.e_avg, r)[..., None]
    # metal: Schlick (F82-tint with white tint), F0 = clamped base colour
    f0m = np.minimum(c, 1.0)
    s5 = lookup2(t.s5, r, mu)[..., None]
    metal = (f0m + (1.0 - f0m) * s5) * (e + fms(f0m + (1.0 - f0m) / 21.0, e_avg) * (1.0 - e))
    # dielectric specular over Lambert
    z = f0d ** 0.25
    s = lookup3(t.s_ior, r, mu, z)
    eta = eta_from_f0(f0d)
    fss = np.clip(dielectric_fss_fit(eta), f0d, 1.0)
    spec = ((f0d + (1.0 - f0d) * s)[..., None]
            * (e + fms(fss, e_avg[..., 0])[..., None] * (1.0 - e)))
    spec = np.where((f0d > 0)[..., None], spec, 0.0)
    diel = spec + c * (1.0 - np.minimum(spec, 1.0))
    return m * metal + (1.0 - m) * diel


def model_fbeta(mat, nov: np.ndarray, tables: ModelTables | None = None) -> np.ndarray:
    """F_beta (H x W x 3 float64) of ``brdf.Material`` at NoV (H x W)."""
    return principled_albedo(mat.c, mat.roughness, mat.metallic, mat.f0_dielectric, nov, tables)


__all__ = ["ModelSpec", "ModelTables", "generate_model_tables", "load_or_generate_model_tables", "principled_albedo",
           "model_fbeta", "fresnel_dielectric", "eta_from_f0", "dielectric_fss_fit", "smith_lambda"]
