"""Through the real renderer (``bpy``): a known 3-D marker is rendered where the camera model
projects it (pinhole with off-centre principal point and fx != fy, and the kb4 fisheye), and
a tiny run through the CLI produces the documented layout with exact depth, resumably and
deterministically."""

from __future__ import annotations

import json
import os
import re

import cv2
import numpy as np
import pytest

from granite.io import read_calibration, read_euroc_image_list, read_tum
from simulation.flights import camera_rotation
from simulation.scenario import parse_scenario

bpy = pytest.importorskip("bpy")
pytestmark = [pytest.mark.blender, pytest.mark.slow]

SMALL_TERRAIN = {"extent": 16.0, "resolution": 0.5, "far_extent": 40.0, "crater_density": 40.0,
                 "crater_max_diameter": 6.0, "rock_density": 0.3}


def _scenario(camera: dict, **extra):
    data = {"name": "tiny", "seed": 5, "camera": camera, "terrain": dict(SMALL_TERRAIN),
            "flight": {"type": "hover", "altitude": 3.0, "duration": 0.1, "pitch": 80.0}}
    data.update(extra)
    return parse_scenario(data, "tiny.toml")


def _tiny_toml(tmp_path, duration: float):
    """A tiny rockless hover scenario file (64x48 pixels, 20 Hz) of ``duration`` seconds."""
    toml = tmp_path / "tiny.toml"
    toml.write_text(
        'name = "tiny"\nseed = 5\n[camera]\nwidth = 64\nheight = 48\nfx = 48.0\nfy = 48.0\n'
        'cx = 31.5\ncy = 23.5\n[terrain]\nextent = 16.0\nresolution = 0.5\nfar_extent = 40.0\n'
        'rock_model = "power_law"\nrock_density = 0.0\n[flight]\ntype = "hover"\n'
        f'altitude = 3.0\nduration = {duration}\npitch = 80.0\n')
    return toml


def _look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    d = target - eye
    alpha = np.arctan2(d[1], d[0])
    pitch = np.arctan2(-d[2], np.hypot(d[0], d[1]))
    T = np.eye(4)
    T[:3, :3] = camera_rotation(alpha, pitch, roll)[0]
    T[:3, 3] = eye
    return T


def _add_marker(center: np.ndarray, radius: float) -> None:
    from simulation.terrain.rocks import icosphere
    from simulation.terrain.scene import _mesh

    v, f = icosphere(3)
    mesh = _mesh("marker", v * radius + center, f, smooth=True)
    mat = bpy.data.materials.new("marker")
    mat.cycles.emission_sampling = "NONE"
    nodes = mat.node_tree.nodes
    nodes.clear()
    emit = nodes.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 50.0
    emit.inputs["Color"].default_value = (1, 1, 1, 1)
    out = nodes.new("ShaderNodeOutputMaterial")
    mat.node_tree.links.new(emit.outputs[0], out.inputs[0])
    mesh.materials.append(mat)
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("marker", mesh))


