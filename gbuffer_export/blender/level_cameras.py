"""Camera paths that move *inside* a level: a walking eye and a flying camera (numpy + :class:`LevelGeometry`).

No bpy here: the planner sees the level only as triangles (``level_geometry``), so it is tested on synthetic rooms
and runs unchanged on any level. Units: metres and seconds in :class:`PathRules`, converted to scene units with
the scene's unit scale; one step is one frame at the scene's fps.

walk
    The eye stands ``eye_height_m`` above a walkable floor (a surface within 45 degrees of horizontal, found with
    downward rays), moves at ``walk_speed_mps``, its heading turns smoothly (an angular velocity that drifts
    randomly, bounded by ``max_turn_deg_s``) and steers towards open space when a wall is ahead; a step up or
    down of more than ``max_step_m`` is not walkable.
fly
    A free 3D path (a drone or spectator camera) at ``fly_speed_mps`` with bounded yaw and pitch rates, between
    ``min_fly_height_m`` above the floor and the top of the level's content box.

Every path keeps ``clearance_m`` from every triangle on the whole segment between consecutive eyes (checked as
exact point-to-triangle distances of the eyes against ``clearance + step / 2``, which bounds every point of the
segment), never starts inside a closed mesh, stays in its allowed region (``Region``), and is re-drawn when its
view lacks content on any frame: more than ``max_background`` of a 16x9 grid of view rays missing the level or
hitting beyond its extent (sky, a skybox, a far ground plane), or a median view depth below
``min_view_depth_m`` (staring at a wall) or above the extent. A level lit by the sky alone (``light = "sky"``: the
renderer sets ``min_sky_fraction``) also needs every eye to see the sky: at least ``min_sky_fraction`` of 64 rays
spread over the upper hemisphere must leave the level, or the eye stands under a roof that no light reaches (a
black clip). Of the first ``candidates`` paths that meet every
rule, the one whose view rays hit the most steep surfaces (walls, props: not floor, not sky) is kept, so a walk
in a town looks at its streets rather than at an empty field.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from ..errors import BlendSRError
from .level_geometry import LevelGeometry

UP = np.array([0.0, 0.0, 1.0])
WALKABLE_COS = math.cos(math.radians(45.0))  # a surface within 45 degrees of horizontal is floor
LEVEL_KINDS = ("walk", "fly")


#: Blender keys the camera and records its matrices in 32-bit floats, and Embree casts rays in 32 bits: a planned
#: step may change by at most this fraction of its length when its eyes are rounded to float32, or the rendered
#: motion is not the planned one (validate allows the declared speed + 2%). Far from the scene's origin a float32
#: position is coarse (0.5 m at 5000 km): a level whose allowed region lies that far is refused before planning.
FLOAT32_STEP_TOLERANCE = 0.01
#: Why a path is refused when its region holds none of the level's floor (``floor_samples``).
NO_FLOOR = "no floor in the region"
#: Why a path is refused under ``min_sky_fraction`` (an eye under a roof).
ROOF = "stands under a roof (sees no sky; the level is lit by the sky alone)"


class PathError(BlendSRError):
    """No path meets the rules (one line naming each rule that failed, the most frequent first);
    ``most_often``: that rule; ``reasons``: every rule that failed, with how often."""

    def __init__(self, message: str, most_often: str | None = None, reasons: dict | None = None):
        super().__init__(message)
        self.most_often = most_often
        self.reasons = dict(reasons or {})


@dataclass(frozen=True)
class PathRules:
    """What a level camera path must do. Metres, seconds, degrees."""

    eye_height_m: float = 1.6
    walk_speed_mps: float = 1.4
    fly_speed_mps: float = 3.0
    max_turn_deg_s: float = 45.0
    clearance_m: float = 0.25
    max_step_m: float = 0.4
    min_fly_height_m: float = 1.0
    min_view_depth_m: float = 0.75
    max_background: float = 0.4
    min_sky_fraction: float = 0.0
    pitch_deg: tuple[float, float] = (-14.0, 2.0)
    tries: int = 60
    candidates: int = 4

    def to_json(self) -> dict:
        d = asdict(self)
        d["pitch_deg"] = list(self.pitch_deg)
        return d


@dataclass(frozen=True)
class Region:
    """Where a clip's eyes may stand: the cells ``cells`` of an ``nx`` x ``ny`` grid over the box ``lo``..``hi``
    (x, y in scene units). None cells: anywhere in the box."""

    lo: tuple[float, float]
    hi: tuple[float, float]
    nx: int = 1
    ny: int = 1
    cells: tuple[tuple[int, int], ...] | None = None

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) integer cell indices of points (N, 2); -1 outside the box."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        lo, hi = np.array(self.lo), np.array(self.hi)
        u = (xy - lo) / np.maximum(hi - lo, 1e-12) * np.array([self.nx, self.ny])
        idx = np.floor(u).astype(int)
        out = (u < 0).any(axis=1) | (idx[:, 0] >= self.nx) | (idx[:, 1] >= self.ny)
        idx[out] = -1
        return idx

    def contains(self, xy: np.ndarray) -> np.ndarray:
        idx = self.cell_of(xy)
        ok = (idx >= 0).all(axis=1)
        if self.cells is not None:
            allowed = {tuple(c) for c in self.cells}
            ok &= np.array([tuple(i) in allowed for i in idx])
        return ok

    def sample(self, rng, n: int) -> np.ndarray:
        """``n`` uniform (x, y) points in the allowed cells."""
        cells = list(self.cells) if self.cells is not None else [(i, j) for i in range(self.nx) for j in range(self.ny)]
        pick = rng.integers(0, len(cells), size=n)
        c = np.array([cells[k] for k in pick], np.float64)
        lo, hi = np.array(self.lo), np.array(self.hi)
        size = (hi - lo) / np.array([self.nx, self.ny])
        return lo + (c + rng.random((n, 2))) * size

    def to_json(self) -> dict:
        return {"lo": list(self.lo), "hi": list(self.hi), "grid": [self.nx, self.ny],
                "cells": [list(c) for c in self.cells] if self.cells is not None else None}


@dataclass
class LevelPath:
    """A planned path: eyes and look-at targets (N, 3) in scene units for frames ``start-1 .. end``, and its report."""

    kind: str
    eyes: np.ndarray
    targets: np.ndarray
    report: dict


# ----------------------------------------------------------------------------------------------
# Views
# ----------------------------------------------------------------------------------------------

def view_dirs(forward: np.ndarray, hfov: float, vfov: float, nx: int = 16, ny: int = 9) -> np.ndarray:
    """Unit rays (nx*ny, 3) through a grid of pixel centres of a camera looking along ``forward`` (world +Z up),
    ``hfov``/``vfov`` half angles in radians."""
    f = forward / np.linalg.norm(forward)
    right = np.cross(f, UP)
    if np.linalg.norm(right) < 1e-9:
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    u = (np.arange(nx) + 0.5) / nx * 2 - 1
    v = (np.arange(ny) + 0.5) / ny * 2 - 1
    uu, vv = np.meshgrid(u * math.tan(hfov), v * math.tan(vfov))
    d = f[None] + uu.reshape(-1, 1) * right[None] + vv.reshape(-1, 1) * up[None]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def view_stats(geom: LevelGeometry, eyes: np.ndarray, targets: np.ndarray, hfov: float, vfov: float) -> dict:
    """Per frame: background fraction (rays missing or beyond the extent), median depth along the view axis of the
    rays that hit (metres; inf when none does) and their 90th percentile (``far_depth_m``: how far the view
    reaches), the share of rays on walls and objects (``structure``) and the
    view's depth p90/p10 with background counted as infinitely far (``depth_ratio``: validate's ``flat-view``
    measure on the ray grid; 1 when nothing is hit)."""
    bg, med, steep, ratio, far = [], [], [], [], []
    for e, t in zip(eyes, targets):
        f = (t - e) / np.linalg.norm(t - e)
        d = view_dirs(f, hfov, vfov)
        dist, tri = geom.first_hits(np.repeat(e[None], len(d), axis=0), d)
        hit = dist <= geom.extent
        bg.append(1.0 - hit.mean())
        z = dist[hit] * (d[hit] @ f)
        med.append(float(np.median(z)) * geom.metres_per_unit if hit.any() else math.inf)
        far.append(float(np.quantile(z, 0.9)) * geom.metres_per_unit if hit.any() else math.inf)
        steep.append(float((np.abs(geom.normals[tri[hit]][:, 2]) < WALKABLE_COS).sum()) / len(d))
        zall = np.where(hit, dist * (d @ f), np.inf)
        p10, p90 = np.quantile(zall, [0.1, 0.9], method="nearest")
        ratio.append(float(p90 / p10) if math.isfinite(p10) and p10 > 0 else 1.0)
    return {"background": np.array(bg), "median_depth_m": np.array(med), "structure": np.array(steep),
            "depth_ratio": np.array(ratio), "far_depth_m": np.array(far)}


def near_far_fraction(depth_ratio: np.ndarray) -> float:
    """The share of frames whose view holds near and far content (depth p90/p10 at least validate's
    ``NEAR_FAR_RATIO``)."""
    from ..validate.exposure import NEAR_FAR_RATIO
    return float((np.asarray(depth_ratio) >= NEAR_FAR_RATIO).mean()) if len(depth_ratio) else 0.0


def _has_depth(path: "LevelPath") -> bool:
    from ..validate.exposure import NEAR_FAR_MIN_FRACTION
    return path.report["near_far_fraction"] >= NEAR_FAR_MIN_FRACTION


def choose_path(found: list["LevelPath"]) -> "LevelPath":
    """The valid path that sees the most walls and objects (not only floor and sky); when it frames one flat
    surface on too many frames (under validate's ``NEAR_FAR_MIN_FRACTION`` of them with near and far content), the
    one with the most such frames instead (then the most structure)."""
    from ..validate.exposure import NEAR_FAR_MIN_FRACTION
    best = max(found, key=lambda p: p.report["structure_fraction_mean"])
    if best.report["near_far_fraction"] >= NEAR_FAR_MIN_FRACTION:
        return best
    return max(found, key=lambda p: (p.report["near_far_fraction"], p.report["structure_fraction_mean"]))


def sky_fraction(geom: LevelGeometry, eyes: np.ndarray, n: int = 128) -> np.ndarray:
    """Per eye: the fraction of rays spread over the upper hemisphere (half of ``n`` sphere directions) that miss
    the level or hit beyond its extent: how much sky the eye sees."""
    from .level_geometry import sphere_directions
    d = sphere_directions(n)
    d = d[d[:, 2] > 0]
    eyes = np.asarray(eyes, np.float64).reshape(-1, 3)
    dist, _ = geom.first_hits(np.repeat(eyes, len(d), axis=0), np.tile(d, (len(eyes), 1)))  # one batch of rays
    return (dist > geom.extent).reshape(len(eyes), len(d)).mean(axis=1)


# ----------------------------------------------------------------------------------------------
# Floors and free space
# ----------------------------------------------------------------------------------------------

def floor_under(geom: LevelGeometry, p: np.ndarray, reach: float) -> float | None:
    """Height of the first surface below ``p`` within ``reach`` if it is walkable, else None."""
    dist, tri = geom.first_hits(p[None], -UP[None])
    if tri[0] < 0 or dist[0] > reach or abs(geom.normals[tri[0]][2]) < WALKABLE_COS:
        return None
    return float(p[2] - dist[0])


def free_distance(geom: LevelGeometry, p: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    dist, _ = geom.first_hits(np.repeat(p[None], len(dirs), axis=0), dirs)
    return dist


def region_room(region: Region, p: np.ndarray, dirs: np.ndarray, ahead: float, n: int = 8) -> np.ndarray:
    """Per direction: how far (up to ``ahead``) a move from ``p`` stays inside ``region``'s allowed cells, probed
    at ``n`` points; the planner steers away from a cell's border before it must stop at it."""
    t = ahead * (np.arange(1, n + 1) / n)
    pts = p[None, None, :2] + t[None, :, None] * dirs[:, None, :2]
    ok = region.contains(pts.reshape(-1, 2)).reshape(len(dirs), n)
    first_out = np.where(ok.all(axis=1), n, np.argmin(ok, axis=1))
    return np.where(first_out == n, ahead, np.where(first_out == 0, 0.0, t[np.maximum(first_out - 1, 0)]))


def _heading_dirs(theta: np.ndarray, pitch: np.ndarray | float = 0.0) -> np.ndarray:
    theta = np.atleast_1d(theta)
    pitch = np.broadcast_to(pitch, theta.shape)
    return np.stack([np.cos(pitch) * np.cos(theta), np.cos(pitch) * np.sin(theta), np.sin(pitch)], axis=1)


# ----------------------------------------------------------------------------------------------
# Path drawing
# ----------------------------------------------------------------------------------------------

class _Smooth:
    """A smooth random signal in [-1, 1]: an Ornstein-Uhlenbeck process, correlation time ``tau`` steps."""

    def __init__(self, rng, tau: float):
        self.rng, self.a, self.v = rng, math.exp(-1.0 / max(tau, 1.0)), float(rng.uniform(-1, 1))

    def __call__(self) -> float:
        self.v = self.a * self.v + math.sqrt(1 - self.a ** 2) * float(self.rng.normal()) * 0.6
        return max(-1.0, min(1.0, self.v))


#: Points drawn on the floor of a region (``floor_samples``), area-weighted, once per level and region.
FLOOR_SAMPLES = 4000


def _cells_box(region: Region) -> tuple[np.ndarray, np.ndarray]:
    """The (x, y) box of ``region``'s allowed cells."""
    lo, hi = np.array(region.lo, np.float64), np.array(region.hi, np.float64)
    if region.cells is None:
        return lo, hi
    size = (hi - lo) / np.array([region.nx, region.ny])
    c = np.array(region.cells, np.float64).reshape(-1, 2)
    return lo + c.min(axis=0) * size, lo + (c.max(axis=0) + 1) * size


def floor_samples(geom: LevelGeometry, region: Region) -> np.ndarray:
    """(N, 3) points spread uniformly by area over the walkable surfaces (within 45 degrees of horizontal, either
    side: a room modelled with outward normals has its floor facing down) inside
    ``region``: of the level's content, or, where that has none there, of every object (a ground plane under
    props). Each triangle is weighted by its area times the share of its box over the region's box, and points
    outside the allowed cells are dropped, so a 2 km ground plane gives a room its floor without drowning it.
    Drawn with a fixed seed and cached on ``geom``; empty when the region holds no floor."""
    cache = geom.__dict__.setdefault("_floor_samples", {})
    if region in cache:
        return cache[region]
    lo, hi = _cells_box(region)
    tri = geom.mesh.triangles
    tlo, thi = tri[:, :, :2].min(axis=1), tri[:, :, :2].max(axis=1)
    span = np.maximum(thi - tlo, 1e-12)
    share = np.prod(np.clip((np.minimum(thi, hi) - np.maximum(tlo, lo)) / span, 0.0, 1.0), axis=1)
    share[np.all(thi - tlo <= 1e-12, axis=1)] = 1.0
    weight = np.asarray(geom.mesh.area_faces, np.float64) * share * (np.abs(geom.normals[:, 2]) > WALKABLE_COS)
    content = weight * geom._content_mask
    weight = content if content.sum() > 0 else weight
    out = np.zeros((0, 3))
    if weight.sum() > 0:
        rng = np.random.default_rng(0)
        k = rng.choice(len(weight), size=FLOOR_SAMPLES, p=weight / weight.sum())
        r1, r2 = rng.random(FLOOR_SAMPLES), rng.random(FLOOR_SAMPLES)
        flip = r1 + r2 > 1
        r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
        t = tri[k]
        out = t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])
        out = out[region.contains(out[:, :2])]
    cache[region] = out
    return out


