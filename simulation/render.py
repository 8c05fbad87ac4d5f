"""Headless Cycles rendering on the CPU with exact intrinsics and a planar depth map.

Camera: the scenario's pinhole (fx, fy, cx, cy) is set through the sensor width (fx),
pixel aspect (fy / fx) and lens shift (cx, cy), with the project's pixel convention (centre of
the top-left pixel = (0, 0)); ``kb4`` is Cycles' equidistant fisheye (r = fx * theta).
A pose ``T_w_c`` (CV convention) becomes Blender's camera matrix ``T_w_c @ diag(1, -1, -1, 1)``.

Each frame is rendered once; the compositor writes the linear colour and the depth pass as
float EXR files to a scratch folder, read back with OpenCV. Cycles' depth pass is planar z for
perspective cameras and the ray length for panoramic ones (converted here to planar z).
Cycles places the first sample of every pixel at the pixel centre, and the depth pass takes
that sample, so depth is exact at pixel centres.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")

import bpy  # noqa: E402
import mathutils  # noqa: E402
import cv2  # noqa: E402
import numpy as np  # noqa: E402

CV_TO_BLENDER = np.diag([1.0, -1.0, -1.0, 1.0])
_SENSOR_WIDTH = 36.0  # mm, arbitrary: only the ratio lens / sensor matters


@contextlib.contextmanager
def _quiet():
    """Silence Blender's C-level stdout (render progress, "Saved:" lines)."""
    import sys

    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def configure_cycles(scene, render_cfg, width: int, height: int, seed: int) -> None:
    """Deterministic CPU Cycles: fixed threads, fixed sampling seed, no animated seed."""
    scene.render.engine = "CYCLES"
    cyc = scene.cycles
    cyc.device = "CPU"
    cyc.samples = render_cfg.samples
    cyc.use_adaptive_sampling = render_cfg.adaptive_threshold > 0
    if cyc.use_adaptive_sampling:
        cyc.adaptive_threshold = render_cfg.adaptive_threshold
        cyc.adaptive_min_samples = (render_cfg.adaptive_min_samples
                                    or min(render_cfg.samples, 4))
    cyc.use_denoising = bool(render_cfg.denoise)
    if cyc.use_denoising:
        cyc.denoiser = "OPENIMAGEDENOISE"
        cyc.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        cyc.denoising_prefilter = "ACCURATE"
        cyc.denoising_use_gpu = False
    cyc.max_bounces = render_cfg.max_bounces
    cyc.diffuse_bounces = render_cfg.max_bounces
    cyc.glossy_bounces = 0
    cyc.transmission_bounces = 0
    cyc.volume_bounces = 0
    cyc.transparent_max_bounces = 0
    cyc.caustics_reflective = False
    cyc.caustics_refractive = False
    cyc.use_light_tree = False
    cyc.seed = seed
    cyc.use_animated_seed = False
    cyc.pixel_filter_type = "BLACKMAN_HARRIS"
    cyc.filter_width = 1.5
    cyc.use_auto_tile = False
    scene.render.threads_mode = "FIXED"
    scene.render.threads = render_cfg.threads
    scene.render.use_persistent_data = True
    scene.render.resolution_x = width
    scene.render.resolution_y = height
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.render.use_motion_blur = bool(render_cfg.motion_blur)
    scene.render.motion_blur_shutter = render_cfg.shutter
    scene.view_layers[0].use_pass_z = True
    _bounce_ray_visibility(scene, render_cfg.max_bounces > 0)


def _bounce_ray_visibility(scene, visible: bool) -> None:
    """Show or hide the built world's surfaces and sky to the rays after the first hit.

    With ``max_bounces = 0`` Cycles still samples the BSDF at the camera ray's hit and traces
    that ray (for multiple importance sampling of lights it might hit): it evaluated the full
    surface shader wherever it hit terrain or a rock (whose sky term is an emission), and the
    world shader wherever it escaped, for every sample, and added the hit surface's sky
    emission as a noisy one-bounce inter-reflection. Hiding surfaces and sky from those rays
    (camera and shadow rays still see everything) removes that work and that light, as
    ``max_bounces = 0`` promises; the sun still lights the surfaces through its shadow rays.
    """
    for obj in scene.objects:
        if obj.type == "MESH" and not obj.name.endswith(_TWIN):
            obj.visible_diffuse = obj.visible_glossy = visible
            obj.visible_transmission = obj.visible_volume_scatter = visible
    if scene.world is not None:
        vis = scene.world.cycles_visibility
        vis.diffuse = vis.glossy = vis.transmission = vis.scatter = visible
    _reject_hidden_rays_at_instances(scene, not visible)


_TWIN = ".bvh_twin"  #: name suffix of the hidden second users made below


