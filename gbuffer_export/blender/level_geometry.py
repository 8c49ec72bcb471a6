"""The triangles of a level and the queries camera planning needs (trimesh + Embree; bpy only in ``from_scene``).

:class:`LevelGeometry` holds the evaluated world-space triangles of every renderable object (instances, modifiers,
armatures and shape keys applied, at one frame) and answers ray and distance queries on them:

- rays: ``trimesh``'s Embree engine (``embreex``, installed with the ``[render]`` extra) when it imports, else
  trimesh's own (rtree-based) engine. Embree casts about 10^5 rays per second on this 2-core machine against
  about 400 for trimesh's own on an 80 k-triangle mesh (measured 2026-11-25), and a path plan casts a few
  thousand rays per try, so Embree is what makes planning on real levels take seconds.
- nearest distance (exact point-to-triangle): Blender's ``mathutils.bvhtree.BVHTree`` when bpy is importable,
  else ``trimesh.proximity.closest_point``. On a 1.3 M-triangle mesh BVHTree answers a query in 1-50 ms after a
  9 s build; trimesh took 1-4 s per query (measured 2026-11-25), too slow for a planner that asks once per step.

Distances are in scene units; :attr:`LevelGeometry.metres_per_unit` converts (the scene's unit scale).
A level's *content box* (:meth:`LevelGeometry.content_bounds`) is the 1st-99th percentile box of its triangle
centroids, leaving out objects that enclose all the others (a ground plane, a skybox: an x-y box at least 3x as wide
and deep as the others' around their centre): a 2 km ground plane or a skybox does not widen it, while streets and rooms (many
triangles) define it. Its diagonal is the level's *extent*.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from ..errors import BlendSRError

GEOMETRY_TYPES = frozenset({"MESH", "CURVE", "SURFACE", "META", "FONT"})


class LevelGeometryError(BlendSRError):
    """A level whose triangles cannot hold a camera path (none, or none of non-zero area)."""


def _ray_engine(mesh):
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
        return RayMeshIntersector(mesh), "embree"
    except Exception:  # embreex missing or failing to load: trimesh's own engine gives the same answers, slower
        from trimesh.ray.ray_triangle import RayMeshIntersector
        return RayMeshIntersector(mesh), "trimesh"


@dataclass
class LevelGeometry:
    """World-space triangles (``vertices`` (V, 3) float64, ``faces`` (F, 3) int64) with ray and distance queries."""

    vertices: np.ndarray
    faces: np.ndarray
    metres_per_unit: float = 1.0
    names: list = field(default_factory=list)
    owner: np.ndarray | None = None  # (F,) index of the object each triangle belongs to (None: one object)

    def __post_init__(self):
        import trimesh
        self.vertices = np.asarray(self.vertices, np.float64)
        self.faces = np.asarray(self.faces, np.int64)
        if len(self.faces) == 0:
            raise LevelGeometryError("the level has no renderable triangles")
        owner = np.zeros(len(self.faces), np.int64) if self.owner is None else np.asarray(self.owner, np.int64)
        self.mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        keep = self.mesh.area_faces > 0
        if not keep.any():  # every triangle collapsed to a line or a point (a mesh scaled to zero)
            raise LevelGeometryError(f"the level has no triangle of non-zero area (all {len(self.faces)} are "
                               "degenerate: a mesh of zero extent), so no camera path can be planned in it")
        if not keep.all():  # degenerate triangles have no normal and break Embree's winding test
            self.mesh = trimesh.Trimesh(self.vertices, self.faces[keep], process=False)
            owner = owner[keep]
        self.owner = owner
        self._content_mask = self._not_enclosing()
        self.normals = np.asarray(self.mesh.face_normals, np.float64)
        self.rays, self.engine = _ray_engine(self.mesh)
        self._bvh = None
        lo, hi = self.content_bounds()
        self.extent = float(np.linalg.norm(hi - lo))

    @property
    def n_triangles(self) -> int:
        return int(len(self.mesh.faces))

    def units(self, metres: float) -> float:
        """``metres`` in scene units."""
        return metres / self.metres_per_unit

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.mesh.bounds[0].copy(), self.mesh.bounds[1].copy()

    def _not_enclosing(self) -> np.ndarray:
        """(F,) bool: False on the triangles of *enclosing* objects, whose x-y box is at least 3x as wide and 3x as
        deep as the other objects' united box and holds its centre (a ground plane, a skybox); a room's walls,
        about as large as what they hold, stay content."""
        c = self.mesh.triangles_center
        ids = np.unique(self.owner)
        if len(ids) < 2:
            return np.ones(len(c), dtype=bool)
        tri = self.mesh.triangles
        full = {i: (tri[self.owner == i].reshape(-1, 3).min(axis=0), tri[self.owner == i].reshape(-1, 3).max(axis=0))
                for i in ids}
        mask = np.ones(len(c), dtype=bool)
        for i in ids:
            others = [full[j] for j in ids if j != i]
            lo = np.min([b[0] for b in others], axis=0)
            hi = np.max([b[1] for b in others], axis=0)
            blo, bhi = full[i]
            centre = 0.5 * (lo + hi)
            if np.all(bhi[:2] - blo[:2] >= 3 * np.maximum(hi[:2] - lo[:2], 1e-9)) \
                    and np.all(blo[:2] <= centre[:2]) and np.all(bhi[:2] >= centre[:2]):
                shell = enclosure(trimesh_of(tri[self.owner == i]), lo, hi)
                if not (shell["upper_hits"] >= SHELL_UPPER_HITS and shell["gap_below"] < SHELL_FLOOR_GAP):
                    mask[self.owner == i] = False  # a room's shell (roof over, floor under the others) stays
        return mask if mask.any() else np.ones(len(c), dtype=bool)

    def content_bounds(self, pct: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) (3,): the ``pct``..``100-pct`` percentile box of the triangle centroids of every object that
        does not enclose the others (see module doc)."""
        c = self.mesh.triangles_center[self._content_mask]
        return np.percentile(c, pct, axis=0), np.percentile(c, 100.0 - pct, axis=0)

    def first_hits(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance to the first hit along each unit ray (inf on a miss) and the triangle hit (-1 on a miss)."""
        return nearest_hits(self.rays, origins, dirs)

    def all_hits(self, origin: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every hit along one ray, sorted by distance: (distances, triangles)."""
        t, r, loc = self.rays.intersects_id(np.asarray(origin, np.float64)[None], np.asarray(direction,
                                            np.float64)[None], multiple_hits=True, return_locations=True)
        if len(t) == 0:
            return np.zeros(0), np.zeros(0, np.int64)
        d = np.linalg.norm(loc - np.asarray(origin)[None], axis=1)
        o = np.argsort(d)
        return d[o], np.asarray(t)[o]

    def nearest_distance(self, points: np.ndarray) -> np.ndarray:
        """Exact distance (scene units) from each point (N, 3) to the nearest triangle."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if self._bvh is None:
            self._bvh = _bvh_tree(self.mesh) or False
        if self._bvh is False:
            import trimesh
            _, dist, _ = trimesh.proximity.closest_point(self.mesh, points)
            return np.asarray(dist, np.float64)
        out = np.empty(len(points))
        for i, p in enumerate(points):
            hit = self._bvh.find_nearest(p.tolist())
            out[i] = hit[3] if hit[0] is not None else np.inf
        return out

    def inside_closed_mesh(self, point: np.ndarray, n_dirs: int = 26, frac: float = 0.5,
                           solid_m: float = 1.5) -> bool:
        """True when more than ``frac`` of rays in ``n_dirs`` directions first hit the back of a triangle and those
        hits are close (median within ``solid_m`` metres): the point is inside a solid object (a pillar, a car
        body). Rays that hit a front face or nothing leave it outside, so rooms and skyboxes whose faces look
        inwards are the space a camera lives in, and so is a room modelled with outward normals (its back faces
        are metres away)."""
        d = sphere_directions(n_dirs)
        dist, tri = self.first_hits(np.repeat(np.asarray(point, np.float64)[None], len(d), axis=0), d)
        hit = tri >= 0
        back = np.zeros(len(d), dtype=bool)
        back[hit] = np.einsum("ij,ij->i", self.normals[tri[hit]], d[hit]) > 0
        if back.mean() <= frac:
            return False
        return bool(np.median(dist[back]) * self.metres_per_unit <= solid_m)


#: An object around the others is their room when it covers this fraction of the upper hemisphere seen from their
#: centre and its floor lies under them within this fraction of their size (``enclosure``).
SHELL_UPPER_HITS = 0.9
SHELL_FLOOR_GAP = 0.25


def trimesh_of(triangles: np.ndarray):
    """A trimesh of the triangles (T, 3, 3)."""
    import trimesh
    t = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    return trimesh.Trimesh(t.reshape(-1, 3), np.arange(len(t) * 3).reshape(-1, 3), process=False)


def enclosure(mesh, lo: np.ndarray, hi: np.ndarray, n: int = 256) -> dict:
    """How the mesh ``mesh`` (a trimesh) surrounds the box ``lo``..``hi`` (the rest of a level): ``upper_hits``,
    the fraction of ``n``/2 rays from the box's centre over the upper hemisphere that hit it; ``front_inside``,
    the fraction of those hits on a face turned to the centre; ``gap_below``, the median distance from the box's
    bottom down to it along vertical rays from a 5x5 grid over the box, over the box's largest side (about 0 when
    it is the floor the box stands on, inf when nothing is below)."""
    rays, _ = _ray_engine(mesh)
    d = sphere_directions(n)
    up = d[d[:, 2] > 0.05]
    centre = 0.5 * (np.asarray(lo, np.float64) + np.asarray(hi, np.float64))
    _, first = nearest_hits(rays, np.repeat(centre[None], len(up), axis=0), up)
    hit = first >= 0
    normals = np.asarray(mesh.face_normals)
    inside = float((np.einsum("ij,ij->i", normals[first[hit]], up[hit]) < 0).mean()) if hit.any() else 0.0
    u = (np.arange(5) + 0.5) / 5
    xx, yy = np.meshgrid(lo[0] + u * (hi[0] - lo[0]), lo[1] + u * (hi[1] - lo[1]))
    origins = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, hi[2])], axis=1)
    dist, _ = nearest_hits(rays, origins, np.repeat(np.array([[0.0, 0.0, -1.0]]), len(origins), axis=0))
    gap = dist - (hi[2] - lo[2])  # from the box's bottom
    size = float(np.max(np.asarray(hi) - np.asarray(lo))) or 1.0
    return {"upper_hits": float(hit.mean()), "front_inside": inside, "gap_below": float(np.median(gap)) / size}


def nearest_hits(rays, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance to the first hit of each unit ray on the intersector ``rays`` (inf on a miss) and the triangle hit
    (-1 on a miss)."""
    origins = np.asarray(origins, np.float64).reshape(-1, 3)
    dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
    dist = np.full(len(origins), np.inf)
    tri = np.full(len(origins), -1, dtype=np.int64)
    if len(origins) == 0:
        return dist, tri
    t, r, loc = rays.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    if len(t):
        d = np.linalg.norm(loc - origins[r], axis=1)
        order = np.argsort(-d)  # keep the nearest when an engine reports several per ray
        dist[r[order]] = d[order]
        tri[r[order]] = t[order]
    return dist, tri