def _start_points(geom, region: Region, rng, kind: str, rules: PathRules, n: int = 48):
    """Candidate starting eyes (list of ((3,) eye, floor height)) seeded on the level's floor inside the region
    (``floor_samples``), not on a grid over its box: a mostly empty, open or steep cell still gives starts where it
    has floor. A walk's eye stands ``eye_height_m`` above its floor point when that floor is the first surface below
    the eye (not a floor under a table); a fly's eye at a random height between ``min_fly_height_m`` above it and
    the top of the content box."""
    pts = floor_samples(geom, region)
    if len(pts) == 0:
        return []
    hi = geom.content_bounds()[1]
    eye_h = geom.units(rules.eye_height_m)
    out = []
    for k in rng.choice(len(pts), size=min(n, len(pts)), replace=False):
        x, y, zf = (float(v) for v in pts[k])
        if kind == "walk":
            eye = np.array([x, y, zf + eye_h])
            f = floor_under(geom, eye, eye_h * 1.01 + geom.units(0.01))
            if f is None or abs(f - zf) > 1e-3 * eye_h:
                continue
            out.append((eye, zf))
        else:
            zmin = zf + geom.units(rules.min_fly_height_m)
            out.append((np.array([x, y, float(rng.uniform(zmin, max(zmin, hi[2])))]), zf))
    return out