def _reject_hidden_rays_at_instances(scene, on: bool) -> None:
    """Make every single-user mesh a BVH instance (``on``) or undo it.

    Cycles bakes the transform of a mesh with one user into its vertices and puts its
    triangles into the one top-level Embree BVH; a ray that none of them is visible to (the
    bounce rays hidden above) still traverses that BVH to the end, testing each triangle on
    its way and only then rejecting it by its visibility mask. A mesh with a second user
    becomes an instance, a BVH of its own under one top-level node whose mask rejects such a
    ray at once. The second user is a twin that no traced ray can see (visible to volume
    scatter rays only, which a scene without volumes never traces), a millionth of the size,
    100 km below the world. Camera and shadow rays pay one instance transform; what it saves:
    docs/simulation.md ("One instance for the whole world").
    """
    for obj in [o for o in scene.objects if o.name.endswith(_TWIN)]:
        bpy.data.objects.remove(obj)
    if not on:
        return
    for obj in list(scene.objects):
        if obj.type != "MESH" or obj.data.users != 1:
            continue
        twin = bpy.data.objects.new(obj.name + _TWIN, obj.data)
        twin.location = (0.0, 0.0, -1.0e5)
        twin.scale = (1e-6, 1e-6, 1e-6)
        twin.visible_camera = twin.visible_shadow = False
        twin.visible_diffuse = twin.visible_glossy = twin.visible_transmission = False
        twin.visible_volume_scatter = True
        scene.collection.objects.link(twin)


def make_camera(scene, cam_cfg):
    """Create the scene camera with the scenario's exact intrinsics."""
    cam = bpy.data.cameras.new("cam0")
    W, H = cam_cfg.width, cam_cfg.height
    cam.clip_start = cam_cfg.clip_start
    cam.clip_end = 1e5
    cam.sensor_fit = "HORIZONTAL"
    cam.sensor_width = _SENSOR_WIDTH
    if cam_cfg.model == "pinhole":
        cam.type = "PERSP"
        cam.lens = cam_cfg.fx * _SENSOR_WIDTH / W
        # Non-square pixels: Blender's vertical pixel is aspect_y / aspect_x horizontal
        # pixels tall, so fy = fx * aspect_x / aspect_y.
        ratio = cam_cfg.fy / cam_cfg.fx
        scene.render.pixel_aspect_x = ratio if ratio >= 1 else 1.0
        scene.render.pixel_aspect_y = 1.0 if ratio >= 1 else 1.0 / ratio
        # Shift is in units of the fitted (horizontal) sensor size = W horizontal pixels; a
        # positive shift moves the frustum right / up, i.e. the principal point left / down.
        cam.shift_x = -(cam_cfg.cx + 0.5 - W / 2) / W
        cam.shift_y = (cam_cfg.cy + 0.5 - H / 2) / (W * ratio)
    else:
        cam.type = "PANO"
        cam.panorama_type = "FISHEYE_EQUIDISTANT"
        cam.fisheye_fov = W / cam_cfg.fx
    obj = bpy.data.objects.new("cam0", cam)
    scene.collection.objects.link(obj)
    scene.camera = obj
    return obj


def _compositor(scene, scratch: Path):
    tree = bpy.data.node_groups.new("granite_comp", "CompositorNodeTree")
    scene.compositing_node_group = tree
    scene.render.use_compositing = True
    layers = tree.nodes.new("CompositorNodeRLayers")
    out = tree.nodes.new("CompositorNodeOutputFile")
    out.directory = str(scratch)
    out.file_name = "f_"
    out.format.media_type = "IMAGE"
    out.format.file_format = "OPEN_EXR"
    out.format.color_depth = "32"
    out.format.exr_codec = "NONE"
    # (a one-channel EXR names its channel "V", which OpenCV cannot read: depth goes as RGB)
    for kind, name, mode in (("RGBA", "rgb", "RGB"), ("FLOAT", "depth", "RGB")):
        item = out.file_output_items.new(kind, name)
        item.override_node_format = True  # fewer channels: less EXR to write and read
        item.format.media_type = "IMAGE"
        item.format.file_format = "OPEN_EXR"
        item.format.color_depth = "32"
        item.format.exr_codec = "NONE"
        item.format.color_mode = mode
    tree.links.new(layers.outputs["Image"], out.inputs["rgb"])
    tree.links.new(layers.outputs["Depth"], out.inputs["depth"])


def _memory_backed_dir() -> str | None:
    """/dev/shm when it is a writable directory (Linux tmpfs: the per-frame EXR files of the
    compositor never touch a disk; 5 ms per 640x480 frame less than under /tmp on this
    machine), else None (the system's temporary directory)."""
    shm = "/dev/shm"
    return shm if os.path.isdir(shm) and os.access(shm, os.W_OK | os.X_OK) else None


def set_camera_pose(cam_obj, T_w_c: np.ndarray) -> None:
    """Place the camera at the CV pose ``T_w_c``."""
    M = np.asarray(T_w_c, dtype=np.float64) @ CV_TO_BLENDER
    cam_obj.matrix_world = mathutils.Matrix(M.tolist())  # (a nested list would be read column-major)


