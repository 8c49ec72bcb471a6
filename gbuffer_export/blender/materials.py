"""Material inspection and per-pixel material parameters (bpy layer).

``inspect_materials`` records which features each material uses and which flag bits (``conventions.Flag``) its
pixels get. ``install_aovs`` adds Shader AOV Output nodes so that Cycles writes base colour, roughness, metallic
and dielectric F0 per pixel, fed from the same sockets as the Principled BSDF (textures included).

``gbuffer_transmission = "behind"``: ``transmissive_materials`` names the materials a deferred renderer would
forward-render (glass, water), ``install_behind`` prepares them and ``see_through`` makes them a Transparent BSDF
for the G-buffer renders (restored afterwards), so that Cycles' data passes, colour passes and AOVs describe the
first surface behind them.
"""
from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass, field

import bpy

from ..conventions import Flag

AOV_COLOR = {"albedo": "bsr_albedo"}
AOV_VALUE = {"roughness": "bsr_roughness", "metallic": "bsr_metallic", "specular": "bsr_specular"}


@dataclass
class MaterialInfo:
    """What a material uses. ``index`` is the material pass index BlendSR assigns (1-based)."""

    name: str
    index: int
    principled: bool
    features: list[str] = field(default_factory=list)
    flags: int = 0

    def to_json(self) -> dict:
        return asdict(self)


#: ``gbuffer_transmission = "behind"``: the AOV that marks a sample whose first hit is a transmissive surface (its
#: alpha: 0 on a cut-out hole, 1 on glass), written in the G-buffer renders; ``convert`` sets Flag.TRANSMISSION where
#: it is above ``REACTIVE_MIN`` (the reactive mask). The shader node types that transmit the scene behind them.
AOV_REACTIVE = "bsr_transmissive"
REACTIVE_MIN = 1e-3
TRANSMISSIVE_NODES = ("BSDF_GLASS", "BSDF_REFRACTION")
BEHIND_LABEL = "BlendSR behind"


def _input(node, *names):
    for n in names:
        if n in node.inputs:
            return node.inputs[n]
    return None


def _nonzero(sock, threshold=1e-6) -> bool:
    """True when an input socket is linked (texture-driven) or its default value is non-zero."""
    if sock is None:
        return False
    if sock.is_linked:
        return True
    v = sock.default_value
    try:
        return any(abs(x) > threshold for x in v)
    except TypeError:
        return abs(v) > threshold


def _surface_node(mat):
    """The node feeding the Cycles material output's Surface, or None."""
    if not mat.node_tree:
        return None, None
    out = mat.node_tree.get_output_node("CYCLES")
    if out is None:
        return None, None
    surf = out.inputs.get("Surface")
    vol = out.inputs.get("Volume")
    node = surf.links[0].from_node if surf is not None and surf.is_linked else None
    return node, (vol is not None and vol.is_linked)