def _valid_eye(geom, p, clearance, rules) -> bool:
    return bool(geom.nearest_distance(p[None])[0] >= clearance and not geom.inside_closed_mesh(p))


class _Walker:
    """A path being drawn (``_draw``): the rules in level units per frame, the current eye ``p`` over its floor
    ``zf``, its heading ``theta`` and climb, and the smooth noises that steer and aim it. ``start`` seats it (or
    gives the reason it cannot start) and must come first; then ``look`` and ``step`` advance it one frame, drawing
    from ``rng`` in the order the scale set's level paths were planned with."""

    def __init__(self, geom: LevelGeometry, kind: str, fps: float, region: Region, rules: PathRules):
        self.geom, self.kind, self.fps, self.region, self.rules = geom, kind, fps, region, rules
        self.speed = geom.units(rules.walk_speed_mps if kind == "walk" else rules.fly_speed_mps) / fps  # per frame
        self.need = geom.units(rules.clearance_m) + 0.5 * self.speed
        self.max_turn = math.radians(rules.max_turn_deg_s) / fps
        self.eye_h = geom.units(rules.eye_height_m)
        self.lo_c, self.hi_c = geom.content_bounds()
        self.ahead = max(geom.units(1.5), 12 * self.speed)
        # a U-turn's width at the bounded turn rate
        self.border_ahead = max(self.ahead, 2.5 * self.speed / max(self.max_turn, 1e-9))
        self.climb = 0.0

    def start(self, rng) -> str | None:
        """Seat the first eye and heading; None, or why no path can start in the region."""
        geom, region = self.geom, self.region
        starts = _start_points(geom, region, rng, self.kind, self.rules)
        if not starts:
            return NO_FLOOR if len(floor_samples(geom, region)) == 0 else "no free standing point in the region"
        starts = [s for s in starts if _valid_eye(geom, s[0], self.need, self.rules)]
        if not starts:
            return "no free standing point in the region"
        self.p, self.zf = starts[0]
        # Initial heading: towards the most open of 24 horizontal directions (seeded among the best quarter), the
        # region's border counting as a wall.
        thetas = np.linspace(0, 2 * math.pi, 24, endpoint=False)
        free = free_distance(geom, self.p, _heading_dirs(thetas))
        free = np.minimum(free, region_room(region, self.p, _heading_dirs(thetas), min(geom.extent, 64 * self.speed),
                                            32))
        best = np.argsort(-np.minimum(free, geom.extent))[:6]
        self.theta = float(thetas[rng.choice(best)]) + float(rng.uniform(-0.1, 0.1))
        self.turn, self.look_yaw, self.look_pitch, self.climb_noise = (
            _Smooth(rng, 1.5 * self.fps), _Smooth(rng, self.fps), _Smooth(rng, self.fps), _Smooth(rng, 2 * self.fps))
        return None

    @property
    def pitch_move(self) -> float:
        """The pitch of a move: a fly's climb; a walk moves level."""
        return self.climb if self.kind == "fly" else 0.0

    def look(self) -> np.ndarray:
        """The current eye's look direction (a unit vector)."""
        lo, hi = self.rules.pitch_deg
        pitch = math.radians(lo + (hi - lo) * 0.5 * (self.look_pitch() + 1))
        yaw = self.theta + math.radians(12.0) * self.look_yaw()
        return _heading_dirs(np.array([yaw]), pitch)[0]

    def step(self) -> bool:
        """Move one frame: random drift plus avoidance of what is ahead; False at a dead end."""
        cand = self.theta + np.linspace(-self.max_turn, self.max_turn, 7)
        dirs = _heading_dirs(cand, self.pitch_move)
        free = free_distance(self.geom, self.p, dirs)
        for k in np.argsort(-self._scores(cand, dirs, free)):
            q = self._moved(dirs[k], free[k])
            if q is not None:
                self.theta, self.p = float(cand[k]), q
                break
        else:
            return False
        if self.kind == "fly":
            self.climb = float(np.clip(self.climb + math.radians(4.0) / self.fps * self.climb_noise() * 4,
                                       -0.35, 0.35))
            if self.p[2] < self.lo_c[2] + self.geom.units(self.rules.min_fly_height_m) + 2 * self.speed:
                self.climb = abs(self.climb)
        return True

    def _scores(self, cand: np.ndarray, dirs: np.ndarray, free: np.ndarray) -> np.ndarray:
        """Per candidate heading: the room ahead less the cost of turning away from the preferred heading (the
        drift, or a full-rate turn towards the more open side when a wall or the cell's border is ahead)."""
        geom, region, max_turn = self.geom, self.region, self.max_turn
        ahead, border_ahead = self.ahead, self.border_ahead
        pref = self.theta + max_turn * self.turn()
        border = region_room(region, self.p, dirs, border_ahead)
        room = np.minimum(np.minimum(free, ahead), border * ahead / border_ahead)  # the cell's border: a wall
        if free[3] < ahead or border[3] < border_ahead:  # a wall or the cell's border ahead: turn at full rate
            side = _heading_dirs(self.theta + np.array([-1.0, 1.0]) * math.radians(60.0), self.pitch_move)
            open_ = np.minimum(free_distance(geom, self.p, side), region_room(region, self.p, side, border_ahead))
            pref = self.theta + max_turn * (1.0 if open_[1] >= open_[0] else -1.0)
        return room - 0.2 * ahead * np.abs(cand - pref) / max(max_turn, 1e-9)

    def _moved(self, d: np.ndarray, free: float) -> np.ndarray | None:
        """The next eye one step along ``d`` (a walk follows its floor, a fly keeps its height band), or None where
        that step leaves the region, hits a surface, climbs a step too high or leaves the band. A walk's floor
        ``zf`` follows the step's floor before the last check (clearance), even when that check refuses it: the
        next candidate of the same frame starts from that floor, as the scale set's paths were drawn."""
        geom, rules, speed, p = self.geom, self.rules, self.speed, self.p
        q = p + speed * d
        if free < speed + self.need or not self.region.contains(q[None, :2])[0]:
            return None
        if self.kind == "walk":
            f = floor_under(geom, q + UP * geom.units(rules.max_step_m), self.eye_h + geom.units(2 * rules.max_step_m))
            if f is None or abs(f - self.zf) > geom.units(rules.max_step_m):
                return None
            self.zf = f
            q[2] = p[2] + np.clip(f + self.eye_h - p[2], -speed, speed)
        else:
            f = floor_under(geom, q, geom.extent)
            low = (f if f is not None else self.lo_c[2]) + geom.units(rules.min_fly_height_m)
            if q[2] < low or q[2] > self.hi_c[2] + geom.units(2.0):
                return None
        return q if geom.nearest_distance(q[None])[0] >= self.need else None


