"""Build the Mars-analogue world in Blender (``bpy``): heightfield mesh, rocks (merged into
one mesh, or Blender instances of the prototypes), matte regolith material with a tile
repeated at several scales, butterscotch sky and a low sun casting shadows. All randomness
comes from the numpy modules (seeded), so the same scenario builds the same scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy
import mathutils
import numpy as np

from simulation.terrain.appearance import (
    ripple_angle,
    ripple_mask,
    ripple_uv,
    rock_base_color,
    rock_projection,
    rotated_tile,
    terrain_base_color,
    tile_in_world,
    tile_uv,
)
from simulation.terrain.model import TerrainModel, make_terrain_model
from simulation.terrain.textures import (
    FINEST_CYCLES,
    RIPPLE_FINEST_CYCLES,
    RIPPLES_PER_TILE,
    make_ripple_texture,
    make_surface_texture,
)


@dataclass
class World:
    """The numpy terrain model of the built world and the direction towards the sun."""

    model: TerrainModel
    sun_direction: np.ndarray


def _mesh(name: str, verts: np.ndarray, tris: np.ndarray, smooth: bool):
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(verts))
    mesh.vertices.foreach_set("co", np.ascontiguousarray(verts, dtype=np.float32).ravel())
    mesh.loops.add(tris.size)
    mesh.loops.foreach_set("vertex_index", np.ascontiguousarray(tris, dtype=np.int32).ravel())
    mesh.polygons.add(len(tris))
    mesh.polygons.foreach_set("loop_start", np.arange(0, tris.size, 3, dtype=np.int32))
    mesh.update(calc_edges=True)
    if smooth:
        mesh.shade_smooth()
    else:
        mesh.shade_flat()
    return mesh


SLOPE_RANGE = 4.0  #: tile slopes (unit RMS) are stored in 8 bits as 0.5 + slope / (2 * range)


def _tile_image(name: str, data: np.ndarray):
    """8-bit Blender image of a tile whose slopes are already in world x, y (8-bit images
    keep the texture cache small: a float image renders ~30 % slower)."""
    data = data.copy()
    size = data.shape[0]
    data[..., :2] = np.clip(0.5 + data[..., :2] / (2.0 * SLOPE_RANGE), 0.0, 1.0)
    img = bpy.data.images.new(name, size, size, alpha=True, float_buffer=False)
    img.colorspace_settings.name = "Non-Color"
    img.alpha_mode = "CHANNEL_PACKED"
    # Blender stores rows bottom-up: array row r is v = (r + 0.5) / size, as assumed.
    img.pixels.foreach_set(np.ascontiguousarray(data, dtype=np.float32).ravel())
    img.pack()
    return img


@dataclass(frozen=True)
class _Layer:
    """One texture layer of the material: its image, the vertex attribute holding its tile
    coordinates, its finest wavelength (m), an optional weight attribute and a contrast."""

    image: object
    uv: str
    finest_wavelength: float
    mask: str | None = None
    strength: float = 1.0


def _layers(cfg, seed: int) -> list[_Layer]:
    """The regolith tile at every ``texture_scales`` size (slopes pre-rotated per layer),
    plus the aeolian-ripple tile when ripples are on."""
    tex = make_surface_texture(seed)
    layers = [_Layer(_tile_image(f"regolith_tile_{k}", rotated_tile(tex, k)), f"uv{k}",
                     scale / FINEST_CYCLES) for k, scale in enumerate(cfg.texture_scales)]
    if _has_ripples(cfg):
        tile = tile_in_world(make_ripple_texture(seed), ripple_angle(cfg.ripple_azimuth))
        layers.append(_Layer(_tile_image("ripple_tile", tile), "uvr",
                             cfg.ripple_wavelength * RIPPLES_PER_TILE / RIPPLE_FINEST_CYCLES,
                             mask="ripple", strength=cfg.ripple_strength))
    return layers


def _has_ripples(cfg) -> bool:
    return cfg.ripple_coverage > 0 and cfg.ripple_strength > 0


def _set_attributes(mesh, uvs: list[np.ndarray], base: np.ndarray,
                    ripples: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Per-vertex tile coordinates ``uv<k>`` (FLOAT2), linear base colour ``base`` and,
    with ``ripples`` = (coordinates, weight), the ripple layer's ``uvr`` and ``ripple``."""
    for k, uv in enumerate(uvs):
        attr = mesh.attributes.new(f"uv{k}", "FLOAT2", "POINT")
        attr.data.foreach_set("vector", np.ascontiguousarray(uv, dtype=np.float32).ravel())
    if ripples is not None:
        attr = mesh.attributes.new("uvr", "FLOAT2", "POINT")
        attr.data.foreach_set("vector", np.ascontiguousarray(ripples[0], np.float32).ravel())
        attr = mesh.attributes.new("ripple", "FLOAT", "POINT")
        attr.data.foreach_set("value", np.ascontiguousarray(ripples[1], np.float32).ravel())
    rgba = np.ones((len(base), 4), dtype=np.float32)
    rgba[:, :3] = base
    attr = mesh.attributes.new("base", "FLOAT_COLOR", "POINT")
    attr.data.foreach_set("color", rgba.ravel())