@pytest.mark.parametrize("camera, offset, radius", [
    ({"width": 160, "height": 120, "fx": 130.0, "fy": 150.0, "cx": 71.3, "cy": 66.8},
     np.array([0.9, -0.5, 0.0]), 0.05),
    ({"model": "kb4", "width": 96, "height": 96, "fx": 30.0, "fy": 30.0, "cx": 47.5, "cy": 47.5},
     np.array([2.6, 1.2, 0.0]), 0.15),
], ids=["pinhole", "kb4"])
def test_marker_projects_onto_its_pixel(camera, offset, radius):
    from simulation.plan import make_plan
    from simulation.render import Renderer
    from simulation.terrain.scene import build_world
    from simulation.writer import calibration_of

    # many samples: the centroid of a marker a few pixels wide must not carry sampling noise
    s = _scenario(camera, render={"samples": 256})
    plan = make_plan(s)
    build_world(s, plan.model)
    ground = float(plan.model.ground_height(1.0, 2.0))
    marker = np.array([1.0, 2.0, ground + 1.2])
    _add_marker(marker, radius)
    # look past the marker so that it lands off the principal point
    T_w_c = _look_at(marker + np.array([-2.0, -2.2, 1.5]), marker + offset, roll=0.1)
    with Renderer(s) as renderer:
        rgb, depth = renderer.render(T_w_c)
    cam = calibration_of(s.camera).camera()
    X_c = np.linalg.inv(T_w_c)[:3] @ np.append(marker, 1.0)
    (uv,), (ok,) = cam.project(X_c[None])
    assert ok and cam.in_image(uv[None], margin=5)[0]
    lum = rgb.mean(axis=2)
    w = np.clip(lum - 2.0, 0.0, None)  # the marker is ~50, the sunlit ground < 1
    assert w.sum() > 0, "marker not rendered"
    vs, us = np.mgrid[: lum.shape[0], : lum.shape[1]]
    centroid = np.array([np.sum(w * us), np.sum(w * vs)]) / w.sum()
    assert np.linalg.norm(centroid - uv) < 0.15, (centroid, uv)
    # the depth at the nearest pixel centre is the planar depth where its ray hits the sphere
    px = np.round(uv)
    (b,), _ = cam.unproject(px[None])
    bc = b @ X_c
    disc = bc * bc - X_c @ X_c + radius * radius
    assert disc > 0, "the pixel centre ray misses the marker"
    expected = (bc - np.sqrt(disc)) * b[2]
    assert abs(depth[int(px[1]), int(px[0])] - expected) < 2e-3


def test_tiny_render_through_the_cli(tmp_path, capsys):
    from simulation import cli
    from simulation.depth import read_depth
    from simulation.plan import make_plan
    from simulation.scenario import load_scenario

    toml = _tiny_toml(tmp_path, 0.1)
    out = tmp_path / "run"
    assert cli.main(["render", str(toml), "--out", str(out), "--quiet"]) == 0
    message = capsys.readouterr().err
    n_frames = int(message.split("rendered ")[1].split()[0])
    total, steady = (float(x) for x in
                     re.findall(r"([\d.]+) s/frame \(([\d.]+) after", message)[0])
    first = float(re.search(r"first, which took ([\d.]+) s", message).group(1))
    assert n_frames > 1  # the mean splits into the first frame and the others (rounded):
    assert total * n_frames == pytest.approx(first + steady * (n_frames - 1),
                                             abs=0.01 * n_frames + 0.05)
    plan = make_plan(load_scenario(toml))
    stamps, names = read_euroc_image_list(out / "mav0" / "cam0" / "data.csv")
    assert len(names) == 3 and list(stamps) == [0, 50_000_000, 100_000_000]
    images = [cv2.imread(str(out / "mav0" / "cam0" / "data" / n), cv2.IMREAD_UNCHANGED)
              for n in names]
    assert all(im.shape == (48, 64) and im.dtype == np.uint8 for im in images)  # monochrome
    assert all(im.std() > 3 for im in images)  # textured, not blank
    assert cli.main(["render", str(toml), "--out", str(tmp_path / "colour"), "--color",
                     "--frames", "0:1", "--quiet"]) == 0
    colour = cv2.imread(str(tmp_path / "colour" / "mav0" / "cam0" / "data" / names[0]),
                        cv2.IMREAD_UNCHANGED)
    assert colour.shape == (48, 64, 3) and colour.dtype == np.uint8
    gt = read_tum(out / "groundtruth.tum")
    np.testing.assert_allclose(gt.poses, plan.poses, atol=1e-9)
    calib = read_calibration(out / "calib.json")
    assert calib.camera_type == "pinhole" and calib.intrinsics["fx"] == 48.0
    cam = calib.camera()
    # depth is planar z: back-projected pixels lie on the terrain mesh (no rocks here)
    for i, t in enumerate(stamps):
        depth = read_depth(out / "mav0" / "depth0" / "data" / f"{t}.npy")
        assert depth.shape == (48, 64) and np.all(np.isfinite(depth))
        uv = np.stack(np.meshgrid(np.arange(64.0), np.arange(48.0)), -1).reshape(-1, 2)
        b, _ = cam.unproject(uv)
        X_c = b * (depth.reshape(-1) / b[:, 2])[:, None]
        X_w = X_c @ gt.poses[i][:3, :3].T + gt.poses[i][:3, 3]
        ground = plan.model.ground_height(X_w[:, 0], X_w[:, 1])
        assert np.max(np.abs(X_w[:, 2] - ground)) < 2e-3
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["seed"] == 5 and manifest["software"]["blender"].startswith("5.")
    assert all(f["render_seconds"] > 0 for f in manifest["frames"])
    assert (out / "scenario.toml").read_text() == toml.read_text()

    # resumable: a second run renders nothing and touches no frame
    first = out / "mav0" / "cam0" / "data" / names[1]
    mtime = first.stat().st_mtime_ns
    assert cli.main(["render", str(toml), "--out", str(out), "--quiet"]) == 0
    assert "skipped 3" in capsys.readouterr().err
    assert first.stat().st_mtime_ns == mtime
    # deterministic: a deleted frame comes back bit-identical
    original = first.read_bytes()
    os.remove(first)
    assert cli.main(["render", str(toml), "--out", str(out), "--quiet"]) == 0
    assert "rendered 1 frames, skipped 2" in capsys.readouterr().err
    assert first.read_bytes() == original


