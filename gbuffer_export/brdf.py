"""Pre-integrated BRDF (F_beta) from G-buffers: split-sum lookup tables, their cache, and the per-pixel sources
``lut``, ``lut-paper`` and ``model`` (pure numpy; see ``docs/brdf.md``).

Split-sum table (Karis 2013; NSRD supplement eq. 15-18). For cos(theta_o) = NoV and perceptual roughness r,

    A(NoV, r) = 1/S sum_s G_vis(l_s) (1 - Fc_s),   B(NoV, r) = 1/S sum_s G_vis(l_s) Fc_s,
    G_vis = G(l, v) VoH / (NoH NoV),   Fc = (1 - VoH)^5,

over GGX-importance-sampled half vectors from a Hammersley set of S points, so that the specular directional
albedo with Schlick Fresnel is F0 * A + B. Conventions:

``ibl`` (default; Karis' image-based-lighting table, learnopengl):  alpha = r^2 in D and in the sampling,
    Schlick-Smith G1(x) = x / (x (1 - k) + k) with k = alpha / 2.
``paper`` (the NSRD supplement read literally, eq. 5, 9, 10): alpha = r in D and in the sampling,
    k = (alpha + 1)^2 / 8 (Karis' remap for analytic lights).

G / NoV is written as G1(l) / (NoV (1 - k) + k), so NoV = 0 stays finite.

Table layout: an N x N table, texel (row i, column j) holds the values at roughness (i + 0.5) / N and
NoV = (j + 0.5) / N. Lookups interpolate bilinearly between texel centres and clamp at the borders.

Per-pixel F_beta (``compute_fbeta``), H x W x 3 float32, 1 on background pixels:

``lut``        F = (1 - m) c + F0 A(NoV, r) + B(NoV, r),  F0 = lerp(F0_dielectric, c, m), where F0_dielectric is
               the clip's ``specular`` buffer, ((ior - 1)/(ior + 1))^2 * 2 * specular_ior_level (0.04 for the
               Principled defaults IOR 1.5 and level 0.5), table convention ``ibl``.
``lut-paper``  the same with the ``paper`` table and F0 = lerp(0.04, c, m) (eq. 7 literally: the specular
               buffer is ignored).
``model``      ``gbuffer_export.brdf_model``: a table-based model of Cycles' Principled BSDF.

NoV comes from the camera-space shading normal and the view direction of the pixel's ray through the
intrinsics at pixel centre + jitter (``compute_nov``).
"""
from __future__ import annotations

import concurrent.futures
import functools
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import BlendSRError
from .brdf_common import cache_dir, hammersley, load_or_generate_file, radical_inverse_base2  # noqa: F401
from .conventions import Flag, pixel_grid, rays_camera

log = logging.getLogger(__name__)

CONVENTIONS = ("ibl", "paper")
SOURCES = ("lut", "lut-paper", "model")
#: Bump when the table generator changes: cached tables of other versions are not reused.
LUT_VERSION = 1
DEFAULT_SIZE = 256
DEFAULT_SAMPLES = 16384
#: Elements per work block of the generator (columns x samples); bounds memory to a few MB per thread.
_BLOCK = 1 << 18


@dataclass(frozen=True)
class LutSpec:
    """Parameters of a split-sum table: ``size`` x ``size`` texels, ``samples`` Hammersley points per texel."""

    size: int = DEFAULT_SIZE
    samples: int = DEFAULT_SAMPLES
    convention: str = "ibl"

    def __post_init__(self):
        if not (isinstance(self.size, (int, np.integer)) and 2 <= self.size <= 4096):
            raise BlendSRError(f"LUT size {self.size!r} must be an integer in [2, 4096]")
        if not (isinstance(self.samples, (int, np.integer)) and 1 <= self.samples <= 1 << 22):
            raise BlendSRError(f"LUT samples {self.samples!r} must be an integer in [1, {1 << 22}]")
        if self.convention not in CONVENTIONS:
            raise BlendSRError(f"LUT convention {self.convention!r} must be one of {', '.join(CONVENTIONS)}")

    @property
    def key(self) -> str:
        """File-name key of the cached table: every parameter that changes its content."""
        return f"brdf_lut_v{LUT_VERSION}_{self.convention}_{self.size}x{self.size}_{self.samples}spp"


