"""A level's unit: how many metres one scene unit depicts, detected from its geometry (numpy + ``LevelGeometry``;
no bpy, so it is tested on synthetic rooms).

Game levels arrive in the unit of their engine: Unreal levels in centimetres, Source and Quake ones in inches,
glTF and Unity ones in metres, whatever a file declares. Level cameras (``level_cameras``) walk at 1.4 m/s with
the eye 1.6 m above the floor: in a level of centimetres read as metres the eye would stand 1.6 cm above the ground.
``detect_unit_scale`` measures four cues in scene units:

headroom
    along vertical rays through a ``COLUMNS`` x ``COLUMNS`` grid over the level's content box (every hit of each
    ray), the median free height between a floor (a surface facing up, within 45 degrees of horizontal, inside the
    content box's heights give or take 10 %) and the ceiling right above it (a surface facing down), over the
    floors that have one; a ceiling on an object that encloses the level (a skybox, ``LevelGeometry``'s
    enclosing rule) is sky, not a ceiling. Used when at least
    ``MIN_COVERED`` columns and ``MIN_COVERED_FRACTION`` of the floors are covered (an interior, or a town with
    roofs and bridges).
height
    the height of the level's content box (``LevelGeometry.content_bounds``: its triangles' 1st-99th percentile
    box, enclosing objects left out): a storey, a town's houses and slopes, a jungle's trees.
objects
    the median diagonal of the boxes of the level's objects (enclosing ones left out), when it has at least
    ``MIN_OBJECTS``: furniture, props, trees and houses are sized for people whatever the level's size (a 4 km
    open world in metres and a 200 m jungle in centimetres have about the same extent in units, not the same
    trees).
extent
    the diagonal of the level's content box (``LevelGeometry.extent``). Used only without headroom and objects:
    a level's size varies more than a room's height or a prop's size.

Each candidate unit ``u`` (``UNITS``, and the file's declared unit) is scored by how typical the cues are in
metres: the sum over the cues of ``-0.5 * (ln(x * u / typical) / sigma)^2`` with ``CUES``' typical metres and
sigmas (log-normal: a headroom of 3 m, within a factor 1.65 at one sigma; an object of 4 m, within a factor 2.2;
a height of 12 m and an extent of 100 m, far looser). The file's declared unit gets ``DECLARED_BONUS`` (about 3
sigma of one cue): a level is read in another unit only when its geometry makes the declared one implausible. The
best score wins.
"""
from __future__ import annotations

import math

import numpy as np

from .level_geometry import LevelGeometry

#: Candidate units (metres per unit), besides the file's declared one: "cube" is the unit of the Cube 2 engine
#: family (Sauerbraten, Tesseract, Red Eclipse: a player 15 units tall, eye 14 units above the feet, so about
#: 0.12 m); Quake's is about an inch (a player 56 units tall).
UNITS = {"m": 1.0, "in": 0.0254, "cm": 0.01, "cube": 0.12, "km": 1000.0}
#: Log-prior of the rarer candidates: a level is read in them only when its cues say so by a clear margin (a
#: jungle's canopy reads as a 14 m ceiling, which Cube units would make a 1.7 m one; a 26 cm bottle, whose size
#: alone says little, would be a 260 m tower in kilometres).
UNIT_PRIOR = {"cube": -2.0, "km": -8.0}
#: Text a level file opens with that names the engine it was exported from -> (unit name, metres per unit, why).
#: A file that names its engine declares its unit as a .blend's unit scale does (``DECLARED_BONUS``).
ENGINE_SIGNATURES = {
    "of cube 2 level": ("cube", 0.12, "written by the Cube 2 engine family's /writeobj (Sauerbraten, Tesseract, "
                                      "Red Eclipse): a player's eye stands 14 units above its feet"),
}
#: cue -> (typical metres, sigma of its natural log).
CUES = {"headroom": (3.0, 0.5), "objects": (4.0, 0.8), "height": (12.0, 1.2), "extent": (100.0, 1.5),
        "spawn": (1.5, 0.3)}
#: Object names of spawn points (player starts) in a level file: their height over the floor below is a person's.
SPAWN_NAMES = r"spawn|player.?start|info_player|start.?point"
DECLARED_BONUS = 4.5
COLUMNS = 48
MIN_COVERED = 24
MIN_COVERED_FRACTION = 0.15
MIN_OBJECTS = 8
FLAT_COS = math.cos(math.radians(45.0))  # level_cameras.WALKABLE_COS: a surface within 45 degrees of horizontal


