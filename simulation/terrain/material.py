"""The regolith material of terrain and rocks (Cycles shader nodes, ``bpy``).

One tile texture repeated at several scales (``terrain.texture_scales``) plus the aeolian-ripple
tile, each faded to its mean where its finest wavelength shrinks below two pixel footprints
(an anisotropic mip-map), a Lambertian sun term and an analytic sky term (emission). Layers
faded out entirely are not evaluated: the graph branches on which layers a shading point
needs, with the same arithmetic in every branch as in one graph that evaluates them all
(:func:`surface_material`).
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy
import numpy as np

from simulation.terrain.appearance import ripple_angle, rotated_tile, tile_in_world
from simulation.terrain.textures import (
    FINEST_CYCLES,
    RIPPLE_FINEST_CYCLES,
    RIPPLES_PER_TILE,
    make_ripple_texture,
    make_surface_texture,
)

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
    coordinates, its finest wavelength (m) and an optional weight attribute (the ripples':
    mask x ``ripple_strength``, so it may exceed 1)."""

    image: object
    uv: str
    finest_wavelength: float
    mask: str | None = None


def has_ripples(cfg) -> bool:
    """Whether the terrain config asks for the aeolian-ripple layer."""
    return cfg.ripple_coverage > 0 and cfg.ripple_strength > 0


def _layers(cfg, seed: int) -> list[_Layer]:
    """The regolith tile at every ``texture_scales`` size (slopes pre-rotated per layer),
    plus the aeolian-ripple tile when ripples are on."""
    tex = make_surface_texture(seed)
    layers = [_Layer(_tile_image(f"regolith_tile_{k}", rotated_tile(tex, k)), f"uv{k}",
                     scale / FINEST_CYCLES) for k, scale in enumerate(cfg.texture_scales)]
    if has_ripples(cfg):
        tile = tile_in_world(make_ripple_texture(seed), ripple_angle(cfg.ripple_azimuth))
        layers.append(_Layer(_tile_image("ripple_tile", tile), "uvr",
                             cfg.ripple_wavelength * RIPPLES_PER_TILE / RIPPLE_FINEST_CYCLES,
                             mask="ripple"))
    return layers


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

    def vector_math(self, operation: str, a, b=None, c=None):
        """A Vector Math node on ``a`` (a socket), ``b`` and ``c`` (sockets or constants);
        returns its vector output."""
        node = self.new("ShaderNodeVectorMath", operation=operation)
        for sock, value in zip(node.inputs, (a, b, c)):
            if value is None:
                continue
            if isinstance(value, bpy.types.NodeSocket):
                self.link(value, sock)
            else:
                sock.default_value = value
        return node.outputs["Vector"]


#: what a faded layer contributes (x-slope, y-slope, albedo): exactly its mean, 0.5
_MEAN = np.full(3, 0.5, np.float32)


def _sum(vectors: list[np.ndarray]) -> tuple:
    """The float32 sum of constant vectors added left to right, as the shader adds them."""
    total = np.asarray(vectors[0], np.float32)
    for v in vectors[1:]:
        total = (total + np.asarray(v, np.float32)).astype(np.float32)
    return tuple(float(x) for x in total)