def inspect_material(mat, index: int) -> MaterialInfo:
    """Features and flag bits of one material."""
    info = MaterialInfo(name=mat.name, index=index, principled=False)
    node, has_volume = _surface_node(mat)
    flags = Flag(0)
    if has_volume:
        info.features.append("volume")
        flags |= Flag.VOLUME
    if node is None or node.type != "BSDF_PRINCIPLED":
        info.features.append(f"shader:{node.type.lower() if node is not None else 'none'}")
        flags |= Flag.NON_PRINCIPLED
        info.flags = int(flags)
        return info
    info.principled = True
    aniso = _input(node, "Anisotropic")
    if _nonzero(aniso):
        info.features.append("anisotropic")
        flags |= Flag.ANISOTROPIC
    tint = _input(node, "Specular Tint")
    if tint is not None and (tint.is_linked or any(abs(c - 1.0) > 1e-4 for c in tint.default_value[:3])):
        info.features.append("specular_tint")
        flags |= Flag.SPECULAR_TINT
    if _nonzero(_input(node, "Subsurface Weight")):
        info.features.append("subsurface")
        flags |= Flag.SUBSURFACE
    alpha = _input(node, "Alpha")
    if alpha is not None and (alpha.is_linked or alpha.default_value < 1.0 - 1e-6):
        info.features.append("alpha")
        flags |= Flag.ALPHA
    strength = _input(node, "Emission Strength")
    ecol = _input(node, "Emission Color")
    if _nonzero(strength) and _nonzero(ecol):
        info.features.append("emission")
        flags |= Flag.EMISSIVE
    if _nonzero(_input(node, "Metallic")):
        info.features.append("metallic")
    if _nonzero(_input(node, "Transmission Weight")):
        info.features.append("transmission")
        flags |= Flag.TRANSMISSION
    if _nonzero(_input(node, "Coat Weight")):
        info.features.append("coat")
        flags |= Flag.COAT
    if _nonzero(_input(node, "Sheen Weight")):
        info.features.append("sheen")
        flags |= Flag.SHEEN
    if _nonzero(_input(node, "Thin Film Thickness")):
        info.features.append("thin_film")
        flags |= Flag.THIN_FILM
    normal = _input(node, "Normal")
    if normal is not None and normal.is_linked:
        info.features.append("normal_map_or_bump")
    if getattr(node, "distribution", "MULTI_GGX") != "MULTI_GGX":
        info.features.append(f"distribution:{node.distribution.lower()}")
        flags |= Flag.SINGLE_SCATTER_GGX
    info.flags = int(flags)
    return info


def scene_materials(scene) -> list:
    """Materials used by renderable objects of the scene, in a deterministic order."""
    mats = {}
    for ob in scene.objects:
        if ob.hide_render or not hasattr(ob, "material_slots"):
            continue
        for slot in ob.material_slots:
            if slot.material is not None:
                mats[slot.material.name] = slot.material
    return [mats[k] for k in sorted(mats)]


def inspect_materials(scene) -> dict[str, MaterialInfo]:
    """Inspect every material in use, assigning pass indices 1..N (index 0 means no material)."""
    infos = {}
    for i, mat in enumerate(scene_materials(scene), start=1):
        mat.pass_index = i
        infos[mat.name] = inspect_material(mat, i)
    return infos


def material_summary(infos: dict[str, MaterialInfo]) -> dict:
    """Counts of each feature over the scene's materials, for the manifest."""
    counts: dict[str, int] = {}
    for info in infos.values():
        for f in info.features:
            counts[f] = counts.get(f, 0) + 1
    return {"materials": len(infos), "principled": sum(i.principled for i in infos.values()),
            "features": dict(sorted(counts.items()))}


def _feed(tree, src_sock, dst_sock):
    """Connect whatever feeds ``src_sock`` (or copy its value) into ``dst_sock``."""
    if src_sock.is_linked:
        tree.links.new(src_sock.links[0].from_socket, dst_sock)
    else:
        v = src_sock.default_value
        try:
            dst_sock.default_value = v
        except (TypeError, ValueError):
            dst_sock.default_value = v[0] if hasattr(v, "__len__") else (v, v, v, 1.0)


def _f0_from_ior(tree, node, dst_sock):
    """Wire dielectric F0 = ((ior-1)/(ior+1))^2 * 2 * specular_ior_level, clamped to [0,1], into ``dst_sock``."""
    nodes, links = tree.nodes, tree.links

    def math(op, a, b=None):
        m = nodes.new("ShaderNodeMath")
        m.operation = op
        m.label = "BlendSR F0"
        for i, src in enumerate((a, b)):
            if src is None:
                continue
            if isinstance(src, (int, float)):
                m.inputs[i].default_value = float(src)
            elif hasattr(src, "is_output") and src.is_output:
                links.new(src, m.inputs[i])
            else:  # an input socket of the Principled node: follow its link or copy its value
                _feed(tree, src, m.inputs[i])
        return m.outputs[0]

    ior = _input(node, "IOR")
    level = _input(node, "Specular IOR Level")
    num = math("SUBTRACT", ior, 1.0)
    den = math("ADD", ior, 1.0)
    r = math("DIVIDE", num, den)
    r2 = math("MULTIPLY", r, r)
    scaled = math("MULTIPLY", r2, math("MULTIPLY", level, 2.0)) if level is not None else r2
    clamped = nodes.new("ShaderNodeClamp")
    links.new(scaled, clamped.inputs["Value"])
    links.new(clamped.outputs[0], dst_sock)