def test_ctrl_c_stops_a_render_after_the_current_frame(tmp_path):
    """SIGINT ends ``granite-sim render`` after the frame being rendered (Blender's own handler
    swallowed it: the run went on to its last frame): exit status 130, every written frame
    complete and listed, and the next run renders the rest."""
    import signal
    import subprocess
    import sys
    import time

    toml = _tiny_toml(tmp_path, 30.0)
    out = tmp_path / "run"
    command = [sys.executable, "-m", "simulation.cli", "render", str(toml), "--out", str(out),
               "--quiet"]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    images = out / "mav0" / "cam0" / "data"
    deadline = time.monotonic() + 120
    while not (images.is_dir() and any(images.glob("*.png"))) and time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "interrupted: stopping after this frame" in err
    written = sorted(p.name for p in images.glob("*.png"))
    assert 0 < len(written) < 600
    manifest = json.loads((out / "manifest.json").read_text())
    finished = [f for f in manifest["frames"] if f["render_seconds"] is not None]
    assert len(finished) == len(written)
    for name in written:
        assert (out / "mav0" / "depth0" / "data" / name.replace(".png", ".npy")).exists()
        assert cv2.imread(str(images / name), cv2.IMREAD_UNCHANGED).std() > 3
    done = subprocess.run(command + ["--frames", f"0:{len(written) + 2}"], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"rendered 2 frames, skipped {len(written)}" in done.stderr


def test_a_failing_frame_stops_the_render_and_keeps_the_frames_before(tmp_path, monkeypatch):
    """The sensor model and the files of frame i run in a worker thread while frame i + 1
    renders: an error there (here: the disk refuses frame 1) stops the run with that error,
    frame 0 stays written and listed, and frame 2 is not written."""
    from simulation.run import prepare, render_run
    from simulation.writer import RunWriter

    toml = _tiny_toml(tmp_path, 0.5)
    from simulation.scenario import load_scenario

    plan, writer, frames = prepare(load_scenario(toml), tmp_path / "run")
    original = RunWriter.write_frame

    def refuse_frame_1(self, i, *args, **kwargs):
        if i == 1:
            raise OSError("no space left on device (test)")
        return original(self, i, *args, **kwargs)

    monkeypatch.setattr(RunWriter, "write_frame", refuse_frame_1)
    with pytest.raises(OSError, match="no space left"):
        render_run(plan, writer, frames)
    images = tmp_path / "run" / "mav0" / "cam0" / "data"
    assert sorted(p.name for p in images.glob("*.png")) == ["0.png"]
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert [f["index"] for f in manifest["frames"] if f["render_seconds"]] == [0]


def test_sensor_noise_in_a_render_is_the_models(tmp_path, capsys):
    """Render the same frames with the sensor model and with --no-sensor (ideal camera): the
    variance of the difference, in the images as the VO reads them (``read_image``), grows
    linearly with the clean signal at the configured gain. The default output is the
    monochrome sensor's: colour images converted to grayscale would average the channels'
    noise (about 0.45 of the variance)."""
    from granite.io.images import read_image
    from simulation import cli
    from simulation.scenario import load_scenario
    from simulation.sensor import output_gain

    toml = tmp_path / "noise.toml"
    toml.write_text(
        'name = "noise"\nseed = 8\n[camera]\nwidth = 160\nheight = 120\nfx = 120.0\nfy = 120.0\n'
        'cx = 79.5\ncy = 59.5\n[terrain]\nextent = 16.0\n'
        'resolution = 0.5\nfar_extent = 40.0\n[sensor]\npsf_sigma = 0.0\n'
        'corner_illumination = 1.0\nprnu = 0.0\ndsnu = 0.0\nmotion_blur = false\n'
        'full_well = 3000.0\n[flight]\ntype = "hover"\naltitude = 3.0\nduration = 0.1\n'
        'pitch = 60.0\n')
    for name, extra in (("with", []), ("without", ["--no-sensor"])):
        assert cli.main(["render", str(toml), "--out", str(tmp_path / name), "--quiet",
                         *extra]) == 0
    capsys.readouterr()
    means, variances = [], []
    names = sorted((tmp_path / "with" / "mav0" / "cam0" / "data").glob("*.png"))
    assert len(names) == 3
    for p in names:
        noisy = read_image(p).astype(np.float64)
        clean = read_image(tmp_path / "without" / "mav0" / "cam0" / "data" / p.name).astype(np.float64)
        diff = noisy - clean
        for lo in range(8, 240, 16):  # clean-signal bins
            sel = (clean >= lo) & (clean < lo + 16)
            if sel.sum() > 200:
                means.append(clean[sel].mean())
                variances.append(diff[sel].var())
    assert len(means) >= 4, "too few signal levels in the render"
    slope, _ = np.polyfit(means, variances, 1)
    gain = output_gain(load_scenario(toml).sensor)
    assert slope == pytest.approx(gain, rel=0.2)
    manifest = json.loads((tmp_path / "with" / "manifest.json").read_text())
    assert manifest["sensor"]["enabled"] and manifest["sensor"]["parameters"]["full_well"] == 3000.0
    assert json.loads((tmp_path / "without" / "manifest.json").read_text())["sensor"]["enabled"] is False


def test_reconfigure_reaches_the_persistent_cycles_session():
    """Renderer.reconfigure(render_cfg) gives, in the same (persistent-data) Cycles session,
    the renders of a fresh renderer built with those settings: a bare assignment of
    ``scene.cycles.samples`` does not tag the scene and Cycles keeps the first render's
    sample count (how 4- and 64-sample renders once came out bit-identical)."""
    import dataclasses

    from simulation.plan import make_plan
    from simulation.render import Renderer
    from simulation.terrain.scene import build_world

    camera = {"width": 64, "height": 48, "fx": 48.0, "fy": 48.0, "cx": 31.5, "cy": 23.5}
    s1 = _scenario(camera, render={"samples": 1})
    s16 = dataclasses.replace(s1, render=dataclasses.replace(s1.render, samples=16))
    plan = make_plan(s1)
    T_w_c = plan.poses[0]
    build_world(s16, plan.model)
    with Renderer(s16) as renderer:
        fresh16, fresh_depth = renderer.render(T_w_c)
    build_world(s1, plan.model)
    with Renderer(s1) as renderer:
        one, _ = renderer.render(T_w_c)
        renderer.reconfigure(s16.render)
        sixteen, depth = renderer.render(T_w_c)
        renderer.reconfigure(s1.render)
        one_again, _ = renderer.render(T_w_c)
    assert np.abs(one - fresh16).max() > 1e-3, "the image does not depend on the sample count"
    np.testing.assert_array_equal(sixteen, fresh16)
    np.testing.assert_array_equal(depth, fresh_depth)
    np.testing.assert_array_equal(one_again, one)


@pytest.mark.parametrize("samples, min_samples, expected", [(8, 2, 2), (8, 0, 4), (2, 0, 2)])
def test_adaptive_sampling_settings_reach_cycles(samples, min_samples, expected):
    """``[render] adaptive_threshold`` and ``adaptive_min_samples`` (0 = min(samples, 4)) are
    what Cycles is configured with; a threshold of 0 switches adaptive sampling off."""
    from simulation.render import configure_cycles

    camera = {"width": 64, "height": 48, "fx": 48.0, "fy": 48.0, "cx": 31.5, "cy": 23.5}
    s = _scenario(camera, render={"samples": samples, "adaptive_threshold": 0.05,
                                  "adaptive_min_samples": min_samples})
    scene = bpy.context.scene
    configure_cycles(scene, s.render, 64, 48, 5)
    assert scene.cycles.use_adaptive_sampling
    assert scene.cycles.adaptive_threshold == pytest.approx(0.05)
    assert scene.cycles.adaptive_min_samples == expected
    off = _scenario(camera, render={"samples": samples})
    configure_cycles(scene, off.render, 64, 48, 5)
    assert not scene.cycles.use_adaptive_sampling


def test_no_light_after_the_first_hit_without_bounces():
    """With ``max_bounces = 0`` a surface gets the sun (shadow rays) and its own sky term,
    nothing else: a bright emitter beside the ground (as the terrain's own sky emission is
    to its neighbours) brightens no ground pixel. Cycles still traces a BSDF ray from every
    first hit and used to add the emission it found there; with ``max_bounces = 1`` it must
    (the control)."""
    import dataclasses

    from simulation.plan import make_plan
    from simulation.render import Renderer
    from simulation.terrain.scene import build_world

    camera = {"width": 96, "height": 72, "fx": 70.0, "fy": 70.0, "cx": 47.5, "cy": 35.5}
    s0 = _scenario(camera, render={"samples": 8, "max_bounces": 0})
    s1 = dataclasses.replace(s0, render=dataclasses.replace(s0.render, max_bounces=1))
    plan = make_plan(s0)
    build_world(s0, plan.model)
    ground = float(plan.model.ground_height(1.0, 2.0))
    marker = np.array([1.0, 2.0, ground + 0.6])
    _add_marker(marker, 0.25)
    lamp = bpy.data.objects["marker"]
    T_w_c = _look_at(marker + np.array([-2.5, -2.5, 2.5]), marker - np.array([0, 0, 0.6]))
    brightening = {}
    with Renderer(s0) as renderer:
        for name, cfg in (("no bounce", s0.render), ("one bounce", s1.render)):
            renderer.reconfigure(cfg)
            lamp.hide_render = False
            lit, depth_lit = renderer.render(T_w_c)
            lamp.hide_render = True
            dark, depth_dark = renderer.render(T_w_c)
            # ground pixels at least 3 pixels away from the emitter's (anti-aliased edges)
            near = cv2.dilate((~(np.abs(depth_lit - depth_dark) < 1e-4)).astype(np.uint8),
                              np.ones((7, 7), np.uint8)) > 0
            ground_px = np.isfinite(depth_dark) & ~near
            assert 0.5 < ground_px.mean() < 0.99
            brightening[name] = float((lit - dark).mean(axis=2)[ground_px].max())
    assert brightening["one bounce"] > 0.05, brightening  # the control: the emitter lights
    assert brightening["no bounce"] <= 1e-6, brightening


def test_the_branching_material_renders_the_all_layer_graphs_image():
    """The regolith material skips the texture layers a shading point has faded out (Mix
    Shader branches on w > 0); every branch sums the layers as the graph that evaluates all of
    them does, so the renders are equal float for float: close to the ground (the finest
    layer on) and looking far over it (the finer layers off), ripples on and off, rocks."""
    from simulation.plan import make_plan
    from simulation.render import Renderer
    from simulation.terrain.material import surface_material
    from simulation.terrain.scene import build_world, sky_radiance

    camera = {"width": 96, "height": 72, "fx": 100.0, "fy": 100.0, "cx": 47.5, "cy": 35.5}
    s = _scenario(camera, render={"samples": 2},
                  terrain=dict(SMALL_TERRAIN, rock_density=2.0, ripple_coverage=0.5,
                               ripple_strength=1.3))  # a weight above 1: mask x 1.3
    plan = make_plan(s)
    x, y = 1.0, 2.0
    ground = float(plan.model.ground_height(x, y))
    poses = {"close": _look_at(np.array([x, y, ground + 0.3]), np.array([x + 0.1, y, ground])),
             "far": _look_at(np.array([x, y, ground + 1.5]), np.array([x + 12.0, y, ground]))}
    focal, a_finest, a_second = 100.0, 0.4 / 40 * 100.0, 1.8 / 40 * 100.0
    images = {}
    for branching in (True, False):
        build_world(s, plan.model)
        if not branching:
            mat = surface_material(s.terrain, s.seed, sky_radiance(s.lighting), focal,
                                   branching=False)
            for obj in bpy.data.objects:
                if obj.type == "MESH":
                    obj.data.materials[0] = mat
        with Renderer(s) as renderer:
            for name, T_w_c in poses.items():
                images[name, branching] = renderer.render(T_w_c)
    # the fade states the branches select between are in the images: the finest layer is
    # on (distance < a / 2 at normal incidence) close by, the second finest off far away
    _, depth_close = images["close", False]
    _, depth_far = images["far", False]
    assert np.nanmin(np.where(np.isfinite(depth_close), depth_close, np.nan)) < a_finest / 2
    assert np.mean(depth_far[np.isfinite(depth_far)] > a_second) > 0.2
    for name in poses:
        rgb_branching, _ = images[name, True]
        rgb_all, _ = images[name, False]
        assert rgb_all.max() > 0.01
        np.testing.assert_array_equal(rgb_branching, rgb_all, err_msg=name)


def test_instanced_rocks_stand_where_the_merged_rocks_do():
    """``rock_instances = true`` (Blender objects sharing prototype meshes) and the default
    (all rocks joined to the terrain's mesh) place every rock triangle at the same spot: the
    depth maps agree, and the rocks are in view (the depth differs from a rockless world)."""
    from simulation.plan import make_plan
    from simulation.render import Renderer
    from simulation.terrain.scene import build_world

    camera = {"width": 96, "height": 72, "fx": 80.0, "fy": 80.0, "cx": 47.5, "cy": 35.5}
    depths = {}
    for name, terrain in (("merged", {"rock_density": 3.0}),
                          ("instanced", {"rock_density": 3.0, "rock_instances": True}),
                          ("rockless", {"rock_density": 0.0})):
        s = _scenario(camera, render={"samples": 1},
                      terrain=dict(SMALL_TERRAIN, rock_model="power_law", **terrain))
        plan = make_plan(s)
        build_world(s, plan.model)
        with Renderer(s) as renderer:
            _, depths[name] = renderer.render(plan.poses[0])
    finite = np.isfinite(depths["merged"])
    assert finite.mean() > 0.9
    np.testing.assert_array_equal(np.isfinite(depths["instanced"]), finite)
    np.testing.assert_allclose(depths["instanced"][finite], depths["merged"][finite], rtol=1e-4)
    assert np.mean(np.abs(depths["rockless"][finite] - depths["merged"][finite]) > 0.01) > 0.02


def test_without_bounces_the_world_is_one_instance_its_image_unchanged():
    """With ``max_bounces = 0`` every single-user mesh gets a hidden second user (so Cycles
    makes it an instance whose mask rejects the bounce rays at once): the twin is visible to
    no ray the render traces and changes neither image nor depth beyond float rounding; with
    bounces (``reconfigure``) the twins are gone."""
    import dataclasses

    from simulation.plan import make_plan
    from simulation.render import Renderer, _reject_hidden_rays_at_instances
    from simulation.terrain.scene import build_world

    camera = {"width": 64, "height": 48, "fx": 48.0, "fy": 48.0, "cx": 31.5, "cy": 23.5}
    s = _scenario(camera, render={"samples": 2})
    plan = make_plan(s)
    build_world(s, plan.model)
    with Renderer(s) as renderer:
        twins = [o for o in bpy.data.objects if o.name.endswith(".bvh_twin")]
        assert [t.data.name for t in twins] == ["surface"]
        twin = twins[0]
        assert not any((twin.visible_camera, twin.visible_shadow, twin.visible_diffuse,
                        twin.visible_glossy, twin.visible_transmission))
        rgb, depth = renderer.render(plan.poses[0])
        _reject_hidden_rays_at_instances(renderer.scene, False)
        renderer.scene.update_tag()
        rgb_flat, depth_flat = renderer.render(plan.poses[0])
        renderer.reconfigure(dataclasses.replace(s.render, max_bounces=1))
        assert not [o for o in bpy.data.objects if o.name.endswith(".bvh_twin")]
    assert rgb.max() > 0.01
    np.testing.assert_allclose(rgb, rgb_flat, rtol=0, atol=1e-5 * rgb.max())
    np.testing.assert_allclose(depth, depth_flat, rtol=1e-6)


def test_the_ripple_contrast_scales_with_ripple_strength():
    """The ripple layer adds mask x ``ripple_strength`` x (texel - mean), also where that
    weight exceeds 1 (the fade's factor is not clamped): without bumps (radiance linear in
    the albedo) a pixel's radiance is linear in the strength, I(2) - I(1) = 2 (I(1) - I(0.5)),
    and the ripples do change the image."""
    from simulation.plan import make_plan
    from simulation.render import Renderer
    from simulation.terrain.scene import build_world

    camera = {"width": 64, "height": 48, "fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5}
    images = {}
    for strength in (0.5, 1.0, 2.0):
        s = _scenario(camera, render={"samples": 1},
                      terrain=dict(SMALL_TERRAIN, rock_density=0.0, ripple_coverage=0.9,
                                   bump_strength=0.0, ripple_strength=strength))
        plan = make_plan(s)
        x, y = 1.0, 2.0
        ground = float(plan.model.ground_height(x, y))
        build_world(s, plan.model)
        with Renderer(s) as renderer:
            images[strength], _ = renderer.render(
                _look_at(np.array([x, y, ground + 1.5]), np.array([x + 0.3, y, ground])))
    step_half = images[1.0] - images[0.5]
    step_one = images[2.0] - images[1.0]
    assert np.abs(step_half).max() > 0.01 * images[1.0].max()
    np.testing.assert_allclose(step_one, 2.0 * step_half, rtol=0,
                               atol=1e-4 * images[1.0].max())


def test_the_sun_without_multiple_importance_sampling_lights_the_same():
    """The sun lights the surfaces through shadow rays only (no MIS with the rays after the
    first hit, which almost never find its disc): the image equals the MIS render but for a
    few such hits, here with a sun disc 10x the default (0.011 % of the peak; 4 samples
    leave about 2 % RMS noise, 35 dB)."""
    from simulation.plan import make_plan
    from simulation.render import Renderer
    from simulation.terrain.scene import build_world

    camera = {"width": 64, "height": 48, "fx": 48.0, "fy": 48.0, "cx": 31.5, "cy": 23.5}
    s = _scenario(camera, render={"samples": 4}, lighting={"sun_angle": 3.5})
    plan = make_plan(s)
    build_world(s, plan.model)
    sun = bpy.data.lights["sun"]
    assert not sun.cycles.use_multiple_importance_sampling
    with Renderer(s) as renderer:
        rgb, _ = renderer.render(plan.poses[0])
        sun.cycles.use_multiple_importance_sampling = True
        sun.update_tag()  # (the scene's tag alone does not re-sync the light)
        rgb_mis, _ = renderer.render(plan.poses[0])
    assert rgb.max() > 0.01
    difference = np.abs(rgb - rgb_mis).max()
    assert 0 < difference < 1e-3 * rgb.max()  # > 0: the switch reached Cycles


def test_without_texture_contrast_the_albedo_is_the_base_colour():
    """``texture_contrast = 0`` takes its own branch (albedo = base colour, no gain); the
    gain's offset is L (1 - c) / 2c, so a tiny contrast must render nearly the same image:
    a wrong offset (say a factor 2) would change the albedo by about half."""
    from simulation.plan import make_plan
    from simulation.render import Renderer
    from simulation.terrain.scene import build_world

    camera = {"width": 64, "height": 48, "fx": 48.0, "fy": 48.0, "cx": 31.5, "cy": 23.5}
    images = {}
    for contrast in (0.0, 1e-4, 0.55):
        s = _scenario(camera, render={"samples": 1},
                      terrain=dict(SMALL_TERRAIN, texture_contrast=contrast))
        plan = make_plan(s)
        build_world(s, plan.model)
        with Renderer(s) as renderer:
            images[contrast], _ = renderer.render(plan.poses[0])
    peak = images[0.0].max()
    assert peak > 0.01
    np.testing.assert_allclose(images[1e-4], images[0.0], rtol=0, atol=2e-3 * peak)
    assert np.abs(images[0.55] - images[0.0]).max() > 0.05 * peak  # contrast shows