class _LayerNodes:
    """The nodes of one layer that decide whether it is needed: tile coordinates, fade
    weight w = clamp(a q - 1) (q = cos(incidence) / distance, a = finest wavelength x focal
    length in pixels; times the mask attribute if any) and the branch condition w > 0.
    Cycles evaluates them where a shading point reaches this layer's branch (the coordinates
    of a masked layer, which its per-branch texture copies share, before every branch)."""

    def __init__(self, n: _Nodes, layer: _Layer, q, focal_px: float):
        self.layer = layer
        self.a = layer.finest_wavelength * focal_px
        self.uv = n.new("ShaderNodeAttribute", attribute_type="GEOMETRY",
                        attribute_name=layer.uv).outputs["Vector"]
        w = n.new("ShaderNodeMath", operation="MULTIPLY_ADD", use_clamp=True)
        n.link(q, w.inputs[0])
        w.inputs[1].default_value = self.a
        w.inputs[2].default_value = -1.0
        self.weight = w.outputs[0]
        if layer.mask is not None:
            mask = n.new("ShaderNodeAttribute", attribute_type="GEOMETRY",
                         attribute_name=layer.mask)
            masked = n.new("ShaderNodeMath", operation="MULTIPLY")
            n.link(self.weight, masked.inputs[0])
            n.link(mask.outputs["Fac"], masked.inputs[1])
            self.weight = masked.outputs[0]
        on = n.new("ShaderNodeMath", operation="GREATER_THAN")
        n.link(self.weight, on.inputs[0])
        on.inputs[1].default_value = 0.0
        self.on = on.outputs[0]
        self._faded_texture = None
        self._copies = 0

    def faded_texture(self, n: _Nodes, shared: bool):
        """(x-slope, y-slope, albedo) of the layer after the fade: mean + w (texel - mean),
        w unclamped (a weight attribute may exceed 1). ``shared``: one node chain for every
        branch that uses it; otherwise a new one per call (Cycles merges identical nodes,
        and a node two branches share is evaluated before they split, i.e. always)."""
        if shared and self._faded_texture is not None:
            return self._faded_texture
        tex = n.new("ShaderNodeTexImage", image=self.layer.image, interpolation="Linear",
                    extension="REPEAT", projection="FLAT")
        if not shared:  # unused with flat projection: only keeps the copies apart
            tex.projection_blend = 0.01 * self._copies
            self._copies += 1
        n.link(self.uv, tex.inputs["Vector"])
        fade = n.new("ShaderNodeMix", data_type="VECTOR", factor_mode="UNIFORM",
                     clamp_factor=False)
        n.link(self.weight, _socket(fade.inputs, "Factor_Float"))
        _socket(fade.inputs, "A_Vector").default_value = tuple(float(x) for x in _MEAN)
        n.link(tex.outputs["Color"], _socket(fade.inputs, "B_Vector"))
        out = _socket(fade.outputs, "Result_Vector")
        if shared:
            self._faded_texture = out
        return out


def _shade_offset(n_layers: int, cfg) -> np.ndarray:
    """The constant K the layer sum starts from, so that the shading needs fewer nodes:
    acc = K + sum of layers, K = (-L / 2, -L / 2, L (1 - c) / (2 c)) for L layers and texture
    contrast c (each layer is in [0, 1] around its mean 0.5). Then acc_xy is the summed slope
    / (2 R) (R = SLOPE_RANGE), and (2 c / L) acc_z = 1 + c (2 x mean layer albedo - 1) is the
    albedo gain (:func:`_shade`)."""
    L, c = n_layers, cfg.texture_contrast
    return np.array([-0.5 * L, -0.5 * L, 0.5 * L * (1.0 - c) / c if c > 0 else 0.0],
                    np.float32)


def _shade(n: _Nodes, acc, n_layers: int, cfg, sky_radiance, normal_in):
    """Closure of a shading point from ``acc`` = K + the summed layers (x-slope, y-slope,
    albedo; :func:`_shade_offset`): Lambertian BSDF plus sky emission.

    shading normal = normalize(N + k (summed slopes)) with k = -0.3 bump / sqrt(L), i.e.
    N + acc (2 R k, 2 R k, 0); albedo = base x gain, gain = 1 + c (2 mean layer albedo - 1) =
    acc . (0, 0, 2 c / L); sky emission = albedo x sky radiance x (1 + n_z) / 2."""
    L = n_layers
    g = 2.0 * SLOPE_RANGE * (-0.3 * cfg.bump_strength / np.sqrt(L))
    tilt = n.vector_math("MULTIPLY_ADD", acc, (g, g, 0.0), normal_in)
    normal = n.vector_math("NORMALIZE", tilt)
    c = cfg.texture_contrast
    base = n.new("ShaderNodeAttribute", attribute_type="GEOMETRY",
                 attribute_name="base").outputs["Vector"]
    albedo = base
    if c > 0:
        gain = n.new("ShaderNodeVectorMath", operation="DOT_PRODUCT")
        n.link(acc, gain.inputs[0])
        gain.inputs[1].default_value = (0.0, 0.0, 2.0 * c / L)
        albedo = n.vector_math("SCALE", base)
        n.link(gain.outputs["Value"], albedo.node.inputs["Scale"])
    bsdf = n.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Roughness"].default_value = 0.0
    n.link(albedo, bsdf.inputs["Color"])
    n.link(normal, bsdf.inputs["Normal"])
    # sky term: (albedo x sky / 2) x (1 + n_z), the second factor as the emission's strength
    nz = n.new("ShaderNodeSeparateXYZ")
    n.link(normal, nz.inputs[0])
    one_plus = n.new("ShaderNodeMath", operation="ADD")
    n.link(nz.outputs["Z"], one_plus.inputs[0])
    one_plus.inputs[1].default_value = 1.0
    half = tuple(0.5 * np.asarray(sky_radiance, dtype=np.float64))
    emit = n.new("ShaderNodeEmission")
    n.link(n.vector_math("MULTIPLY", albedo, half), emit.inputs["Color"])
    n.link(one_plus.outputs[0], emit.inputs["Strength"])
    both = n.new("ShaderNodeAddShader")
    n.link(bsdf.outputs["BSDF"], both.inputs[0])
    n.link(emit.outputs["Emission"], both.inputs[1])
    return both.outputs["Shader"]