def _columns(geom: LevelGeometry, n: int):
    """Per column of an ``n`` x ``n`` grid over the content box: the hits of one downward ray from above the
    level, top to bottom, as (heights, normal z, enclosing object?) arrays."""
    lo, hi = geom.content_bounds()
    blo, bhi = geom.bounds()
    top = bhi[2] + 0.01 * float(np.max(bhi - blo)) + 1e-6
    xs = np.linspace(lo[0], hi[0], n + 2)[1:-1]
    ys = np.linspace(lo[1], hi[1], n + 2)[1:-1]
    X, Y = np.meshgrid(xs, ys)
    origins = np.stack([X.ravel(), Y.ravel(), np.full(X.size, top)], axis=1)
    dirs = np.tile([0.0, 0.0, -1.0], (len(origins), 1))
    tri, ray, loc = geom.rays.intersects_id(origins, dirs, multiple_hits=True, return_locations=True)
    tri, ray = np.asarray(tri, np.int64), np.asarray(ray, np.int64)
    enclosing = ~geom._content_mask
    order = np.lexsort((-loc[:, 2], ray))  # by column, then from the top down
    z, tri, ray = loc[order, 2], tri[order], ray[order]
    out = []
    for idx in np.split(np.arange(len(ray)), np.nonzero(np.diff(ray))[0] + 1):
        if len(idx) == 0:
            continue
        zc, tc = z[idx], tri[idx]
        keep = np.concatenate([[True], np.diff(zc) < -1e-9 * max(1.0, abs(top))])  # one hit per surface
        out.append((zc[keep], geom.normals[tc[keep]][:, 2], enclosing[tc[keep]]))
    return out


def measure_cues(geom: LevelGeometry, n: int = COLUMNS) -> dict:
    """The cues of the module doc in scene units, with the counts they rest on."""
    eps = 1e-4 * max(geom.extent, 1e-9)
    gaps, floors = [], 0
    cols = _columns(geom, n)
    lo, hi = geom.content_bounds()
    margin = 0.1 * (hi[2] - lo[2]) + eps
    for z, nz, enc in cols:
        up = (nz > FLAT_COS) & (z >= lo[2] - margin) & (z <= hi[2] + margin)  # not a skybox's bottom far below
        floors += int(up.sum())
        for k in np.nonzero(up)[0]:
            if k > 0 and nz[k - 1] < -FLAT_COS and not enc[k - 1] and z[k - 1] - z[k] > eps:
                gaps.append(z[k - 1] - z[k])
    covered = len(gaps)
    sizes = _object_sizes(geom)
    return {"columns": n * n, "columns_hit": len(cols), "floors": floors, "covered_floors": covered,
            "covered_fraction": covered / floors if floors else 0.0,
            "headroom_units": float(np.median(gaps)) if gaps else None,
            "height_units": float(hi[2] - lo[2]) if hi[2] - lo[2] > eps else None,
            "objects": len(sizes), "objects_units": float(np.median(sizes)) if len(sizes) >= MIN_OBJECTS else None,
            "extent_units": float(geom.extent)}