def _draw(geom: LevelGeometry, kind: str, n: int, fps: float, region: Region, rng, rules: PathRules):
    """One candidate path of ``n`` eyes (or None with a reason)."""
    w = _Walker(geom, kind, fps, region, rules)
    why = w.start(rng)
    if why:
        return None, why
    eyes, looks = [w.p.copy()], []
    for i in range(n):
        looks.append(w.look())
        if i == n - 1:
            break
        if not w.step():
            return None, "walked into a dead end"
        eyes.append(w.p.copy())
    eyes = np.array(eyes)
    return (eyes, eyes + np.array(looks)), None


def float32_step_error(eyes: np.ndarray) -> float:
    """The largest relative change of a step's length between consecutive eyes when they are rounded to float32
    (what Blender stores); 0 for a path that does not move."""
    e = np.asarray(eyes, np.float64)
    d64 = np.linalg.norm(np.diff(e, axis=0), axis=1)
    d32 = np.linalg.norm(np.diff(e.astype(np.float32).astype(np.float64), axis=0), axis=1)
    moving = d64 > 0
    return float(np.max(np.abs(d32[moving] - d64[moving]) / d64[moving])) if moving.any() else 0.0


def check_level_scale(geom: LevelGeometry, kind: str, fps: float, region: Region, rules: PathRules) -> None:
    """Refuse, before planning, a level where no ``kind`` path can move as declared: one whose allowed region
    lies so far from the origin that float32 positions there are coarser than ``FLOAT32_STEP_TOLERANCE`` of a
    step (``speed / fps``), or whose content is smaller than a camera's clearance. PathError naming the numbers
    in metres."""
    mpu = geom.metres_per_unit
    speed = rules.walk_speed_mps if kind == "walk" else rules.fly_speed_mps
    step = geom.units(speed) / fps
    lo, hi = np.array(region.lo, np.float64), np.array(region.hi, np.float64)
    z_lo, z_hi = geom.bounds()[0][2], geom.bounds()[1][2]
    nearest = np.abs(np.append(np.clip(0.0, lo, hi), np.clip(0.0, z_lo, z_hi)))  # the region's point nearest 0
    ulp = float(np.spacing(np.float32(nearest.max())))
    if not math.isfinite(ulp) or ulp > FLOAT32_STEP_TOLERANCE * step:
        raise PathError(f"{kind} path: the level's allowed region lies {nearest.max() * mpu:.4g} m from the scene's "
                        f"origin, where Blender's 32-bit positions are {ulp * mpu:.3g} m apart, too coarse for "
                        f"steps of {step * mpu:.3g} m a frame ({speed:g} m/s at {fps:g} fps); move the level "
                        "towards the origin or check its unit scale")
    extent_m = geom.extent * mpu
    if extent_m < 4 * rules.clearance_m:
        raise PathError(f"{kind} path: the level's content is {extent_m:.3g} m across, too small to hold a camera "
                        f"that keeps {rules.clearance_m:g} m from every surface (is its unit scale right?)")