def _bvh_tree(mesh):
    """Blender's BVH over the triangles, or None without bpy."""
    try:
        import bpy  # noqa: F401  (mathutils comes with the bpy module)
        from mathutils.bvhtree import BVHTree
    except ImportError:
        return None
    return BVHTree.FromPolygons(np.asarray(mesh.vertices).tolist(), np.asarray(mesh.faces).tolist(),
                                all_triangles=True)


def sphere_directions(n: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (a Fibonacci lattice), (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (1.0 + 5 ** 0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def metres_per_unit(scene) -> float:
    """Metres per Blender unit of ``scene`` (its unit scale; 1 when the unit system is NONE)."""
    us = scene.unit_settings
    return float(us.scale_length) if us.system != "NONE" and us.scale_length > 0 else 1.0


def from_scene(scene, frame: int | None = None) -> LevelGeometry:
    """The evaluated triangles of every renderable object of ``scene`` at ``frame`` (default: the current one)."""
    import bpy

    if frame is not None:
        scene.frame_set(int(frame))
    dg = bpy.context.evaluated_depsgraph_get() if scene == bpy.context.scene else scene.view_layers[0].depsgraph
    verts, faces, names, owner = [], [], [], []
    offset = 0
    for inst in dg.object_instances:
        ob = inst.object
        orig = ob.original
        if ob.type not in GEOMETRY_TYPES or orig.hide_render or any(c.hide_render for c in orig.users_collection):
            continue
        if inst.is_instance and inst.parent is not None and inst.parent.original.hide_render:
            continue
        try:
            me = ob.to_mesh()
        except RuntimeError:
            continue
        try:
            me.calc_loop_triangles()
            n, nt = len(me.vertices), len(me.loop_triangles)
            if n == 0 or nt == 0:
                continue
            v = np.empty(n * 3, dtype=np.float64)
            me.vertices.foreach_get("co", v)
            t = np.empty(nt * 3, dtype=np.int64)
            me.loop_triangles.foreach_get("vertices", t)
        finally:
            ob.to_mesh_clear()
        m = np.array(inst.matrix_world, dtype=np.float64)
        verts.append(v.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3])
        faces.append(t.reshape(-1, 3) + offset)
        owner.append(np.full(nt, len(names)))
        names.append(orig.name if not inst.is_instance else f"{orig.name}#{len(names)}")
        offset += n
    if not verts:
        raise BlendSRError(f"scene {scene.name!r} has no renderable triangles")
    return LevelGeometry(np.concatenate(verts), np.concatenate(faces), metres_per_unit(scene), names,
                         np.concatenate(owner))
