"""Build the Mars-analogue world in Blender (``bpy``): heightfield and rocks as one mesh
("surface"; or the rocks as Blender instances of the prototypes), matte regolith material
with a tile repeated at several scales, butterscotch sky and a low sun casting shadows. All
randomness comes from the numpy modules (seeded), so the same scenario builds the same
scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy
import mathutils
import numpy as np

from simulation.terrain.appearance import (
    ripple_mask,
    ripple_uv,
    rock_base_color,
    rock_projection,
    terrain_base_color,
    tile_uv,
)
from simulation.terrain.material import has_ripples, surface_material
from simulation.terrain.model import TerrainModel, make_terrain_model


@dataclass
class World:
    """The numpy terrain model of the built world and the direction towards the sun."""

    model: TerrainModel
    sun_direction: np.ndarray


def _mesh(name: str, verts: np.ndarray, tris: np.ndarray, smooth):
    """A Blender mesh of triangles; ``smooth``: one flag for all faces or one per face
    (smooth: interpolated vertex normals; flat: the face normal)."""
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(verts))
    mesh.vertices.foreach_set("co", np.ascontiguousarray(verts, dtype=np.float32).ravel())
    mesh.loops.add(tris.size)
    mesh.loops.foreach_set("vertex_index", np.ascontiguousarray(tris, dtype=np.int32).ravel())
    mesh.polygons.add(len(tris))
    mesh.polygons.foreach_set("loop_start", np.arange(0, tris.size, 3, dtype=np.int32))
    mesh.update(calc_edges=True)
    if np.ndim(smooth):
        mesh.polygons.foreach_set("use_smooth", np.asarray(smooth, dtype=bool))
        mesh.update()
    elif smooth:
        mesh.shade_smooth()
    else:
        mesh.shade_flat()
    return mesh


@dataclass
class _Surface:
    """Triangles with the material's per-vertex attributes (see :func:`_set_attributes`)."""

    verts: np.ndarray
    tris: np.ndarray
    smooth: bool
    uvs: list[np.ndarray]
    base: np.ndarray
    ripples: tuple[np.ndarray, np.ndarray] | None


def _joined_mesh(name: str, parts: list[_Surface], material):
    """One mesh of several surfaces (each keeps its shading and attributes): Cycles then
    builds one BVH of all of them, which :mod:`simulation.render` can make a single
    instance (docs/simulation.md, "One instance for the whole world")."""
    offsets = np.cumsum([0] + [len(p.verts) for p in parts[:-1]])
    tris = np.concatenate([p.tris + o for p, o in zip(parts, offsets)])
    smooth = np.concatenate([np.full(len(p.tris), p.smooth) for p in parts])
    mesh = _mesh(name, np.concatenate([p.verts for p in parts]), tris, smooth)
    ripples = None
    if parts[0].ripples is not None:
        ripples = tuple(np.concatenate([p.ripples[i] for p in parts]) for i in range(2))
    _set_attributes(mesh, [np.concatenate([p.uvs[k] for p in parts])
                           for k in range(len(parts[0].uvs))],
                    np.concatenate([p.base for p in parts]), ripples)
    mesh.materials.append(material)
    return mesh


def _set_attributes(mesh, uvs: list[np.ndarray], base: np.ndarray,
                    ripples: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Per-vertex tile coordinates ``uv<k>`` (FLOAT2), linear base colour ``base`` and,
    with ``ripples`` = (coordinates, weight), the ripple layer's ``uvr`` and ``ripple`` (its
    fade weight's factor: the ripple mask x ``ripple_strength``)."""
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
    # Sunlight comes through shadow rays only (next-event estimation, unbiased on its own):
    # without multiple importance sampling the rays after the first hit (which find a
    # 0.35 deg disc a few times in a million) skip the sun's evaluation and MIS weights.
    sun.cycles.use_multiple_importance_sampling = False
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
    if not has_ripples(cfg):
        return None
    return np.zeros((len(xy), 2), np.float32), np.zeros(len(xy), np.float32)


def _rock_colors(cfg, rocks, seed: int) -> np.ndarray:
    """Seeded linear base colour per rock (at least one row)."""
    return rock_base_color(cfg, np.random.default_rng([seed, 0x2C0]), max(len(rocks), 1))


def _merged_rock_surface(cfg, protos, rocks, seed: int) -> _Surface | None:
    """All rocks as one flat-shaded surface, one base colour per rock (None: no rocks)."""
    verts, tris, owner = merged_rocks(protos, rocks)
    if not len(verts):
        return None
    colors = _rock_colors(cfg, rocks, seed)
    xy = rock_projection(verts)
    return _Surface(verts, tris, False,
                    [tile_uv(xy, s, k) for k, s in enumerate(cfg.texture_scales)],
                    colors[owner], _no_ripples(cfg, xy))


def _rock_instances(coll, cfg, protos, rocks, material, seed: int) -> None:
    """One object per rock sharing its prototype's mesh (Blender / Cycles instancing); the
    texture follows the prototype's local frame, one colour per prototype."""
    colors = _rock_colors(cfg, rocks, seed)
    meshes = []
    for k, (v, f) in enumerate(protos):
        mesh = _mesh(f"rock_proto_{k}", v, f, smooth=False)
        xy = rock_projection(v)
        _set_attributes(mesh, [tile_uv(xy, 0.5 * s, j) for j, s in
                               enumerate(cfg.texture_scales)],
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


def sky_radiance(light_cfg) -> tuple:
    """Linear RGB radiance of the uniform sky (``[lighting]`` sky colour x strength)."""
    return tuple(c * light_cfg.sky_strength for c in light_cfg.sky_color)


def build_world(scenario, model: TerrainModel | None = None) -> World:
    """Reset Blender and build the scenario's world (terrain, rocks, material, sky, sun).
    ``model`` (from :func:`make_terrain_model`) is reused when given."""
    cfg, seed = scenario.terrain, scenario.seed
    if model is None:
        model = make_terrain_model(cfg, seed)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    material = surface_material(cfg, seed, sky_radiance(scenario.lighting), scenario.camera.fx)
    verts, tris = model.heightfield.triangles()
    xy = verts[:, :2]
    ripples = None
    if has_ripples(cfg):  # the ripple layer's weight: mask x strength (deviation from the mean)
        ripples = (ripple_uv(xy, cfg), cfg.ripple_strength * ripple_mask(cfg, seed, xy))
    parts = [_Surface(verts, tris, True,
                      [tile_uv(xy, s, k) for k, s in enumerate(cfg.texture_scales)],
                      terrain_base_color(cfg, seed, xy), ripples)]
    if not cfg.rock_instances:  # the rocks join the terrain's mesh
        rock_surface = _merged_rock_surface(cfg, model.prototypes, model.rocks, seed)
        parts += [rock_surface] if rock_surface is not None else []
    mesh = _joined_mesh("surface", parts, material)
    scene.collection.objects.link(bpy.data.objects.new("surface", mesh))
    if cfg.rock_instances:
        rock_coll = bpy.data.collections.new("rocks")
        scene.collection.children.link(rock_coll)
        _rock_instances(rock_coll, cfg, model.prototypes, model.rocks, material, seed)
    sun_dir = _sky_and_sun(scene, scenario.lighting)
    return World(model, sun_dir)