#: The lower pitch bound of a second round of candidates when none of the first frames near and far content (a
#: small interior seen at eye height: the floor near the camera gives the near content).
STEEP_PITCH_DEG = -30.0


@dataclass(frozen=True)
class _Drawing:
    """What every candidate path of one ``plan_level_path`` call shares (the level, the path's kind, length and
    camera, the region, the seeded generator)."""
    geom: LevelGeometry
    kind: str
    n_frames: int
    fps: float
    seed: int
    fov: tuple[float, float]
    region: Region
    rng: np.random.Generator


def _candidates(draw: _Drawing, rules: PathRules, reasons: dict[str, int]) -> list[LevelPath]:
    """Draw paths under ``rules`` until ``rules.candidates`` meet every rule (three times as many while none of them
    shows near and far content) or ``rules.tries`` are spent; each refused draw's reason is counted in ``reasons``."""
    geom, kind, n_frames, fps, seed, region = draw.geom, draw.kind, draw.n_frames, draw.fps, draw.seed, draw.region
    hfov, vfov = draw.fov
    rng = draw.rng
    found: list[LevelPath] = []
    for t in range(rules.tries):
        drawn, why = _draw(geom, kind, n_frames, fps, region, rng, rules)
        if drawn is None:
            reasons[why] = reasons.get(why, 0) + 1
            continue
        eyes, targets = drawn
        vs = view_stats(geom, eyes, targets, hfov, vfov)
        extent_m = geom.extent * geom.metres_per_unit
        why = None
        if float32_step_error(eyes) > FLOAT32_STEP_TOLERANCE:
            why = "moves by less than Blender's 32-bit positions resolve here (too far from the origin)"
        elif vs["background"].max() > rules.max_background:
            why = "looks at the sky or background"
        elif vs["median_depth_m"].min() < rules.min_view_depth_m:
            why = "stares at a surface closer than min_view_depth_m"
        elif vs["median_depth_m"].max() > extent_m:
            why = "looks beyond the level's extent"
        sky = float(sky_fraction(geom, eyes).min()) if rules.min_sky_fraction > 0 and not why else None
        if sky is not None and sky < rules.min_sky_fraction:
            why = ROOF
        if why:
            reasons[why] = reasons.get(why, 0) + 1
            continue
        step = np.linalg.norm(np.diff(eyes, axis=0), axis=1) * geom.metres_per_unit
        nominal = rules.walk_speed_mps if kind == "walk" else rules.fly_speed_mps  # walk: horizontal, rises <= it
        clear = geom.nearest_distance(eyes) * geom.metres_per_unit
        report = {"kind": kind, "seed": int(seed), "try": t, "fps": fps, "metres_per_unit": geom.metres_per_unit,
                  "speed_m_per_frame": float(np.median(step)) if len(step) else 0.0,
                  "speed_max_m_per_frame": float(step.max()) if len(step) else 0.0,
                  "speed_mps": float(np.median(step)) * fps if len(step) else 0.0,
                  "declared_speed_mps": nominal, "declared_max_speed_mps": nominal * (math.sqrt(2.0) if
                                                                                      kind == "walk" else 1.0),
                  "clearance_m": float(clear.min()), "min_clearance_rule_m": rules.clearance_m,
                  "median_depth_m": float(np.median(vs["median_depth_m"])),
                  "far_depth_m": float(np.median(vs["far_depth_m"])),
                  "background_fraction_max": float(vs["background"].max()),
                  "background_fraction_mean": float(vs["background"].mean()),
                  "level_extent_m": extent_m, "region": region.to_json(), "rules": rules.to_json(),
                  "structure_fraction_mean": float(vs["structure"].mean()), "candidates_drawn": len(found) + 1,
                  "near_far_fraction": near_far_fraction(vs["depth_ratio"]),
                  **({"sky_fraction_min": sky} if sky is not None else {}),
                  "ray_engine": geom.engine}
        found.append(LevelPath(kind, eyes, targets, report))
        if len(found) >= rules.candidates and (_has_depth(choose_path(found)) or len(found) >= 3 * rules.candidates):
            break  # enough candidates, or three times as many when none of them shows near and far content
    return found