@dataclass(frozen=True)
class Lut:
    """A split-sum table: ``a`` and ``b`` are size x size float32 (rows roughness, columns NoV)."""

    spec: LutSpec
    a: np.ndarray
    b: np.ndarray

    def lookup(self, nov: np.ndarray, roughness: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(A, B) at NoV and roughness (same-shape arrays), bilinear between texel centres."""
        return lookup_ab(self.a, self.b, nov, roughness)


# ----------------------------------------------------------------------------------------------
# Generation
# ----------------------------------------------------------------------------------------------

def alpha_k(roughness, convention: str = "ibl"):
    """GGX alpha and Schlick-Smith k of a perceptual roughness (scalar or array) in a table convention."""
    r = np.clip(np.asarray(roughness, dtype=np.float64), 0.0, 1.0)
    if convention == "ibl":
        alpha = r * r
        return alpha, alpha / 2.0
    if convention == "paper":
        return r, (r + 1.0) ** 2 / 8.0
    raise BlendSRError(f"unknown table convention {convention!r}; use one of {', '.join(CONVENTIONS)}")


def _row_ab(nov: np.ndarray, alpha: float, k: float, u1: np.ndarray, u2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A and B (float64, shape of ``nov``) for one alpha over the columns ``nov`` (1-D, in (0, 1])."""
    a2 = alpha * alpha
    cos_h = np.sqrt((1.0 - u1) / (1.0 + (a2 - 1.0) * u1))
    sin_h = np.sqrt(np.maximum(0.0, 1.0 - cos_h * cos_h))
    phi = 2.0 * np.pi * u2
    hx = (sin_h * np.cos(phi)).astype(np.float32)  # V lies in the xz plane: the y component never enters
    hz = cos_h.astype(np.float32)
    w = (1.0 / cos_h).astype(np.float32)             # 1 / NoH (cos_h > 0 since u1 < 1)
    vz = nov.astype(np.float32)
    vx = np.sqrt(np.maximum(0.0, 1.0 - nov * nov)).astype(np.float32)
    ncol, ns = nov.size, u1.size
    step = max(1, _BLOCK // max(ncol, 1))
    sum_g = np.zeros(ncol)
    sum_b = np.zeros(ncol)
    k32 = np.float32(k)
    one_k = np.float32(1.0 - k)
    for s0 in range(0, ns, step):
        sl = slice(s0, min(ns, s0 + step))
        voh = np.multiply.outer(vx, hx[sl])
        voh += np.multiply.outer(vz, hz[sl])
        np.maximum(voh, 0.0, out=voh)
        nol = voh * hz[sl]                 # NoL = 2 VoH NoH - NoV
        nol *= 2.0
        nol -= vz[:, None]
        np.maximum(nol, 0.0, out=nol)
        den = nol * one_k
        den += k32
        den += np.float32(1e-30)           # k = 0 (alpha = 0): G1 = 1 where NoL > 0, 0 where NoL = 0
        g = np.divide(nol, den, out=nol)   # G1(l)
        g *= voh
        g *= w[sl]                         # G1(l) VoH / NoH; the 1 / (NoV (1-k) + k) factor is per column
        t = np.subtract(1.0, voh, out=voh)
        fc = t * t
        fc *= fc
        fc *= t                            # (1 - VoH)^5
        sum_g += g.sum(axis=1, dtype=np.float64)
        sum_b += np.einsum("ij,ij->i", g, fc, dtype=np.float64)
    gv = 1.0 / (nov * (1.0 - k) + k)
    b = gv * sum_b / ns
    a = gv * (sum_g - sum_b) / ns
    return a, b


def integrate_ab(nov, roughness, samples: int = DEFAULT_SAMPLES, convention: str = "ibl",
                 workers: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Split-sum (A, B) by GGX importance sampling of a ``samples``-point Hammersley set, at arbitrary
    NoV and roughness (broadcast together; NoV is clamped to [1e-6, 1], roughness to [0, 1]). float64 arrays."""
    nov_b, r_b = np.broadcast_arrays(np.asarray(nov, dtype=np.float64), np.asarray(roughness, dtype=np.float64))
    shape = nov_b.shape
    nov_f = np.clip(nov_b.ravel(), 1e-6, 1.0)
    r_f = np.clip(r_b.ravel(), 0.0, 1.0)
    u1, u2 = hammersley(int(samples))
    a = np.empty(nov_f.size)
    b = np.empty(nov_f.size)
    groups = [np.flatnonzero(r_f == r) for r in np.unique(r_f)]

    def work(idx):
        alpha, k = alpha_k(r_f[idx[0]], convention)
        a[idx], b[idx] = _row_ab(nov_f[idx], float(alpha), float(k), u1, u2)

    workers = workers or min(len(groups), os.cpu_count() or 1)
    if workers > 1:
        with concurrent.futures.ThreadPoolExecutor(workers) as ex:
            list(ex.map(work, groups))
    else:
        for g in groups:
            work(g)
    return a.reshape(shape), b.reshape(shape)


def texel_centres(size: int) -> np.ndarray:
    """(i + 0.5) / size for i = 0..size-1: the roughness of row i and the NoV of column i."""
    return (np.arange(size) + 0.5) / size


def generate_lut(spec: LutSpec = LutSpec(), workers: int | None = None) -> Lut:
    """Compute a split-sum table (threads over roughness rows; numpy releases the GIL)."""
    log.debug("split-sum table: %dx%d texels, %d samples each, %s convention", spec.size, spec.size, spec.samples,
              spec.convention)
    c = texel_centres(spec.size)
    nov, r = np.meshgrid(c, c, indexing="xy")  # rows: roughness, columns: NoV
    a, b = integrate_ab(nov, r, spec.samples, spec.convention, workers)
    return Lut(spec, a.astype(np.float32), b.astype(np.float32))


# ----------------------------------------------------------------------------------------------
# Lookup
# ----------------------------------------------------------------------------------------------

def _bilinear_coords(u: np.ndarray, n: int):
    x = np.clip(np.nan_to_num(np.asarray(u, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    x = np.clip(x * n - 0.5, 0.0, n - 1.0)
    i0 = np.minimum(np.floor(x).astype(np.intp), n - 1)
    i1 = np.minimum(i0 + 1, n - 1)
    return i0, i1, x - i0


def lookup_table(table: np.ndarray, nov, roughness) -> np.ndarray:
    """Bilinear texel-centre lookup of an N x N table (rows roughness, columns NoV) at NoV and roughness
    (clamped to [0, 1]; NaN reads as 0). Returns float64 of the broadcast shape."""
    nov, roughness = np.broadcast_arrays(np.asarray(nov), np.asarray(roughness))
    n_r, n_v = table.shape
    j0, j1, fx = _bilinear_coords(nov, n_v)
    i0, i1, fy = _bilinear_coords(roughness, n_r)
    t = np.asarray(table, dtype=np.float64)
    top = t[i0, j0] * (1 - fx) + t[i0, j1] * fx
    bot = t[i1, j0] * (1 - fx) + t[i1, j1] * fx
    return top * (1 - fy) + bot * fy


def lookup_ab(a: np.ndarray, b: np.ndarray, nov, roughness) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) from tables ``a`` and ``b`` at NoV and roughness (see ``lookup_table``)."""
    return lookup_table(a, nov, roughness), lookup_table(b, nov, roughness)


# ----------------------------------------------------------------------------------------------
# EXR and cache
# ----------------------------------------------------------------------------------------------

def write_lut(path: str | os.PathLike, lut: Lut) -> None:
    """Write ``lut`` as a float32 EXR with channels A and B (atomic), its parameters in the header."""
    from .exr import write_exr

    attrs = {"blendsr_lut": f"convention={lut.spec.convention} size={lut.spec.size} samples={lut.spec.samples} "
                            f"version={LUT_VERSION} rows=roughness cols=NoV texel_centres=(i+0.5)/N"}
    write_exr(path, {"A": lut.a, "B": lut.b}, half=False, attributes=attrs)


def read_lut(path: str | os.PathLike, spec: LutSpec | None = None) -> Lut:
    """Read a table EXR (channels A and B, square). ``spec`` is recorded as given (default: size from the file,
    samples and convention unknown -> the defaults)."""
    from .exr import ExrError, read_exr

    ab = read_exr(path, ("A", "B"))
    if ab.shape[0] != ab.shape[1]:
        raise ExrError(f"{path}: LUT must be square, got {ab.shape[1]}x{ab.shape[0]}")
    if not np.all(np.isfinite(ab)):
        raise ExrError(f"{path}: LUT holds non-finite values")
    spec = spec or LutSpec(size=int(ab.shape[0]))
    if spec.size != ab.shape[0]:
        raise ExrError(f"{path}: LUT is {ab.shape[0]}x{ab.shape[0]}, expected {spec.size}x{spec.size}")
    return Lut(spec, np.ascontiguousarray(ab[..., 0]), np.ascontiguousarray(ab[..., 1]))


def default_spec(convention: str = "ibl") -> LutSpec:
    """The table ``compute_fbeta`` uses: DEFAULT_SIZE x DEFAULT_SIZE, DEFAULT_SAMPLES samples (read at call time)."""
    return LutSpec(size=DEFAULT_SIZE, samples=DEFAULT_SAMPLES, convention=convention)


def cached_lut_path(spec: LutSpec) -> Path:
    return cache_dir() / f"{spec.key}.exr"


def load_or_generate_lut(spec: LutSpec = LutSpec()) -> Lut:
    """The table of ``spec`` from the disk cache, generated and written there (atomically) when absent or
    unreadable. Memoised per process and cache directory."""
    return _load_or_generate(spec, str(cache_dir()))


@functools.lru_cache(maxsize=8)
def _load_or_generate(spec: LutSpec, cache: str) -> Lut:
    from .exr import ExrError

    return load_or_generate_file(Path(cache) / f"{spec.key}.exr", lambda p: read_lut(p, spec),
                                 lambda: generate_lut(spec), write_lut, (ExrError,))


# ----------------------------------------------------------------------------------------------
# Per-pixel quantities
# ----------------------------------------------------------------------------------------------

def _hw(a: np.ndarray, name: str) -> np.ndarray:
    """H x W x 1 or H x W -> H x W float64 with NaN/Inf replaced by 0."""
    a = np.asarray(a)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise ValueError(f"G-buffer {name!r} has shape {a.shape}; expected H x W x 1")
    return np.nan_to_num(a.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)


def compute_nov(normal: np.ndarray, intrinsics, jitter=(0.0, 0.0)) -> np.ndarray:
    """cos(theta_o) per pixel (H x W float32 in [0, 1]) from the camera-space shading normal (H x W x 3) and the
    view direction towards the camera along the ray through pixel centre + jitter.

    Handling: normals are renormalised (edge pixels average normals); a back-facing normal (N.V < 0) is
    mirrored, NoV = |N.V|, as Cycles flips the normal of a surface seen from behind (two-sided shading) and
    shading normals bent past the silhouette then read as grazing; a zero or non-finite normal gives NoV = 1."""
    n = np.nan_to_num(np.asarray(normal, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normal has shape {n.shape}; expected H x W x 3")
    h, w = n.shape[:2]
    xs, ys = pixel_grid(h, w)
    d = rays_camera(xs + float(jitter[0]), ys + float(jitter[1]), tuple(float(v) for v in intrinsics))
    v = -d / np.linalg.norm(d, axis=-1, keepdims=True)
    norm = np.linalg.norm(n, axis=-1)
    dot = np.sum(n * v, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        nov = np.where(norm > 1e-8, np.abs(dot) / np.where(norm > 1e-8, norm, 1.0), 1.0)
    return np.clip(nov, 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class Material:
    """Per-pixel Principled parameters from G-buffers, H x W (x 3 for ``c``), float64, sanitised and clamped."""

    c: np.ndarray          # base colour, >= 0
    roughness: np.ndarray  # [0, 1]
    metallic: np.ndarray   # [0, 1]
    f0_dielectric: np.ndarray  # [0, 1], the ``specular`` buffer
    background: np.ndarray  # bool


def material_from_gbuf(gbuf: dict[str, np.ndarray]) -> Material:
    """Read and sanitise albedo, roughness, metallic, specular and flags (NaN -> 0, values clamped)."""
    for key in ("albedo", "normal", "roughness", "metallic", "specular"):
        if key not in gbuf:
            raise ValueError(f"G-buffers lack {key!r} (have {', '.join(sorted(gbuf))})")
    c = np.asarray(gbuf["albedo"], dtype=np.float64)
    if c.ndim != 3 or c.shape[2] != 3:
        raise ValueError(f"G-buffer 'albedo' has shape {c.shape}; expected H x W x 3")
    c = np.maximum(np.nan_to_num(c, nan=0.0, posinf=1.0, neginf=0.0), 0.0)
    r = np.clip(_hw(gbuf["roughness"], "roughness"), 0.0, 1.0)
    m = np.clip(_hw(gbuf["metallic"], "metallic"), 0.0, 1.0)
    s = np.clip(_hw(gbuf["specular"], "specular"), 0.0, 1.0)
    flags = gbuf.get("flags")
    if flags is None:
        bg = np.zeros(c.shape[:2], dtype=bool)
    else:
        f = np.asarray(flags)
        if f.ndim == 3:
            f = f[..., 0]
        bg = (f.astype(np.uint32) & np.uint32(Flag.BACKGROUND)) != 0
    for name, a in (("roughness", r), ("metallic", m), ("specular", s), ("flags", bg)):
        if a.shape != c.shape[:2]:
            raise ValueError(f"G-buffer {name!r} is {a.shape[1]}x{a.shape[0]}, albedo is {c.shape[1]}x{c.shape[0]}")
    return Material(c, r, m, s, bg)


def split_sum_fbeta(c, metallic, f0_dielectric, a, b) -> np.ndarray:
    """F = (1 - m) c + F0 A + B with F0 = lerp(F0_dielectric, c, m); c H x W x 3, the rest H x W. float64."""
    m = np.asarray(metallic)[..., None]
    f0 = (1.0 - m) * np.asarray(f0_dielectric)[..., None] + m * c
    return (1.0 - m) * c + f0 * np.asarray(a)[..., None] + np.asarray(b)[..., None]


#: Upper end of a table source's F_beta. The split-sum formula F = (1 - m) c + F0 A + B adds the diffuse albedo c
#: to the specular albedo F0 A + B without the energy split of a layered BSDF (Cycles and ``model`` weight the
#: diffuse by 1 - the specular albedo), so on a bright dielectric at grazing angles it exceeds 1: up to 1.9 for a
#: white smooth one (B -> 1 as NoV -> 0). A directional albedo above 1 is not physical, and ``validate`` refuses
#: F_beta above its ``fbeta_max`` (1.05): every table source clamps to 1, which is also the layered value for white.
FBETA_MAX = 1.0


def compute_fbeta(source: str, gbuf: dict[str, np.ndarray], intrinsics, jitter=(0.0, 0.0),
                  lut: Lut | None = None) -> np.ndarray:
    """F_beta (H x W x 3 float32, finite, in [0, FBETA_MAX]; 1.0 on background pixels) of a table source from
    G-buffers.

    source: 'lut', 'lut-paper' or 'model' (see the module doc). gbuf: albedo (H x W x 3), normal (H x W x 3,
    camera space), roughness, metallic, specular (H x W x 1 each), optional flags (H x W x 1 uint32).
    intrinsics (fx, fy, cx, cy) and jitter (dx, dy) in pixels of this level. ``lut`` overrides the cached table
    (for 'lut'/'lut-paper')."""
    if source not in SOURCES:
        raise BlendSRError(f"unknown F_beta source {source!r}; use one of {', '.join(SOURCES)} "
                         "('cycles' comes from the renderer's colour passes)")
    mat = material_from_gbuf(gbuf)
    nov = compute_nov(gbuf["normal"], intrinsics, jitter).astype(np.float64)
    if source == "model":
        from .brdf_model import model_fbeta

        f = model_fbeta(mat, nov)
    else:
        convention = "ibl" if source == "lut" else "paper"
        table = lut if lut is not None else load_or_generate_lut(default_spec(convention))
        a, b = table.lookup(nov, mat.roughness)
        f0d = mat.f0_dielectric if source == "lut" else np.full_like(mat.roughness, 0.04)
        f = split_sum_fbeta(mat.c, mat.metallic, f0d, a, b)
    f = np.minimum(np.nan_to_num(f, nan=1.0, posinf=1.0, neginf=0.0), FBETA_MAX)  # see FBETA_MAX
    f = np.where(mat.background[..., None], 1.0, f)
    return f.astype(np.float32)


__all__ = ["LutSpec", "Lut", "CONVENTIONS", "SOURCES", "FBETA_MAX", "alpha_k", "hammersley", "integrate_ab",
           "generate_lut", "lookup_table", "lookup_ab", "write_lut", "read_lut", "cache_dir", "cached_lut_path",
           "load_or_generate_lut", "default_spec", "compute_nov", "compute_fbeta", "split_sum_fbeta",
           "material_from_gbuf", "Material", "texel_centres"]