#: The least pass alpha threshold BlendSR renders with: at 0 Cycles writes the data passes on the first surface a
#: camera ray meets, a cut-out hole included.
MIN_ALPHA_THRESHOLD = 1e-6


def raise_alpha_threshold(view_layer) -> float:
    """Raise the view layer's pass alpha threshold to ``MIN_ALPHA_THRESHOLD`` if it is below; returns it."""
    if view_layer.pass_alpha_threshold < MIN_ALPHA_THRESHOLD:
        view_layer.pass_alpha_threshold = MIN_ALPHA_THRESHOLD
    return view_layer.pass_alpha_threshold


def install_aovs(scene, view_layer, infos: dict[str, MaterialInfo], buffers) -> list[str]:
    """Add AOV outputs for the requested parameter buffers to every Principled material; returns AOV names. On an
    ALPHA material each is 0 where the alpha is under the view layer's pass alpha threshold (``_times_coverage``).
    Call ``raise_alpha_threshold`` first."""
    wanted = [b for b in (*AOV_COLOR, *AOV_VALUE) if b in buffers]
    if not wanted:
        return []
    existing = {a.name for a in view_layer.aovs}
    for b in wanted:
        name = AOV_COLOR.get(b) or AOV_VALUE[b]
        if name not in existing:
            aov = view_layer.aovs.add()
            aov.name = name
            aov.type = "COLOR" if b in AOV_COLOR else "VALUE"
    for mat in scene_materials(scene):
        info = infos.get(mat.name)
        if info is None:
            continue
        node, _ = _surface_node(mat)
        tree = mat.node_tree
        if not info.principled:
            _install_simple_aovs(tree, node, wanted)
            continue
        coverage = _coverage(tree, node, view_layer.pass_alpha_threshold) if info.flags & Flag.ALPHA else None
        for b in wanted:
            out = tree.nodes.new("ShaderNodeOutputAOV")
            out.aov_name = AOV_COLOR.get(b) or AOV_VALUE[b]
            dst = out.inputs["Color" if b in AOV_COLOR else "Value"]
            if b == "albedo":
                _feed(tree, _input(node, "Base Color"), dst)
            elif b == "roughness":
                _feed(tree, _input(node, "Roughness"), dst)
            elif b == "metallic":
                _feed(tree, _input(node, "Metallic"), dst)
            elif b == "specular":
                _f0_from_ior(tree, node, dst)
            if coverage is not None:
                _times_coverage(tree, coverage, dst)
    return [AOV_COLOR.get(b) or AOV_VALUE[b] for b in wanted]


def _coverage(tree, node, threshold: float):
    """An output socket that is 1 where the Principled BSDF's Alpha (its link or its value) is at least
    ``threshold`` (the view layer's pass alpha threshold) and 0 below: whether Cycles' data passes stop on the
    surface there."""
    below = tree.nodes.new("ShaderNodeMath")
    below.operation, below.label = "LESS_THAN", "BlendSR coverage"
    _feed(tree, _input(node, "Alpha"), below.inputs[0])
    below.inputs[1].default_value = threshold
    above = tree.nodes.new("ShaderNodeMath")
    above.operation, above.label = "SUBTRACT", "BlendSR coverage"
    above.inputs[0].default_value = 1.0
    tree.links.new(below.outputs[0], above.inputs[1])
    return above.outputs[0]


