"""Scenario files: TOML -> a typed, validated, immutable tree of dataclasses.

Every field has a default, a type and an allowed range; an unknown key, a wrong type or a value
out of range raises :class:`granite.errors.ConfigError` naming the file and the dotted key,
before anything is rendered. Units: metres, seconds, degrees (angles in the file), Hz.

World frame: z up, metres; the terrain is centred on the origin. Flight altitudes are metres
above the terrain surface at the flight's reference point (``center`` / ``start``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from granite.config_schema import build_dataclass, read_toml_file, resolve_bundled_toml
from granite.config_schema import check_value as _check_value
from granite.config_schema import spec_field as _f
from granite.errors import ConfigError

SCENARIO_DIR = Path(__file__).resolve().parent.parent / "scenarios"


@dataclass(frozen=True)
class CameraConfig:
    """Intrinsics in the project's pixel convention (centre of the top-left pixel = (0, 0)).

    ``pinhole``: fx, fy, cx, cy. ``kb4``: an equidistant fisheye (r = fx * theta) written as
    Kannala-Brandt with k1..k4 = 0; it needs a square image, fx == fy and the principal point
    at the image centre; pixels farther than width / 2 from the centre see nothing.
    """

    model: str = _f("pinhole", choices=("pinhole", "kb4"))
    width: int = _f(640, 16, 8192)
    height: int = _f(480, 16, 8192)
    fx: float = _f(400.0, 1.0, 1e5)
    fy: float = _f(400.0, 1.0, 1e5)
    cx: float = _f(319.5, -1e4, 1e4)
    cy: float = _f(239.5, -1e4, 1e4)
    rate_hz: float = _f(20.0, 0.1, 1000.0)
    clip_start: float = _f(0.05, 1e-4, 10.0)


@dataclass(frozen=True)
class RenderConfig:
    """Cycles settings and image post-processing."""

    samples: int = _f(4, 1, 4096)
    denoise: bool = _f(False, doc="OpenImageDenoise (CPU); rarely needed: the lighting is noise-free")
    adaptive_threshold: float = _f(0.0, 0.0, 1.0, doc="0 disables adaptive sampling")
    adaptive_min_samples: int = _f(0, 0, 4096, doc="with adaptive sampling, the samples every "
                                   "pixel gets; 0 = min(samples, 4)")
    max_bounces: int = _f(0, 0, 16, doc="0 = direct sun + analytic sky light (noise-free)")
    exposure: float = _f(0.0, -10.0, 10.0, doc="stops; used by sensor.exposure_mode = 'fixed'")
    motion_blur: bool = _f(False, doc="Cycles motion blur (exact, twice the render time); "
                           "the sensor's motion_blur is the cheap default")
    shutter: float = _f(0.5, 0.0, 1.0, doc="exposure time as a fraction of the frame interval")
    threads: int = _f(2, 1, 256)
    grayscale: bool = _f(True, doc="8-bit monochrome images, the default sensor's (false: colour, "
                         "the sensor model applied per channel)")
    depth_format: str = _f("npy", choices=("npy", "inv16"))


@dataclass(frozen=True)
class SensorConfig:
    """Camera sensor model (:mod:`simulation.sensor`). Defaults: a 640x480 global-shutter
    monochrome navigation camera like Ingenuity's (OmniVision OV7251 class); each value and
    its source is documented in docs/simulation.md."""

    enabled: bool = _f(True, doc="false = ideal camera: same exposure and encoding, no noise, "
                       "fixed pattern, optics or JPEG")
    full_well: float = _f(6300.0, 100.0, 1e7, doc="full-well capacity (electrons)")
    read_noise: float = _f(2.1, 0.0, 1e4, doc="temporal read noise (electrons rms)")
    dark_current: float = _f(50.0, 0.0, 1e7, doc="electrons per second")
    dsnu: float = _f(1.0, 0.0, 1e4, doc="dark signal non-uniformity (electrons rms, fixed)")
    prnu: float = _f(0.01, 0.0, 0.5, doc="photo-response non-uniformity (relative rms, fixed)")
    analog_gain: float = _f(1.0, 0.01, 1000.0, doc="1 = the full well fills the ADC range")
    adc_bits: int = _f(10, 8, 16)
    output_bits: int = _f(8, choices=(8, 16))
    transfer: str = _f("linear", choices=("linear", "srgb"), doc="output encoding")
    exposure_mode: str = _f("auto", choices=("auto", "fixed"),
                            doc="auto: mean radiance -> ae_target of the ADC range; fixed: "
                            "radiance 2^-render.exposure fills it")
    ae_target: float = _f(0.3, 0.001, 1.0, doc="auto exposure: mean level / ADC range")
    exposure_time: float = _f(0.003, 0.0, 1.0, doc="seconds (motion blur, dark signal)")
    motion_blur: bool = _f(True, doc="blur over exposure_time from depth and poses")
    psf_sigma: float = _f(0.5, 0.0, 20.0, doc="Gaussian lens PSF (pixels, 0 = off)")
    corner_illumination: float = _f(0.75, 0.05, 1.0, doc="vignetting: relative illumination "
                                    "at the image corner (1 = off)")
    jpeg_quality: int = _f(0, 0, 100, doc="JPEG compression quality (0 = off)")


@dataclass(frozen=True)
class TerrainConfig:
    """Procedural Mars-analogue terrain (see :mod:`simulation.terrain`)."""

    extent: float = _f(256.0, 8.0, 4096.0, doc="side of the detailed square (m)")
    resolution: float = _f(0.5, 0.05, 16.0, doc="grid spacing of the detailed square (m)")
    far_extent: float = _f(3000.0, 0.0, 1e5, doc="coarse apron up to this distance (m)")
    relief: float = _f(6.0, 0.0, 500.0, doc="amplitude of the large-scale relief (m)")
    relief_wavelength: float = _f(120.0, 1.0, 1e4)
    ridges: float = _f(0.35, 0.0, 1.0, doc="weight of ridged noise")
    plains: float = _f(0.6, 0.0, 1.0, doc="how strongly smooth plains flatten the relief")
    detail: float = _f(0.25, 0.0, 10.0, doc="amplitude of metre-scale undulations (m)")
    crater_density: float = _f(6.0, 0.0, 500.0, doc="craters per hectare with D >= min")
    crater_min_diameter: float = _f(3.0, 0.2, 1000.0)
    crater_max_diameter: float = _f(45.0, 0.2, 5000.0)
    crater_depth_ratio: float = _f(0.15, 0.0, 0.5, doc="depth / diameter of a fresh crater")
    crater_size_exponent: float = _f(2.0, 0.5, 5.0, doc="N(>D) ~ D^-exponent (2 = the "
                                     "equilibrium population of small Martian craters)")
    rock_model: str = _f("golombek_rapp", choices=("golombek_rapp", "power_law"),
                         doc="rock size-frequency model")
    rock_abundance: float = _f(0.06, 0.005, 0.4, doc="golombek_rapp: fraction k of the area "
                               "covered by rocks of any size (Mars landing sites 0.05-0.2)")
    rock_density: float = _f(0.3, 0.0, 10.0, doc="power_law: rocks per m^2 with D >= min")
    rock_min_diameter: float = _f(0.15, 0.01, 20.0, doc="smaller stones are in the texture")
    rock_max_diameter: float = _f(2.0, 0.01, 50.0)
    rock_size_exponent: float = _f(2.2, 0.5, 6.0, doc="power_law: N(>D) ~ D^-exponent")
    ripple_coverage: float = _f(0.35, 0.0, 1.0, doc="fraction of the ground with aeolian ripples")
    ripple_wavelength: float = _f(0.8, 0.02, 50.0, doc="crest spacing of the ripples (m)")
    ripple_azimuth: float = _f(60.0, -360.0, 360.0, doc="compass direction of the wind across "
                               "the crests (deg)")
    ripple_strength: float = _f(2.0, 0.0, 5.0, doc="slope and albedo contrast of the ripples")
    ripple_patch_size: float = _f(25.0, 1.0, 1000.0, doc="typical size of a ripple field (m)")
    rock_instances: bool = _f(False, doc="Blender instances instead of one merged mesh")
    texture_scales: tuple = _f((0.4, 1.8, 8.1, 36.5), 0.01, 1000.0, doc="tile sizes (m)")
    texture_contrast: float = _f(0.55, 0.0, 1.0, doc="albedo modulation by the tile")
    bump_strength: float = _f(1.0, 0.0, 10.0)
    color: tuple = _f((0.40, 0.205, 0.11), 0.0, 1.0, length=3, doc="linear albedo")
    color_dark: tuple = _f((0.16, 0.10, 0.07), 0.0, 1.0, length=3)
    rock_color: tuple = _f((0.18, 0.12, 0.09), 0.0, 1.0, length=3)


@dataclass(frozen=True)
class LightingConfig:
    """Sun and sky. Azimuth: compass degrees, clockwise from north (+y) to east (+x)."""

    sun_elevation: float = _f(25.0, 1.0, 90.0)
    sun_azimuth: float = _f(135.0, -360.0, 360.0)
    sun_strength: float = _f(5.0, 0.0, 1000.0, doc="irradiance (W/m^2 in Blender units)")
    sun_angle: float = _f(0.35, 0.0, 30.0, doc="angular diameter (deg)")
    sky_color: tuple = _f((0.80, 0.56, 0.34), 0.0, 1.0, length=3, doc="linear RGB")
    sky_strength: float = _f(0.45, 0.0, 100.0)


@dataclass(frozen=True)
class FrameDropsConfig:
    """Seeded bursts of missing images (ground truth is kept for every frame)."""

    probability: float = _f(0.0, 0.0, 1.0, doc="per-frame probability that a burst starts")
    min_burst: int = _f(1, 1, 10000)
    max_burst: int = _f(5, 1, 10000)
    keep_first: int = _f(20, 0, 1000000, doc="frames at the start that are never dropped")


# ------------------------------------------------------------------------------- flights


@dataclass(frozen=True)
class _FlightBase:
    duration: float = _f(20.0, 0.1, 36000.0)
    clearance: float = _f(1.0, 0.0, 100.0, doc="minimum height above terrain and rocks (m)")
    pitch: float = _f(45.0, -90.0, 90.0, doc="camera look-down angle below the horizon (deg)")


@dataclass(frozen=True)
class SpiralFlight(_FlightBase):
    """Helical ascent then descent at constant speed (paper Fig. 4)."""

    type: str = "spiral"
    duration: float = _f(40.0, 0.1, 36000.0)
    center: tuple = _f((0.0, 0.0), -1e5, 1e5, length=2)
    radius: float = _f(12.0, 0.5, 1e4)
    altitude_min: float = _f(4.0, 0.0, 1e4)
    altitude_max: float = _f(40.0, 0.0, 1e4)
    speed: float = _f(4.0, 0.01, 100.0, doc="constant path speed (m/s)")
    yaw_offset: float = _f(90.0, -360.0, 360.0, doc="0 = look along the path, 90 = inward")


@dataclass(frozen=True)
class RotationFlight(_FlightBase):
    """Translate, rotate in place about the camera centre, translate again."""

    type: str = "rotation"
    start: tuple = _f((-10.0, 0.0), -1e5, 1e5, length=2)
    heading: float = _f(0.0, -360.0, 360.0, doc="compass heading of the first leg (deg)")
    altitude: float = _f(10.0, 0.0, 1e4)
    leg_length: float = _f(10.0, 0.0, 1e4, doc="length of each straight leg (m)")
    rotation_duration: float = _f(8.0, 0.1, 1e4, doc="the legs share the rest of duration")
    yaw_sweep: float = _f(180.0, -1080.0, 1080.0, doc="total yaw turned in place (deg)")
    pitch_sweep: float = _f(20.0, 0.0, 89.0, doc="amplitude of the pitch nod in place (deg)")


@dataclass(frozen=True)
class HoverFlight(_FlightBase):
    """Station keeping with small smooth drifts."""

    type: str = "hover"
    center: tuple = _f((0.0, 0.0), -1e5, 1e5, length=2)
    altitude: float = _f(8.0, 0.0, 1e4)
    amplitude: float = _f(0.3, 0.0, 100.0, doc="position drift amplitude (m)")
    yaw_amplitude: float = _f(5.0, 0.0, 180.0, doc="deg")
    heading: float = _f(0.0, -360.0, 360.0)
    period: float = _f(6.0, 0.1, 1e4, doc="period of the slowest drift (s)")


@dataclass(frozen=True)
class SurveyFlight(_FlightBase):
    """Lawnmower pattern: parallel legs joined by smooth turns (quintic spline)."""

    type: str = "survey"
    center: tuple = _f((0.0, 0.0), -1e5, 1e5, length=2)
    width: float = _f(40.0, 0.1, 1e4, doc="across-track size of the area (m)")
    length: float = _f(40.0, 0.1, 1e4, doc="along-track leg length (m)")
    spacing: float = _f(10.0, 0.1, 1e4, doc="distance between legs (m)")
    heading: float = _f(0.0, -360.0, 360.0, doc="compass heading of the first leg")
    altitude: float = _f(20.0, 0.0, 1e4)


@dataclass(frozen=True)
class AggressiveFlight(_FlightBase):
    """Fast, low, randomly turning flight with banking (seeded quintic spline)."""

    type: str = "aggressive"
    center: tuple = _f((0.0, 0.0), -1e5, 1e5, length=2)
    radius: float = _f(25.0, 1.0, 1e4, doc="waypoints within this distance of the center")
    altitude_min: float = _f(3.0, 0.0, 1e4)
    altitude_max: float = _f(8.0, 0.0, 1e4)
    speed: float = _f(7.0, 0.01, 100.0, doc="mean path speed (m/s)")
    turn_distance: float = _f(8.0, 0.5, 1e4, doc="mean distance between turns (m)")
    bank: float = _f(1.0, 0.0, 5.0, doc="0 = level camera, 1 = quadrotor-like banking")


FLIGHT_TYPES: dict[str, type] = {
    "spiral": SpiralFlight,
    "rotation": RotationFlight,
    "hover": HoverFlight,
    "survey": SurveyFlight,
    "aggressive": AggressiveFlight,
}


@dataclass(frozen=True)
class Scenario:
    """A complete, validated scenario. ``source`` is the file it was read from."""

    name: str
    description: str = ""
    seed: int = 0
    camera: CameraConfig = field(default_factory=CameraConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    lighting: LightingConfig = field(default_factory=LightingConfig)
    flight: Any = field(default_factory=SpiralFlight)
    frame_drops: FrameDropsConfig = field(default_factory=FrameDropsConfig)
    source: Path | None = None

    @property
    def n_frames(self) -> int:
        """Frames of the whole flight at ``camera.rate_hz`` (t = i / rate, t <= duration)."""
        return int(math.floor(self.flight.duration * self.camera.rate_hz + 1e-9)) + 1


# ------------------------------------------------------------------------------- loading

_SECTIONS = {
    "camera": CameraConfig,
    "render": RenderConfig,
    "sensor": SensorConfig,
    "terrain": TerrainConfig,
    "lighting": LightingConfig,
    "frame_drops": FrameDropsConfig,
}


def _build(cls: type, table: Any, prefix: str, err, skip: tuple = ()) -> Any:
    return build_dataclass(
        cls, table, err, where=lambda key: f"{prefix}.{key}",
        unknown=lambda key, known: f"unknown key {prefix}.{key} (known keys: {known})",
        name=prefix, skip=skip)


def _cross_checks(s: Scenario, err) -> None:
    c, t, f = s.camera, s.terrain, s.flight
    if c.model == "kb4":
        if c.width != c.height:
            raise err("camera.width must equal camera.height for the kb4 model (Cycles renders "
                      "the equidistant fisheye exactly only on square images)")
        if c.fx != c.fy:
            raise err("camera.fy must equal camera.fx for the kb4 (equidistant fisheye) model")
        if abs(c.cx - (c.width - 1) / 2) > 1e-9 or abs(c.cy - (c.height - 1) / 2) > 1e-9:
            raise err(f"camera.cx, camera.cy must be the image centre ({(c.width - 1) / 2:g}, "
                      f"{(c.height - 1) / 2:g}) for the kb4 model")
        if c.width / c.fx > 2 * math.pi:
            raise err("camera.fx too small: the fisheye would cover more than 360 degrees")
    if t.crater_min_diameter > t.crater_max_diameter:
        raise err("terrain.crater_min_diameter must not exceed terrain.crater_max_diameter")
    if t.rock_min_diameter > t.rock_max_diameter:
        raise err("terrain.rock_min_diameter must not exceed terrain.rock_max_diameter")
    if t.resolution * 4 > t.extent:
        raise err("terrain.resolution must be at most a quarter of terrain.extent")
    cells = (t.extent / t.resolution) ** 2
    if cells > 4.2e6:
        raise err(f"terrain.extent / terrain.resolution gives {cells:.3g} grid cells (max 4.2e6)")
    if s.render.adaptive_min_samples > s.render.samples:
        raise err("render.adaptive_min_samples must not exceed render.samples")
    if s.frame_drops.min_burst > s.frame_drops.max_burst:
        raise err("frame_drops.min_burst must not exceed frame_drops.max_burst")
    for lo, hi in (("altitude_min", "altitude_max"),):
        if hasattr(f, lo) and getattr(f, lo) > getattr(f, hi):
            raise err(f"flight.{lo} must not exceed flight.{hi}")
    if len(t.texture_scales) > 6:
        raise err("terrain.texture_scales takes at most 6 tile sizes")
    sn = s.sensor
    if sn.enabled and sn.motion_blur and sn.exposure_time > 0 and s.render.motion_blur:
        raise err("sensor.motion_blur and render.motion_blur are both on (the image would be "
                  "blurred twice); switch one off")
    if sn.exposure_time >= 1.0 / c.rate_hz:
        raise err(f"sensor.exposure_time ({sn.exposure_time:g} s) must be shorter than the "
                  f"frame interval (1 / camera.rate_hz = {1.0 / c.rate_hz:g} s)")
    if sn.jpeg_quality > 0 and sn.output_bits != 8:
        raise err("sensor.jpeg_quality needs sensor.output_bits = 8")
    if f.type == "rotation" and f.rotation_duration >= f.duration:
        raise err("flight.rotation_duration must be shorter than flight.duration")


def parse_scenario(data: dict, source: str | Path = "<scenario>") -> Scenario:
    """Build a :class:`Scenario` from decoded TOML ``data`` (``source`` names it in errors)."""
    src = Path(source)

    def err(message: str) -> ConfigError:
        return ConfigError(f"{src}: {message}")

    data = dict(data)
    kwargs: dict[str, Any] = {}
    for key in ("name", "description"):
        if key in data:
            kwargs[key] = _check_value(data.pop(key), str, {}, key, err)
    if "seed" in data:
        kwargs["seed"] = _check_value(data.pop("seed"), int, {"lo": 0, "hi": 2**31 - 1}, "seed", err)
    for key, cls in _SECTIONS.items():
        if key in data:
            kwargs[key] = _build(cls, data.pop(key), key, err)
    if "flight" in data:
        table = data.pop("flight")
        if not isinstance(table, dict):
            raise err("[flight] must be a table")
        kind = table.get("type", "spiral")
        if kind not in FLIGHT_TYPES:
            raise err(f"flight.type must be one of {', '.join(FLIGHT_TYPES)}, got {kind!r}")
        body = {k: v for k, v in table.items() if k != "type"}
        kwargs["flight"] = _build(FLIGHT_TYPES[kind], body, "flight", err, skip=("type",))
    if data:
        known = ", ".join(["name", "description", "seed", "flight", *_SECTIONS])
        raise err(f"unknown key {next(iter(data))} (known keys: {known})")
    kwargs.setdefault("name", src.stem)
    scenario = Scenario(**kwargs, source=None if str(source) == "<scenario>" else src)
    _cross_checks(scenario, err)
    return scenario


def resolve_scenario_path(name_or_path: str | Path) -> Path:
    """A path to an existing file, or the name of a bundled scenario (``scenarios/NAME.toml``)."""
    return resolve_bundled_toml(name_or_path, SCENARIO_DIR, "scenario")


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Read and validate a scenario file (or bundled scenario name)."""
    path = resolve_scenario_path(name_or_path)
    return parse_scenario(read_toml_file(path, "scenario"), path)