class Renderer:
    """Renders frames of a built world (:func:`simulation.terrain.scene.build_world`).

    ``render(T_w_c, motion=None)`` returns linear RGB ``(H, W, 3)`` float32 and planar depth
    ``(H, W)`` float32 (inf where no surface). ``motion`` = poses at shutter open and close
    for motion blur (the middle pose is ``T_w_c``); the depth is then rendered a second
    time without blur at ``T_w_c`` (exact, at twice the cost).
    """

    def __init__(self, scenario):
        self.scenario = scenario
        self.scene = bpy.context.scene
        cam = scenario.camera
        self.width, self.height = cam.width, cam.height
        configure_cycles(self.scene, scenario.render, cam.width, cam.height, scenario.seed)
        self.camera = make_camera(self.scene, cam)
        self.scratch = Path(tempfile.mkdtemp(prefix="granite-sim-", dir=_memory_backed_dir()))
        _compositor(self.scene, self.scratch)
        self._planar = None
        if cam.model == "kb4":
            self._planar = _fisheye_bearing_z(cam)

    def reconfigure(self, render_cfg) -> None:
        """Apply other Cycles settings (a :class:`~simulation.scenario.RenderConfig`, e.g. more
        samples) to the following renders of this renderer.

        Cycles keeps its session between renders (persistent data) and re-reads its settings
        only when the scene is tagged as changed: assigning ``scene.cycles.samples`` alone
        does not tag it (Blender 5.0.1), and the next renders keep the first render's sample
        count (bit-identical images). Assignments to ``scene.render`` do tag it, as does the
        explicit tag here; Cycles then rebuilds the scene once (a few seconds, like the first
        render) and the renders equal those of a fresh renderer with these settings.
        """
        configure_cycles(self.scene, render_cfg, self.width, self.height, self.scenario.seed)
        self.scene.update_tag()

    def close(self) -> None:
        shutil.rmtree(self.scratch, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _keyframe_motion(self, poses: list[np.ndarray]) -> None:
        """Keyframe the camera at shutter open / centre / close around frame 1."""
        obj, s = self.camera, self.scenario.render.shutter
        obj.animation_data_clear()
        obj.rotation_mode = "QUATERNION"
        for pose, frame in zip(poses, (1.0 - 0.5 * s, 1.0, 1.0 + 0.5 * s)):
            set_camera_pose(obj, pose)
            obj.keyframe_insert("location", frame=frame)
            obj.keyframe_insert("rotation_quaternion", frame=frame)
        for fcurve in _fcurves(obj):
            for kp in fcurve.keyframe_points:
                kp.interpolation = "LINEAR"
        self.scene.frame_set(1)

    def _render_files(self):
        for f in self.scratch.glob("*.exr"):
            f.unlink()
        with _quiet():
            bpy.ops.render.render(write_still=False)
        rgb = _read_exr(self.scratch / "f_rgb.exr")
        depth = _read_exr(self.scratch / "f_depth.exr")
        rgb = np.ascontiguousarray(rgb[..., 2::-1] if rgb.ndim == 3 else rgb, dtype=np.float32)
        if depth.ndim == 3:
            depth = depth[..., 0]
        return rgb, depth.astype(np.float32)

    def render(self, T_w_c: np.ndarray, motion: tuple[np.ndarray, np.ndarray] | None = None):
        scene = self.scene
        if motion is not None and self.scenario.render.motion_blur:
            self._keyframe_motion([motion[0], T_w_c, motion[1]])
            rgb, _ = self._render_files()
            # The depth pass of a blurred frame comes from a random time in the shutter
            # interval: render the depth again, sharp, at the mid-exposure pose.
            self.camera.animation_data_clear()
            scene.render.use_motion_blur = False
            set_camera_pose(self.camera, T_w_c)
            try:
                _, depth = self._render_files()
            finally:
                scene.render.use_motion_blur = True
        else:
            if self.camera.animation_data is not None:
                self.camera.animation_data_clear()
            set_camera_pose(self.camera, T_w_c)
            rgb, depth = self._render_files()
        depth[~np.isfinite(depth) | (depth <= 0) | (depth >= 1e9)] = np.inf
        if self._planar is not None:
            depth = depth * self._planar
            depth[~(depth > 0)] = np.inf
        return rgb, depth


def _fcurves(obj):
    anim = obj.animation_data
    action = anim.action if anim else None
    if action is None:
        return []
    if hasattr(action, "fcurves"):
        return list(action.fcurves)
    # Blender >= 4.4 layered actions
    curves = []
    for layer in action.layers:
        for strip in layer.strips:
            for bag in strip.channelbags:
                curves.extend(bag.fcurves)
    return curves


def _fisheye_bearing_z(cam_cfg) -> np.ndarray:
    """cos(theta) per pixel of the equidistant fisheye (r = fx * theta)."""
    u, v = np.meshgrid(np.arange(cam_cfg.width, dtype=np.float64),
                       np.arange(cam_cfg.height, dtype=np.float64))
    theta = np.hypot(u - cam_cfg.cx, v - cam_cfg.cy) / cam_cfg.fx
    return np.cos(theta).astype(np.float32)


def _read_exr(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise RuntimeError(f"Blender did not write {path}")
    return img


def software_versions() -> dict[str, str]:
    import platform

    return {"blender": bpy.app.version_string, "python": platform.python_version(),
            "numpy": np.__version__, "opencv": cv2.__version__}