def plan_level_path(geom: LevelGeometry, kind: str, n_frames: int, fps: float, seed: int, fov: tuple[float, float],
                    region: Region | None = None, rules: PathRules = PathRules()) -> LevelPath:
    """Draw seeded ``kind`` paths of ``n_frames`` eyes until one meets every rule (module doc); PathError after
    ``rules.tries`` draws. ``fov``: the camera's (horizontal, vertical) half angles in radians."""
    hfov, vfov = fov
    if kind not in LEVEL_KINDS:
        raise BlendSRError(f"level camera {kind!r}: choose one of {', '.join(LEVEL_KINDS)}")
    if region is None:
        lo, hi = geom.content_bounds()
        region = Region((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])))
    check_level_scale(geom, kind, fps, region, rules)
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, LEVEL_KINDS.index(kind), 7])
    draw = _Drawing(geom, kind, n_frames, fps, seed, (hfov, vfov), region, rng)
    reasons: dict[str, int] = {}
    found = _candidates(draw, rules, reasons)
    if found and not _has_depth(choose_path(found)):  # a small interior: look further down, the floor in view
        steeper = replace(rules, pitch_deg=(min(rules.pitch_deg[0], STEEP_PITCH_DEG), rules.pitch_deg[1]))
        found += _candidates(draw, steeper, reasons)
    if found:
        return choose_path(found)
    ranked = sorted(reasons.items(), key=lambda kv: (-kv[1], kv[0]))
    text = "; ".join(f"{k}: {v}" for k, v in ranked) or "no attempt"
    raise PathError(f"no {kind} path meets the rules after {rules.tries} tries ({text})",
                    ranked[0][0] if ranked else None, dict(ranked))


