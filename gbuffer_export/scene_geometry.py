"""What a scene's geometry must be before anything renders (pure numpy, no bpy): faces to render, finite vertex
positions, a non-zero extent and one Blender's 32-bit positions can hold. ``geometry_problem`` judges a summary the
bpy layer measures (``gbuffer_export.blender.scene_setup.geometry_summary``); the render refuses a scene it finds a
problem in before rendering, in one line naming the file (``docs/rendering.md``, "Scene formats")."""
from __future__ import annotations

import math
from dataclasses import dataclass

#: The largest scene rendered, in scene units (Blender's positions are 32-bit in units, whatever a unit means): its
#: extent (the diagonal of its geometry's box) and its farthest coordinate from the origin. At 1e6 units a position
#: steps by 1/16 unit; at the 1e7 of a planet-sized file by a whole unit (depth, motion and camera paths break).
MAX_EXTENT_UNITS = 1e6
#: Below this extent (relative to the farthest coordinate, or absolutely below 1e-9 units) every vertex is at one
#: point: nothing covers a pixel.
MIN_EXTENT_REL = 1e-7


@dataclass(frozen=True)
class GeometrySummary:
    """The scene's mesh geometry as rendered: ``vertices`` and ``faces`` of its renderable meshes, how many vertices
    are NaN or infinite, the world box of the finite ones (``lo``/``hi``, None without any), its metres per unit and
    whether it holds other renderable geometry (curves, text, volumes, instancers) this summary does not measure."""

    vertices: int
    faces: int
    nonfinite: int
    lo: tuple[float, float, float] | None
    hi: tuple[float, float, float] | None
    metres_per_unit: float = 1.0
    other: bool = False

    @property
    def extent(self) -> float | None:
        """The diagonal of the geometry's box in scene units (None without finite vertices)."""
        if self.lo is None or self.hi is None:
            return None
        return math.dist(self.lo, self.hi)

    @property
    def reach(self) -> float:
        """The largest absolute coordinate of a finite vertex (scene units)."""
        return max((abs(v) for v in (*(self.lo or ()), *(self.hi or ()))), default=0.0)


def geometry_problem(g: GeometrySummary) -> str | None:
    """What is wrong with the geometry (a phrase to follow the file's name), or None when it can be rendered."""
    if g.other and g.faces == 0:
        return None  # only geometry this summary does not measure: Cycles renders it as it is
    if g.vertices == 0:
        return "has no geometry to render (no mesh, or meshes without vertices)"
    if g.faces == 0:
        return (f"has {g.vertices} vertices but no faces (a truncated file, or points only): nothing to render")
    if g.nonfinite >= g.vertices:
        return f"every one of its {g.vertices} vertices is NaN or infinite: nothing to render"
    extent, reach = g.extent, g.reach
    if extent is None or not (math.isfinite(extent) and math.isfinite(reach)):
        return "its vertex positions overflow (no finite extent)"
    if extent <= max(MIN_EXTENT_REL * reach, 1e-9) and not g.other:
        return "is degenerate: its geometry has zero extent (every vertex at one point): nothing to render"
    if max(extent, reach) > MAX_EXTENT_UNITS:
        what = f"an extent of {extent:.3g}" if extent >= reach else f"a vertex {reach:.3g}"
        metres = f" ({max(extent, reach) * g.metres_per_unit:.3g} m)" if g.metres_per_unit != 1.0 else ""
        return (f"is absurdly large: {what} units from {'corner to corner' if extent >= reach else 'the origin'}"
                f"{metres}, beyond the {MAX_EXTENT_UNITS:g} units Blender's 32-bit positions hold to 1/16 unit "
                "(depth, motion and camera paths break); scale it down or fix its unit")
    return None