def surface_material(cfg, seed: int, sky_radiance, focal_px: float,
                     branching: bool = True) -> object:
    """The one material of terrain and rocks (both carry the same vertex attributes).

    Tile layer k (tile size s_k) holds no detail finer than s_k / FINEST_CYCLES (the ripple
    layer: its own finest wavelength; its weight is multiplied by the per-vertex ripple mask x
    ``ripple_strength``, which scales its deviation from the mean); it is faded
    to its mean (what a pixel integrating the texture sees) as that wavelength shrinks from 2
    to 1 pixel footprints (footprint along the view = camera distance / (``focal_px`` x
    cos(incidence))), like an anisotropic mip-map: without
    this, sub-pixel texture renders as sampling noise that changes from frame to frame.
    albedo = base colour x (1 + contrast x (mean layer albedo - 0.5) x 2); shading normal =
    normalize(N - 0.3 bump x summed layer slopes / sqrt(layers)); Lambertian sun light plus a
    sky term albedo x sky radiance x (1 + n_z) / 2 (uniform, unoccluded sky hemisphere) as
    non-sampled emission: noise-free and ray-free. Apart from the mip-map fade (which follows
    the camera distance smoothly, as a real pixel's footprint does) the shading depends on the
    surface point only.

    Cycles' shader VM runs every node of a graph, so a layer faded out (w = 0: its texture
    adds exactly the mean) would still cost its texture lookup. The graph therefore branches
    with Mix Shader nodes whose factor is 0 or 1 (Cycles skips the nodes only one side
    needs): on the unmasked layers from coarse to fine (a finer layer is on only where every
    coarser one is, since w grows with the wavelength), then on each masked layer (ripples,
    absent from rocks and most of the ground). Each branch sums the layers in the same order
    as one all-layer graph would, an off layer as its exact faded value, so the image is the
    same float for float as with ``branching=False`` (that one graph;
    ``tests/test_sim_render.py``); what it saves: docs/simulation.md.
    """
    layers = _layers(cfg, seed)
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
    nodes = [_LayerNodes(n, layer, inv_dist.outputs[0], focal_px) for layer in layers]

    offset = _shade_offset(len(nodes), cfg)

    def leaf(on: frozenset):
        """The closure where exactly the layers ``on`` are not faded out."""
        acc, pending = None, [offset]  # pending: constants before the first layer that is on
        for k, ln in enumerate(nodes):
            if k in on:
                vec = ln.faded_texture(n, shared=ln.layer.mask is None)
                acc = n.vector_math("ADD", _sum(pending) if acc is None else acc, vec)
            elif acc is None:
                pending.append(_MEAN)
            else:
                acc = n.vector_math("ADD", acc, _sum([_MEAN]))
        if acc is None:  # every layer faded out: the constant sum
            acc = n.vector_math("ADD", _sum(pending), (0.0, 0.0, 0.0))
        return _shade(n, acc, len(nodes), cfg, sky_radiance, geom.outputs["Normal"])

    def split(on_sock, off_closure, on_closure):
        mix = n.new("ShaderNodeMixShader")
        n.link(on_sock, mix.inputs["Fac"])
        n.link(off_closure, mix.inputs[1])  # weight 1 - fac
        n.link(on_closure, mix.inputs[2])   # weight fac
        return mix.outputs["Shader"]

    masked = [k for k, ln in enumerate(nodes) if ln.layer.mask is not None]
    chain = sorted((k for k, ln in enumerate(nodes) if ln.layer.mask is None),
                   key=lambda k: -nodes[k].a)  # coarse to fine

    def with_masks(on: frozenset, j: int = 0):
        if j == len(masked):
            return leaf(on)
        k = masked[j]
        return split(nodes[k].on, with_masks(on, j + 1), with_masks(on | {k}, j + 1))

    def chained(i: int, on: frozenset):
        if i == len(chain):
            return with_masks(on)
        k = chain[i]  # off: every finer chain layer is off too
        return split(nodes[k].on, with_masks(on), chained(i + 1, on | {k}))

    out = n.new("ShaderNodeOutputMaterial", target="ALL")
    every_layer = frozenset(range(len(nodes)))
    n.link(chained(0, frozenset()) if branching else leaf(every_layer), out.inputs["Surface"])
    return mat