def _socket(sockets, identifier: str):
    """Socket by identifier (names repeat on multi-type nodes such as Mix)."""
    for sock in sockets:
        if sock.identifier == identifier:
            return sock
    raise KeyError(identifier)


class _Nodes:
    """Tiny helper to wire shader nodes."""

    def __init__(self, material):
        if material.node_tree is None:  # Blender < 5 (in 5.x materials always use nodes)
            material.use_nodes = True
        self.tree = material.node_tree
        self.tree.nodes.clear()

    def new(self, kind: str, **props):
        node = self.tree.nodes.new(kind)
        for key, value in props.items():
            setattr(node, key, value)
        return node

    def link(self, out, inp):
        self.tree.links.new(out, inp)


def _surface_material(cfg, layers: list[_Layer], sky_radiance, focal_px: float) -> object:
    """The one material of terrain and rocks (both carry the same vertex attributes).

    Tile layer k (tile size s_k) holds no detail finer than s_k / FINEST_CYCLES (the ripple
    layer: its own finest wavelength; it is also weighted by the per-vertex ripple mask and
    its deviation from the mean scaled by ``ripple_strength``); it is faded
    to its mean (what a pixel integrating the texture sees) as that wavelength shrinks from 2
    to 1 pixel footprints (footprint along the view = camera distance / (``focal_px`` x
    cos(incidence))), like an anisotropic mip-map: without
    this, sub-pixel texture renders as sampling noise that changes from frame to frame.
    albedo = base colour x (1 + contrast x (mean layer albedo - 0.5) x 2); shading normal =
    normalize(N - 0.3 bump x summed layer slopes / sqrt(layers)); Lambertian sun light plus a
    sky term albedo x sky radiance x (1 + n_z) / 2 (uniform, unoccluded sky hemisphere) as
    non-sampled emission: noise-free and ray-free. Apart from the mip-map fade (which follows
    the camera distance smoothly, as a real pixel's footprint does) the shading depends on the
    surface point only. The graph is small: Cycles' shader VM cost grows with node count.
    """
    mat = bpy.data.materials.new("regolith")
    mat.cycles.emission_sampling = "NONE"  # the sky term must not turn the ground into a light
    n = _Nodes(mat)
    # footprint along the view direction = distance / (focal * cos(incidence)): q = cos / d
    geom = n.new("ShaderNodeNewGeometry")
    cos_i = n.new("ShaderNodeVectorMath", operation="DOT_PRODUCT")
    n.link(geom.outputs["Incoming"], cos_i.inputs[0])
    n.link(geom.outputs["Normal"], cos_i.inputs[1])
    inv_dist = n.new("ShaderNodeMath", operation="DIVIDE")
    n.link(cos_i.outputs["Value"], inv_dist.inputs[0])
    n.link(n.new("ShaderNodeLightPath").outputs["Ray Length"], inv_dist.inputs[1])
    acc = None
    for layer in layers:
        uv = n.new("ShaderNodeAttribute", attribute_type="GEOMETRY", attribute_name=layer.uv)
        tex = n.new("ShaderNodeTexImage", image=layer.image, interpolation="Linear",
                    extension="REPEAT", projection="FLAT")
        n.link(uv.outputs["Vector"], tex.inputs["Vector"])
        # w = clamp(finest wavelength in footprints - 1) = clamp(a cos / distance - 1)
        a = layer.finest_wavelength * focal_px
        w = n.new("ShaderNodeMath", operation="MULTIPLY_ADD", use_clamp=True)
        n.link(inv_dist.outputs[0], w.inputs[0])
        w.inputs[1].default_value = a
        w.inputs[2].default_value = -1.0
        weight = w.outputs[0]
        if layer.mask is not None:
            mask = n.new("ShaderNodeAttribute", attribute_type="GEOMETRY",
                         attribute_name=layer.mask)
            masked = n.new("ShaderNodeMath", operation="MULTIPLY")
            n.link(weight, masked.inputs[0])
            n.link(mask.outputs["Fac"], masked.inputs[1])
            weight = masked.outputs[0]
        fade = n.new("ShaderNodeMix", data_type="VECTOR", factor_mode="UNIFORM")
        n.link(weight, _socket(fade.inputs, "Factor_Float"))
        # (no slope, no slope, mean albedo) = what a pixel integrating the tile sees
        _socket(fade.inputs, "A_Vector").default_value = (0.5, 0.5, 0.5)
        n.link(tex.outputs["Color"], _socket(fade.inputs, "B_Vector"))
        out_vec = _socket(fade.outputs, "Result_Vector")
        if layer.strength != 1.0:  # mean + strength (value - mean)
            st = n.new("ShaderNodeVectorMath", operation="MULTIPLY_ADD")
            n.link(out_vec, st.inputs[0])
            st.inputs[1].default_value = (layer.strength,) * 3
            st.inputs[2].default_value = (0.5 * (1.0 - layer.strength),) * 3
            out_vec = st.outputs["Vector"]
        if acc is None:
            acc = out_vec  # (x-slope, y-slope, albedo)
        else:
            add = n.new("ShaderNodeVectorMath", operation="ADD")
            n.link(acc, add.inputs[0])
            n.link(out_vec, add.inputs[1])
            acc = add.outputs["Vector"]
    L = len(layers)
    # slope sum = 2 R (acc - L / 2) with R = SLOPE_RANGE; N' = N + k (slope sum) =
    # acc * 2 R k + (N - L R k)
    k_tilt = -0.3 * cfg.bump_strength / np.sqrt(L)
    g = 2.0 * SLOPE_RANGE * k_tilt
    shifted = n.new("ShaderNodeVectorMath", operation="ADD")
    n.link(geom.outputs["Normal"], shifted.inputs[0])
    shifted.inputs[1].default_value = (-L * SLOPE_RANGE * k_tilt, -L * SLOPE_RANGE * k_tilt, 0.0)
    tilt = n.new("ShaderNodeVectorMath", operation="MULTIPLY_ADD")
    n.link(acc, tilt.inputs[0])
    tilt.inputs[1].default_value = (g, g, 0.0)
    n.link(shifted.outputs["Vector"], tilt.inputs[2])
    normal = n.new("ShaderNodeVectorMath", operation="NORMALIZE")
    n.link(tilt.outputs["Vector"], normal.inputs[0])
    # gain = 1 + 2 c (sum / L - 0.5) = (2c / L) * sum_z + (1 - c), with sum_z = acc . e_z
    c = cfg.texture_contrast
    gain = n.new("ShaderNodeVectorMath", operation="DOT_PRODUCT")
    n.link(acc, gain.inputs[0])
    gain.inputs[1].default_value = (0.0, 0.0, 2.0 * c / L)
    base = n.new("ShaderNodeAttribute", attribute_type="GEOMETRY", attribute_name="base")
    albedo = n.new("ShaderNodeVectorMath", operation="MULTIPLY_ADD")
    n.link(base.outputs["Vector"], albedo.inputs[0])
    n.link(gain.outputs["Value"], albedo.inputs[1])
    bias = n.new("ShaderNodeVectorMath", operation="SCALE")
    n.link(base.outputs["Vector"], bias.inputs[0])
    bias.inputs["Scale"].default_value = 1.0 - c
    n.link(bias.outputs["Vector"], albedo.inputs[2])
    bsdf = n.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Roughness"].default_value = 0.0
    n.link(albedo.outputs["Vector"], bsdf.inputs["Color"])
    n.link(normal.outputs["Vector"], bsdf.inputs["Normal"])
    # sky term: albedo * (sky/2 * n_z + sky/2)
    nz = n.new("ShaderNodeVectorMath", operation="DOT_PRODUCT")
    nz.inputs[1].default_value = (0.0, 0.0, 1.0)
    n.link(normal.outputs["Vector"], nz.inputs[0])
    half = tuple(0.5 * np.asarray(sky_radiance, dtype=np.float64))
    amb = n.new("ShaderNodeVectorMath", operation="MULTIPLY_ADD")
    n.link(nz.outputs["Value"], amb.inputs[0])
    amb.inputs[1].default_value = half
    amb.inputs[2].default_value = half
    sky = n.new("ShaderNodeVectorMath", operation="MULTIPLY")
    n.link(albedo.outputs["Vector"], sky.inputs[0])
    n.link(amb.outputs["Vector"], sky.inputs[1])
    emit = n.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 1.0
    n.link(sky.outputs["Vector"], emit.inputs["Color"])
    both = n.new("ShaderNodeAddShader")
    n.link(bsdf.outputs["BSDF"], both.inputs[0])
    n.link(emit.outputs["Emission"], both.inputs[1])
    out = n.new("ShaderNodeOutputMaterial", target="ALL")
    n.link(both.outputs["Shader"], out.inputs["Surface"])
    return mat