def spawn_heights(geom: LevelGeometry, points) -> list[float]:
    """The height (scene units) of each spawn point (``points``: (N, 3) positions) over the first surface below
    it; points with nothing below, or on it, are left out."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return []
    dist, tri = geom.first_hits(pts, np.tile([0.0, 0.0, -1.0], (len(pts), 1)))
    return [float(d) for d, t in zip(dist, tri) if t >= 0 and d > 1e-6 * max(geom.extent, 1e-9)]


def _object_sizes(geom: LevelGeometry) -> np.ndarray:
    """The box diagonal of each object (``geom.owner``) that does not enclose the others, in scene units."""
    keep = geom._content_mask
    tri = geom.mesh.triangles[keep]
    owner = geom.owner[keep]
    if len(owner) == 0:
        return np.zeros(0)
    order = np.argsort(owner, kind="stable")
    owner, tri = owner[order], tri[order]
    starts = np.r_[0, np.nonzero(np.diff(owner))[0] + 1]
    lo = np.minimum.reduceat(tri.min(axis=1), starts, axis=0)
    hi = np.maximum.reduceat(tri.max(axis=1), starts, axis=0)
    d = np.linalg.norm(hi - lo, axis=1)
    return d[d > 0]


def _score(cues: dict, unit: float, use: tuple[str, ...]) -> float:
    s = 0.0
    for name in use:
        typical, sigma = CUES[name]
        s -= 0.5 * (math.log(cues[f"{name}_units"] * unit / typical) / sigma) ** 2
    return s


def detect_unit_scale(geom: LevelGeometry, declared: float | None = None, spawns=None) -> dict:
    """The level's metres per unit (module doc) and the evidence: ``{"metres_per_unit", "unit", "declared",
    "cues", "used", "scores"}``. ``declared``: the file's own unit (default: ``geom.metres_per_unit``);
    ``spawns``: positions (N, 3) of the file's spawn points (``SPAWN_NAMES``), whose median height over the floor
    is the ``spawn`` cue."""
    declared = float(geom.metres_per_unit if declared is None else declared)
    cues = measure_cues(geom)
    heights = spawn_heights(geom, spawns) if spawns is not None else []
    cues.update(spawns=len(heights), spawn_units=float(np.median(heights)) if heights else None)
    has_headroom = (cues["headroom_units"] is not None and cues["covered_floors"] >= MIN_COVERED
                    and cues["covered_fraction"] >= MIN_COVERED_FRACTION)
    use = tuple(k for k, ok in (("headroom", has_headroom), ("objects", cues["objects_units"] is not None),
                                ("height", cues["height_units"] is not None),
                                ("spawn", cues["spawn_units"] is not None),
                                ("extent", not has_headroom and cues["objects_units"] is None
                                 and cues["extent_units"] > 0)) if ok)
    names = {**UNITS}
    if not any(math.isclose(declared, u, rel_tol=1e-9) for u in UNITS.values()):
        names["declared"] = declared
    scores = {k: _score(cues, u, use) + (DECLARED_BONUS if math.isclose(u, declared, rel_tol=1e-9) else
                                         UNIT_PRIOR.get(k, 0.0)) for k, u in names.items()}
    best = max(scores, key=scores.get) if use else next(k for k, u in names.items() if
                                                        math.isclose(u, declared, rel_tol=1e-9))
    return {"metres_per_unit": names[best], "unit": best, "declared": declared, "cues": cues, "used": list(use),
            "scores": {k: round(v, 3) for k, v in scores.items()}}


def engine_unit(path) -> dict | None:
    """The unit a text level file (an OBJ) names by its engine in its first lines (``ENGINE_SIGNATURES``):
    ``{"unit", "metres_per_unit", "engine_line", "why"}``, or None (a binary or unknown file)."""
    from pathlib import Path
    try:
        with open(Path(path), "rb") as f:
            head = f.read(4096).decode("utf-8", errors="replace")
    except (OSError, TypeError):
        return None
    for line in head.splitlines()[:20]:
        low = line.strip().lower()
        if not low.startswith("#"):
            continue
        for sig, (name, mpu, why) in ENGINE_SIGNATURES.items():
            if sig in low:
                return {"unit": name, "metres_per_unit": mpu, "engine_line": line.strip(), "why": why}
    return None


def resolve_unit_scale(geom: LevelGeometry, unit_scale, source=None, spawns=None) -> dict:
    """Set ``geom.metres_per_unit`` from ``unit_scale`` (``RenderConfig.unit_scale``: "auto" detects it, a
    number is taken as given) and return the manifest's record of it. ``source``: the level's file, whose engine
    line (``engine_unit``) declares its unit where the file format has no unit of its own; ``spawns``: its
    spawn points' positions (``detect_unit_scale``)."""
    declared = float(geom.metres_per_unit)
    if unit_scale == "auto":
        engine = engine_unit(source) if source is not None else None
        if engine is not None:
            declared = engine["metres_per_unit"]
        out = {"requested": "auto", **detect_unit_scale(geom, declared, spawns),
               **({"engine": engine} if engine is not None else {})}
    else:
        out = {"requested": float(unit_scale), "metres_per_unit": float(unit_scale), "declared": declared}
    geom.metres_per_unit = float(out["metres_per_unit"])
    return out