def _times_coverage(tree, coverage, dst) -> None:
    """Feed ``dst`` (an AOV output's input) with what fed it times ``coverage`` (``_coverage``). Cycles writes a
    camera path's AOVs at every surface it passes, unweighted, up to and including the first surface whose alpha
    reaches the pass alpha threshold, where it writes the data passes (measured: 2.4 = 0.8 + 0.8 + 0.8 at a hole
    of a two-faced pane of alpha 0 before a wall). Zero below the threshold leaves that surface's value alone: the
    AOVs describe the surface the data passes describe (docs/rendering.md, "Alpha cut-outs")."""
    colour = dst.type == "RGBA"
    m = tree.nodes.new("ShaderNodeVectorMath" if colour else "ShaderNodeMath")
    m.operation = "SCALE" if colour else "MULTIPLY"
    m.label = "BlendSR coverage"
    value_in, factor_in = (m.inputs[0], m.inputs["Scale"]) if colour else (m.inputs[0], m.inputs[1])
    if dst.is_linked:
        tree.links.new(dst.links[0].from_socket, value_in)
    else:
        value_in.default_value = tuple(dst.default_value)[:3] if colour else dst.default_value
    tree.links.new(coverage, factor_in)
    tree.links.new(m.outputs[0], dst)


def _install_simple_aovs(tree, node, wanted) -> None:
    """Best-effort parameters for a plain Diffuse or Glossy BSDF (their pixels stay flagged NON_PRINCIPLED)."""
    if node is None or node.type not in ("BSDF_DIFFUSE", "BSDF_GLOSSY"):
        return
    values = {"metallic": 1.0 if node.type == "BSDF_GLOSSY" else 0.0, "specular": 0.0,
              "roughness": 1.0 if node.type == "BSDF_DIFFUSE" else None}
    for b in wanted:
        out = tree.nodes.new("ShaderNodeOutputAOV")
        out.aov_name = AOV_COLOR.get(b) or AOV_VALUE[b]
        if b == "albedo":
            _feed(tree, node.inputs["Color"], out.inputs["Color"])
        elif b == "roughness" and values["roughness"] is None:
            _feed(tree, node.inputs["Roughness"], out.inputs["Value"])
        else:
            out.inputs["Value"].default_value = values[b]


def _shader_nodes(node, seen=None):
    """``node`` and the shader nodes feeding it through Mix/Add Shader nodes (the closures a surface mixes)."""
    seen = set() if seen is None else seen
    if node is None or node.name in seen:
        return []
    seen.add(node.name)
    out = [node]
    if node.type in ("MIX_SHADER", "ADD_SHADER"):
        for sock in node.inputs:
            if sock.type == "SHADER" and sock.is_linked:
                out += _shader_nodes(sock.links[0].from_node, seen)
    return out


def is_transmissive(mat, info: MaterialInfo) -> bool:
    """Whether the material shows the scene behind it by refraction: a Principled BSDF with transmission
    (``Flag.TRANSMISSION``), or a Glass or Refraction BSDF anywhere in the shaders its surface mixes."""
    if info.flags & Flag.TRANSMISSION:
        return True
    node, _ = _surface_node(mat)
    for n in _shader_nodes(node):
        if n.type in TRANSMISSIVE_NODES or (n.type == "BSDF_PRINCIPLED"
                                            and _nonzero(_input(n, "Transmission Weight"))):
            return True
    return False


def transmissive_materials(scene, infos: dict[str, MaterialInfo]) -> tuple[str, ...]:
    """Names of the scene's transmissive materials (``is_transmissive``), sorted."""
    return tuple(m.name for m in scene_materials(scene) if m.name in infos and is_transmissive(m, infos[m.name]))


def install_behind(view_layer, names) -> None:
    """Prepare the materials ``names`` for ``see_through``: an unlinked Transparent BSDF (labelled ``BEHIND_LABEL``)
    and an AOV output ``AOV_REACTIVE`` fed from the Principled Alpha (1 for other shaders) in each; the view layer's
    AOV. Call ``raise_alpha_threshold`` first (Cycles writes data passes on transparent surfaces at 0)."""
    if not names:
        return
    if AOV_REACTIVE not in {a.name for a in view_layer.aovs}:
        aov = view_layer.aovs.add()
        aov.name, aov.type = AOV_REACTIVE, "VALUE"
    for name in names:
        tree = bpy.data.materials[name].node_tree
        node, _ = _surface_node(bpy.data.materials[name])
        transparent = tree.nodes.new("ShaderNodeBsdfTransparent")
        transparent.label = BEHIND_LABEL
        transparent.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        out = tree.nodes.new("ShaderNodeOutputAOV")
        out.aov_name = AOV_REACTIVE
        alpha = _input(node, "Alpha") if node is not None and node.type == "BSDF_PRINCIPLED" else None
        if alpha is not None:
            _feed(tree, alpha, out.inputs["Value"])
        else:
            out.inputs["Value"].default_value = 1.0