def _sky_and_sun(scene, light_cfg) -> np.ndarray:
    world = bpy.data.worlds.new("mars_sky")
    scene.world = world
    if world.node_tree is None:  # Blender < 5
        world.use_nodes = True
    # The sky is seen by camera rays only; its light on the ground is the materials' emission
    # term (noise-free), so the world is neither sampled as a light nor hit by bounces.
    world.cycles.sampling_method = "NONE"
    nodes, links = world.node_tree.nodes, world.node_tree.links
    nodes.clear()
    bg = nodes.new("ShaderNodeBackground")
    bg.inputs["Color"].default_value = (*light_cfg.sky_color, 1.0)
    path = nodes.new("ShaderNodeLightPath")
    scale = nodes.new("ShaderNodeMath")
    scale.operation = "MULTIPLY"
    scale.inputs[1].default_value = light_cfg.sky_strength
    links.new(path.outputs["Is Camera Ray"], scale.inputs[0])
    links.new(scale.outputs[0], bg.inputs["Strength"])
    out = nodes.new("ShaderNodeOutputWorld")
    links.new(bg.outputs["Background"], out.inputs["Surface"])
    el, az = np.deg2rad(light_cfg.sun_elevation), np.deg2rad(light_cfg.sun_azimuth)
    to_sun = np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
    sun = bpy.data.lights.new("sun", type="SUN")
    sun.energy = light_cfg.sun_strength
    sun.angle = np.deg2rad(light_cfg.sun_angle)
    sun_obj = bpy.data.objects.new("sun", sun)
    scene.collection.objects.link(sun_obj)
    # A sun lamp shines along its local -z axis: point -z away from to_sun.
    z = to_sun
    x = np.cross([0.0, 0.0, 1.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = x, y, z
    sun_obj.matrix_world = mathutils.Matrix(m.tolist())
    return to_sun


def merged_rocks(protos, rocks) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All rock placements as one triangle soup: each prototype scaled, turned by its yaw
    and moved to its location (the transforms Blender instances would apply). Returns
    vertices, triangles and the rock index of every vertex."""
    verts, tris, owner, offset = [], [], [], 0
    for i in range(len(rocks)):
        v, f = protos[rocks.proto[i]]
        c, s = np.cos(rocks.yaw[i]), np.sin(rocks.yaw[i])
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        verts.append((v * rocks.scale[i]) @ R.T + rocks.location[i])
        tris.append(f + offset)
        owner.append(np.full(len(v), i))
        offset += len(v)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(owner)


def _no_ripples(cfg, xy: np.ndarray):
    """Ripple attributes of rock vertices: coordinates (unused) and weight 0."""
    if not _has_ripples(cfg):
        return None
    return np.zeros((len(xy), 2), np.float32), np.zeros(len(xy), np.float32)


def _rocks(coll, cfg, protos, rocks, material, seed: int) -> None:
    rng = np.random.default_rng([seed, 0x2C0])
    colors = rock_base_color(cfg, rng, max(len(rocks), 1))
    L = len(cfg.texture_scales)
    if not cfg.rock_instances:
        verts, tris, owner = merged_rocks(protos, rocks)
        if not len(verts):
            return
        mesh = _mesh("rocks", verts, tris, smooth=False)
        xy = rock_projection(verts)
        _set_attributes(mesh, [tile_uv(xy, s, k) for k, s in enumerate(cfg.texture_scales)],
                        colors[owner], _no_ripples(cfg, xy))
        mesh.materials.append(material)
        coll.objects.link(bpy.data.objects.new("rocks", mesh))
        return
    # One object per rock sharing its prototype's mesh (Blender / Cycles instancing); the
    # texture follows the prototype's local frame, one colour per prototype.
    meshes = []
    for k, (v, f) in enumerate(protos):
        mesh = _mesh(f"rock_proto_{k}", v, f, smooth=False)
        xy = rock_projection(v)
        _set_attributes(mesh, [tile_uv(xy, 0.5 * s, j) for j, s in
                               enumerate(cfg.texture_scales[:L])],
                        np.repeat(colors[k % len(colors)][None], len(v), axis=0),
                        _no_ripples(cfg, xy))
        mesh.materials.append(material)
        meshes.append(mesh)
    for i in range(len(rocks)):
        ob = bpy.data.objects.new(f"rock_{i:05d}", meshes[rocks.proto[i]])
        ob.location = rocks.location[i].tolist()
        ob.rotation_euler = (0.0, 0.0, float(rocks.yaw[i]))
        ob.scale = rocks.scale[i].tolist()
        coll.objects.link(ob)


def build_world(scenario, model: TerrainModel | None = None) -> World:
    """Reset Blender and build the scenario's world (terrain, rocks, material, sky, sun).
    ``model`` (from :func:`make_terrain_model`) is reused when given."""
    cfg, seed = scenario.terrain, scenario.seed
    if model is None:
        model = make_terrain_model(cfg, seed)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    light = scenario.lighting
    sky_radiance = tuple(c * light.sky_strength for c in light.sky_color)
    material = _surface_material(cfg, _layers(cfg, seed), sky_radiance, scenario.camera.fx)
    verts, tris = model.heightfield.triangles()
    mesh = _mesh("terrain", verts, tris, smooth=True)
    xy = verts[:, :2]
    ripples = (ripple_uv(xy, cfg), ripple_mask(cfg, seed, xy)) if _has_ripples(cfg) else None
    _set_attributes(mesh, [tile_uv(xy, s, k) for k, s in enumerate(cfg.texture_scales)],
                    terrain_base_color(cfg, seed, xy), ripples)
    mesh.materials.append(material)
    scene.collection.objects.link(bpy.data.objects.new("terrain", mesh))
    rock_coll = bpy.data.collections.new("rocks")
    scene.collection.children.link(rock_coll)
    _rocks(rock_coll, cfg, model.prototypes, model.rocks, material, seed)
    sun_dir = _sky_and_sun(scene, light)
    return World(model, sun_dir)