# ----------------------------------------------------------------------------------------------
# A dataset clip's region: its cell, moved where the level has floor
# ----------------------------------------------------------------------------------------------

def clip_regions(geom: LevelGeometry, spec: dict) -> list[tuple[Region, dict | None]]:
    """The ``Region``s a dataset clip may use, in order, each with the move the manifest records (None: its own
    cell). ``spec``: the clip's ``region`` (``grid``, ``cell``, ``split``, ``cells`` per split) over the level's
    content box. Its own cell first when that has floor (``floor_samples``), else the nearest cell of its split
    that has; then every cell of its split with floor, for when no path fits in the first. A cell never leaves its
    split, so a test cell's clips stay test clips."""
    lo, hi = geom.content_bounds()
    nx, ny = (int(v) for v in spec["grid"])

    def region(cells) -> Region:
        return Region((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])), nx, ny,
                      tuple(tuple(int(v) for v in c) for c in cells))
    cell = tuple(int(v) for v in spec["cell"])
    split_cells = [tuple(int(v) for v in c) for c in (spec.get("cells") or {}).get(spec.get("split"), [])] or [cell]
    floored = [c for c in split_cells if len(floor_samples(geom, region([c])))]
    out: list[tuple[Region, dict | None]] = []
    if cell in floored:
        out.append((region([cell]), None))
    elif floored:
        near = min(floored, key=lambda c: ((c[0] - cell[0]) ** 2 + (c[1] - cell[1]) ** 2, c))
        out.append((region([near]), {"from": list(cell), "to": [list(near)], "reason": NO_FLOOR + " of its cell"}))
    else:
        out.append((region([cell]), None))  # no floor in the split: the planner says so
    if len(floored) > 1:
        out.append((region(floored), {"from": list(cell), "to": [list(c) for c in floored],
                                      "reason": "no path in the cell alone"}))
    return out


def plan_clip_path(geom: LevelGeometry, kind: str, n_frames: int, fps: float, seed: int, fov: tuple[float, float],
                   region: "Region | dict | None" = None, rules: PathRules = PathRules()) -> LevelPath:
    """``plan_level_path`` for a clip: ``region`` a ``Region``, None (the whole level) or a dataset clip's region
    spec, tried cell by cell (``clip_regions``); a path planned outside the clip's own cell records the move in
    its report (``region_move``). PathError of the last region tried when none holds a path."""
    tries = clip_regions(geom, region) if isinstance(region, dict) else [(region, None)]
    for k, (reg, move) in enumerate(tries):
        try:
            path = plan_level_path(geom, kind, n_frames, fps, seed, fov, reg, rules)
        except PathError:
            if k == len(tries) - 1:
                raise
            continue
        if move is not None:
            path.report["region_move"] = move
        return path
    raise AssertionError("unreachable")


# ----------------------------------------------------------------------------------------------
# The level's unit checked on the planned views
# ----------------------------------------------------------------------------------------------

#: The most a walk's median view depth (metres, the median over its frames) may be in a level with ceilings (an
#: interior: ``level_scale``'s headroom cue) and in any level; a walk that sees further was planned in a wrong unit
#: (a Cube map read in metres sees 138-260 m).
INTERIOR_MAX_VIEW_M = 40.0
MAX_VIEW_M = 250.0


def implausible_view(path: LevelPath, unit: dict) -> str | None:
    """Why ``path``'s views say the level's unit is wrong (None when they do not): a walk whose views reach
    (``far_depth_m``: the 90th percentile of the view depth, the median over frames) beyond ``INTERIOR_MAX_VIEW_M``
    in an interior or ``MAX_VIEW_M`` anywhere."""
    depth = float(path.report["far_depth_m"])
    interior = "headroom" in unit.get("used", ())
    limit = INTERIOR_MAX_VIEW_M if interior else MAX_VIEW_M
    if path.kind == "walk" and depth > limit:
        return (f"the walk's views reach {depth:.0f} m, more than {limit:g} m "
                f"{'inside an interior' if interior else 'on foot'}")
    return None