def is_volume_only(mat) -> bool:
    """True when ``mat``'s Cycles output has a volume shader and no surface one: a participating medium's domain (fog,
    smoke), whose boundary no ray stops at."""
    node, has_volume = _surface_node(mat)
    return bool(has_volume) and node is None


def volume_domain(ob) -> bool:
    """True when every material of ``ob`` is volume-only (``is_volume_only``): a fog or smoke box is a medium to see
    through, not a surface to frame, keep a camera clear of, or record in a G-buffer."""
    slots = [s.material for s in getattr(ob, "material_slots", ())]
    return bool(slots) and all(m is not None and is_volume_only(m) for m in slots)


@contextlib.contextmanager
def volumes_muted(scene):
    """While inside, the volume-only materials of ``scene``'s objects have their Volume output unlinked: the
    G-buffer passes hold the first surface behind fog, as a game's G-buffer does (Cycles stops the passes of a
    camera ray at its first volume scattering event). Restored on leaving, also on an error."""
    saved = []
    mats = {s.material for ob in scene.objects for s in getattr(ob, "material_slots", ()) if s.material is not None}
    try:
        for mat in sorted((m for m in mats if is_volume_only(m)), key=lambda m: m.name):
            out = mat.node_tree.get_output_node("CYCLES")
            link = out.inputs["Volume"].links[0]
            saved.append((mat.node_tree, link.from_socket, out.inputs["Volume"]))
            mat.node_tree.links.remove(link)
        yield
    finally:
        for tree, src, dst in saved:
            tree.links.new(src, dst)


@contextlib.contextmanager
def see_through(names):
    """While inside, each material of ``names`` (prepared by ``install_behind``) is a white Transparent BSDF: its
    surface output fed by it, its volume unlinked, its AOV outputs but ``AOV_REACTIVE`` writing to no AOV (Cycles
    evaluates a muted AOV output all the same, measured: the glass's albedo added to the one behind). Every link and
    AOV name is restored on leaving, also on an error."""
    saved = []
    try:
        for name in names:
            tree = bpy.data.materials[name].node_tree
            out = tree.get_output_node("CYCLES")
            transparent = next(n for n in tree.nodes if n.label == BEHIND_LABEL)
            links = {k: (out.inputs[k].links[0].from_socket if out.inputs[k].is_linked else None)
                     for k in ("Surface", "Volume") if k in out.inputs}
            aovs = [(n, n.aov_name) for n in tree.nodes if n.type == "OUTPUT_AOV" and n.aov_name != AOV_REACTIVE]
            saved.append((tree, out, links, aovs))
            tree.links.new(transparent.outputs["BSDF"], out.inputs["Surface"])
            for ln in list(out.inputs["Volume"].links) if "Volume" in out.inputs else ():
                tree.links.remove(ln)
            for n, _ in aovs:
                n.aov_name = ""
        yield
    finally:
        for tree, out, links, aovs in saved:
            for k, src in links.items():
                for ln in list(out.inputs[k].links):
                    tree.links.remove(ln)
                if src is not None:
                    tree.links.new(src, out.inputs[k])
            for n, name in aovs:
                n.aov_name = name


def object_is_moving(ob, scene, frame: int) -> bool:
    """True when the object's world transform or its deformation may differ between frame-1 and frame
    (animated transform, parent, armature, shape keys or any modifier with animation)."""
    if ob.animation_data and ob.animation_data.action:
        return True
    if ob.parent is not None and object_is_moving(ob.parent, scene, frame):
        return True
    for mod in getattr(ob, "modifiers", []):
        if mod.type in ("ARMATURE", "CLOTH", "SOFT_BODY", "FLUID", "DYNAMIC_PAINT", "OCEAN", "WAVE"):
            return True
    data = getattr(ob, "data", None)
    keys = getattr(data, "shape_keys", None) if data is not None else None
    if keys is not None and keys.animation_data and keys.animation_data.action:
        return True
    return False