def with_overrides(s: Scenario, width: int | None = None, height: int | None = None,
                   samples: int | None = None, grayscale: bool | None = None,
                   depth_format: str | None = None, sensor: bool | None = None) -> Scenario:
    """A copy with command-line overrides. A new image size rescales the intrinsics (same
    field of view: fx, cx scale with the width, fy, cy with the height)."""
    cam, ren = s.camera, s.render

    def err(message: str) -> ConfigError:
        return ConfigError(f"command line: {message}")

    if width is not None or height is not None:
        w = _check_value(cam.width if width is None else width, int, {"lo": 16, "hi": 8192}, "--width", err)
        h = _check_value(cam.height if height is None else height, int, {"lo": 16, "hi": 8192}, "--height", err)
        sx, sy = w / cam.width, h / cam.height
        if cam.model == "kb4" and abs(sx - sy) > 1e-12:
            raise err("the kb4 camera keeps its aspect ratio: --width/--height must scale equally")
        cam = dataclasses.replace(cam, width=w, height=h, fx=cam.fx * sx, fy=cam.fy * sy,
                                  cx=(cam.cx + 0.5) * sx - 0.5, cy=(cam.cy + 0.5) * sy - 0.5)
    changes: dict[str, Any] = {}
    if samples is not None:
        changes["samples"] = _check_value(samples, int, {"lo": 1, "hi": 4096}, "--samples", err)
    if grayscale is not None:
        changes["grayscale"] = bool(grayscale)
    if depth_format is not None:
        changes["depth_format"] = _check_value(
            depth_format, str, {"choices": ("npy", "inv16")}, "--depth-format", err)
    ren = dataclasses.replace(ren, **changes)
    sen = s.sensor if sensor is None else dataclasses.replace(s.sensor, enabled=bool(sensor))
    return dataclasses.replace(s, camera=cam, render=ren, sensor=sen)


def scenario_to_dict(s: Scenario) -> dict:
    """Plain-data view of a scenario (for the manifest)."""
    out = dataclasses.asdict(s)
    out["source"] = None if s.source is None else str(s.source)
    out["flight"]["type"] = s.flight.type
    return out