@dataclass(frozen=True)
class ClipPlan:
    """What one clip's path is planned for: the camera ``kind`` ("walk", "fly"), ``n_frames`` eyes, the frame rate,
    the seed, the half fields of view (radians) and the region cell (None: the whole level)."""
    kind: str
    n_frames: int
    fps: float
    seed: int
    fov: tuple[float, float]
    region: object = None

    def path(self, geom: LevelGeometry, rules: PathRules, kind: str | None = None, region=False) -> LevelPath:
        """``plan_clip_path`` of this clip (``kind``/``region``: another camera kind or cell; None: the whole
        level)."""
        return plan_clip_path(geom, kind or self.kind, self.n_frames, self.fps, self.seed, self.fov,
                              self.region if region is False else region, rules)


def plan_level_camera(geom: LevelGeometry, clip: ClipPlan, rules: PathRules = PathRules(), unit_scale="auto",
                      source=None, spawns=None) -> tuple[LevelPath, dict]:
    """The level's unit (``level_scale.resolve_unit_scale``) and a clip's path in it (``plan_clip_path``): the
    renderer and ``blendsr dataset --dry-run`` plan through this one function. With ``unit_scale`` "auto" the unit
    is checked on the planned views (``implausible_view``): a wrong one gives way to the next candidate by score
    whose path looks right. Returns (path, the unit's record for the manifest: cues, scores, choice and the
    ``view_check``). ``source``: the level's file (its engine line names its unit); ``spawns``: its spawn points'
    positions."""
    from .level_scale import resolve_unit_scale
    return plan_in_unit(geom, clip, rules, resolve_unit_scale(geom, unit_scale, source, spawns))


def plan_in_unit(geom: LevelGeometry, clip: ClipPlan, rules: PathRules, unit: dict) -> tuple[LevelPath, dict]:
    """A clip's path in ``geom`` whose unit is resolved (``unit``: ``level_scale.resolve_unit_scale``'s record, left
    as it is): ``plan_level_camera`` once the unit is known. An "auto" unit is checked on the planned views and may
    give way to the next candidate (``geom.metres_per_unit`` follows); returns (path, the unit's final record)."""
    from .level_scale import UNITS
    path = clip.path(geom, rules)
    if unit["requested"] != "auto":
        return path, unit
    unit = dict(unit)
    why = implausible_view(path, unit)
    check = {"far_depth_m": path.report["far_depth_m"], "plausible": why is None, "rejected": []}
    if why is not None:
        first = (path, unit["metres_per_unit"])
        order = sorted(unit.get("scores", {}), key=lambda k: -unit["scores"][k])
        mpu_of = {**UNITS, "declared": unit.get("declared")}
        check["rejected"].append({"unit": unit["unit"], "why": why})
        for name in order[1:3]:
            geom.metres_per_unit = float(mpu_of[name])
            try:
                other = clip.path(geom, rules)
            except PathError as exc:
                check["rejected"].append({"unit": name, "why": str(exc)})
                continue
            why = implausible_view(other, unit)
            if why is None:
                path = other
                unit = {**unit, "unit": name, "metres_per_unit": geom.metres_per_unit, "chosen_by": "view check"}
                check.update(far_depth_m=other.report["far_depth_m"], plausible=True)
                break
            check["rejected"].append({"unit": name, "why": why})
        else:
            path, geom.metres_per_unit = first
    unit["view_check"] = check
    return path, unit


#: A scene of one object smaller than this (metres across, in its detected unit) is an object, not a level.
SINGLE_OBJECT_M = 20.0


def suggest_fix(geom: LevelGeometry, clip: ClipPlan, rules: PathRules = PathRules(), unit: dict | None = None) -> str:
    """A fix that works for a clip that has no path: each alternative is planned, in order (the other camera kind
    in the same region, the same kind over the whole level: fewer regions, then the next units by score: a
    ``unit_scale``), and the first that gives a path is named. A scene with no floor, or a single object under
    ``SINGLE_OBJECT_M`` across, is framed by orbit; where nothing works, the advice is the file's own camera."""
    if len(floor_samples(geom, Region(*_whole(geom)))) == 0:
        objs = len(np.unique(geom.owner))
        return (f"the scene is {'a single object' if objs == 1 else f'{objs} objects'} with no floor: walk and fly "
                "cannot be planned on it; use the camera orbit")
    if len(np.unique(geom.owner)) == 1 and geom.extent * geom.metres_per_unit < SINGLE_OBJECT_M:
        return ("the scene is a single object, nothing a camera moves inside: walk and fly find no path on it; "
                "use the camera orbit")
    kind, region = clip.kind, clip.region
    other = "fly" if kind == "walk" else "walk"
    tries = [(f"use the camera {other} for this clip", other, region, None)]
    if region is not None:
        tries.append(('use fewer regions (regions = "1x1"): the whole level has a path', kind, None, None))
    scores = (unit or {}).get("scores") or {}
    from .level_scale import UNITS
    for name in sorted(scores, key=lambda k: -scores[k])[1:3]:
        if name in UNITS:
            tries.append((f"set unit_scale = {UNITS[name]:g} ({name}): the level has a path in that unit", kind,
                          region, UNITS[name]))
    keep = geom.metres_per_unit
    try:
        for text, k, reg, mpu in tries:
            geom.metres_per_unit = keep if mpu is None else mpu
            try:
                clip.path(geom, rules, kind=k, region=reg)
            except PathError:
                continue
            return text
    finally:
        geom.metres_per_unit = keep
    return "no other camera kind, region or unit gives a path: use cameras scene:NAME (the file's own camera)"


def _whole(geom: LevelGeometry):
    lo, hi = geom.content_bounds()
    return (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1]))