# ----------------------------------------------------------------------------------------------
# Untextured materials (RenderConfig.materials = "untextured")
# ----------------------------------------------------------------------------------------------

def _is_data(image) -> bool:
    cs = image.colorspace_settings
    return bool(cs.is_data) or cs.name in ("Non-Color", "Raw")


def image_mean(image) -> tuple[float, ...] | None:
    """The mean RGBA of ``image`` as its Image Texture node outputs it: a colour image's pixels decoded from sRGB to
    linear first, RGB weighted by alpha (cut-out texels' colours are not seen), alpha its plain mean. None when the
    image has no pixels Blender can read (missing file, a movie, tiles)."""
    import numpy as np

    from ..colour_spaces import srgb_decode
    if image is None or image.source not in ("FILE", "GENERATED") or image.size[0] == 0 or image.size[1] == 0:
        return None
    n = image.size[0] * image.size[1] * image.channels
    if n == 0 or len(image.pixels) != n:
        return None
    px = np.empty(n, np.float32)
    image.pixels.foreach_get(px)
    px = px.reshape(-1, image.channels).astype(np.float64)
    rgb = px[:, :3] if image.channels >= 3 else np.repeat(px[:, :1], 3, axis=1)
    alpha = px[:, 3] if image.channels == 4 else np.ones(len(px))
    if not _is_data(image) and image.colorspace_settings.name.lower().startswith("srgb") and not image.is_float:
        rgb = srgb_decode(np.clip(rgb, 0.0, 1.0))
    w = alpha if alpha.sum() > 1e-6 else np.ones(len(px))
    mean = (rgb * w[:, None]).sum(axis=0) / w.sum()
    return (*(round(float(v), 5) for v in mean), round(float(alpha.mean()), 5))


def _material_trees(scene):
    """The node trees of the scene's materials and every shader node group (a group may hold textures)."""
    seen = {}
    for mat in scene_materials(scene):
        if mat.node_tree is not None:
            seen[mat.node_tree.as_pointer()] = mat.node_tree
    for g in bpy.data.node_groups:
        if g.bl_idname == "ShaderNodeTree":
            seen[g.as_pointer()] = g
    return list(seen.values())


def make_untextured(scene) -> dict:
    """Replace every image texture of the scene's materials by a constant: each link from an Image Texture node's
    Color output becomes its image's mean (``image_mean``; a missing image: neutral grey, as the importers render
    it), a normal map fed by a texture becomes flat (the Normal Map node is left unlinked), and alpha links stay
    (a cut-out is shape, not texture). Roughness, metallic and every other unlinked value are kept. Returns the
    manifest's ``material_mode`` record: the mode, how many texture links were replaced and each image's mean."""
    from ..colour_spaces import BT709_LUMA
    from .importers import FLAT_NORMAL, NEUTRAL_ALBEDO, NEUTRAL_DATA, _set_default
    means: dict[str, list | None] = {}
    replaced = 0
    for tree in _material_trees(scene):
        for node in list(tree.nodes):
            if node.type != "TEX_IMAGE":
                continue
            image = node.image
            key = image.name if image is not None else "(none)"
            if key not in means:
                m = image_mean(image)
                means[key] = list(m) if m is not None else None
            mean = means[key]
            data = image is not None and _is_data(image)
            for link in [ln for out in node.outputs if out.name != "Alpha" for ln in out.links]:
                to_node, sock = link.to_node, link.to_socket
                if to_node.type == "NORMAL_MAP":
                    value = FLAT_NORMAL
                elif mean is None:
                    v = NEUTRAL_DATA if data else NEUTRAL_ALBEDO
                    value = (v, v, v, 1.0)
                else:
                    value = (*mean[:3], 1.0)
                tree.links.remove(link)
                if sock.type == "VALUE":  # a texture's colour into a number (a bump height, a factor): its luminance
                    value = float(sum(w * c for w, c in zip(BT709_LUMA, value)))
                _set_default(sock, value)
                replaced += 1
    return {"mode": "untextured", "links_replaced": replaced, "image_means": dict(sorted(means.items()))}
