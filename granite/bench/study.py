"""Study files: scenarios x terrain seeds x VO variants, read, validated and expanded into the
sequences and runs of a ``granite bench`` study (format: ``docs/bench.md``).

Validation works like the scenario and configuration files: an unknown key, a wrong type, a
value out of range, a missing scenario, configuration or dataset, or a flight that the chosen
terrain seed puts below ground is one :class:`~granite.errors.ConfigError` line naming the file
and the key (``study.toml: scenario[2].frames: ...``), before any work.
"""

from __future__ import annotations

import dataclasses
import json
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from granite.config_schema import check_value, read_toml_file, resolve_bundled_toml, toml_value
from granite.errors import ConfigError, GraniteError
from granite.evaluation import ALIGNMENTS, DEFAULT_RPE_DELTA

STUDY_DIR = Path(__file__).resolve().parent.parent.parent / "studies"

#: Rendering settings of a study (``[render]``) and per scenario entry: key -> (type, limits, default).
RENDER_KEYS: dict[str, tuple[type, dict, Any]] = {
    "width": (int, {"lo": 16, "hi": 8192}, None),
    "height": (int, {"lo": 16, "hi": 8192}, None),
    "samples": (int, {"lo": 1, "hi": 4096}, None),
    "grayscale": (bool, {}, True),
    "depth_format": (str, {"choices": ("npy", "inv16")}, "inv16"),
    "sensor": (bool, {}, True),
    "threads": (int, {"lo": 1, "hi": 256}, 1),
}
BUILTIN_CONFIGS = ("default", "reference")


@dataclass(frozen=True)
class Variant:
    """One VO configuration of the study."""

    name: str
    config: str = "default"  # "default", "reference" or a resolved file path
    finest_level_only: bool = False
    current_frame_keyframe: bool = False
    overrides: dict = field(default_factory=dict)

    @property
    def slug(self) -> str:
        return slugify(self.name)

    def label(self) -> str:
        """How the configuration was made (summary.json, report)."""
        base = {"default": "built-in defaults (configs/mono_default.toml)",
                "reference": "reference configuration (configs/reference.toml)"}.get(self.config, self.config)
        parts = [base]
        if self.overrides:
            parts.append("overrides " + json.dumps(self.overrides, sort_keys=True))
        ablations = [s for on, s in ((self.finest_level_only, "†"), (self.current_frame_keyframe, "‡")) if on]
        if ablations:
            parts.append("ablation " + " ".join(ablations))
        return f"{self.name}: " + ", ".join(parts)

    def build(self):
        """The validated :class:`~granite.estimator.config.VoConfig`."""
        from granite.cli.run_cmd import apply_ablations
        from granite.estimator.config import VoConfig

        if self.config == "default":
            base = VoConfig()
        elif self.config == "reference":
            base = VoConfig.reference()
        else:
            base = VoConfig.load(self.config)
        if self.overrides:
            data = {name: dataclasses.asdict(getattr(base, name)) for name in VoConfig.sections()}
            for table, values in self.overrides.items():
                data[table] = {**data.get(table, {}), **values}  # unknown tables: from_dict says so
            base = VoConfig.from_dict(data)
        return apply_ablations(base, self.finest_level_only, self.current_frame_keyframe)


@dataclass(frozen=True)
class Sequence:
    """One sequence of the study: a scenario rendered with one terrain seed, or a dataset."""

    id: str  # folder name (unique in the study)
    label: str  # scenario / dataset label as in the tables
    seed: int | None  # None: a pre-rendered dataset
    frames: str  # "A:B" or "all"
    dataset: str | None = None  # pre-rendered dataset folder (no rendering)
    scenario_text: str | None = None  # generated scenario file (rendered sequences)
    width: int | None = None
    height: int | None = None
    frame_range: tuple[int, int] | None = None  # [A, B) of the flight's frames
    fingerprint: str | None = None

    @property
    def rendered(self) -> bool:
        return self.dataset is None

    def folder(self, out: Path) -> Path:
        return Path(self.dataset) if self.dataset is not None else out / "sequences" / self.id

    def scenario_file(self, out: Path) -> Path:
        return out / "scenarios" / f"{self.id}.toml"

    def chunks(self, frames_per_task: int) -> list[tuple[int, int]]:
        a, b = self.frame_range
        return [(i, min(i + frames_per_task, b)) for i in range(a, b, frames_per_task)]


@dataclass(frozen=True)
class Study:
    """A validated study (see the module docstring)."""

    name: str
    description: str
    source: Path
    delta: float
    align: str
    frames_per_task: int
    sequences: tuple[Sequence, ...]
    variants: tuple[Variant, ...]

    def runs(self) -> list[tuple[Sequence, Variant]]:
        """Every (sequence, variant) pair, in table order."""
        return [(s, v) for s in self.sequences for v in self.variants]


def slugify(text: str) -> str:
    """A folder-safe name: † -> dagger, ‡ -> ddagger, other characters -> _."""
    text = text.replace("‡", "ddagger").replace("†", "dagger")
    return re.sub(r"[^A-Za-z0-9.-]+", "_", text).strip("_") or "x"


def resolve_study_path(name_or_path: str | Path) -> Path:
    """A study file, or the name of a bundled one (``studies/NAME.toml``)."""
    return resolve_bundled_toml(name_or_path, STUDY_DIR, "study")


def load_study(name_or_path: str | Path, check_flights: bool = True) -> Study:
    """Read and validate a study file (or bundled study name)."""
    path = resolve_study_path(name_or_path)
    return parse_study(read_toml_file(path, "the study"), path, check_flights)


def scenario_toml(data: dict) -> str:
    """A scenario dict (top-level keys and one level of tables) as TOML."""
    lines = ["# written by granite bench: the study's scenario with its seed and overrides"]
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    for key, value in data.items():
        if key not in tables:
            lines.append(f"{key} = {toml_value(value)}")
    for name, table in tables.items():
        lines.append(f"\n[{name}]")
        lines.extend(f"{key} = {toml_value(value)}" for key, value in table.items())
    return "\n".join(lines) + "\n"


def parse_study(data: dict, source: str | Path = "<study>", check_flights: bool = True) -> Study:
    """Build a :class:`Study` from decoded TOML (``source`` names it in errors; relative paths
    in the file are relative to its folder)."""
    src = Path(source)
    base = src.parent

    def err(message: str) -> ConfigError:
        return ConfigError(f"{src}: {message}")

    def value(table: dict, key: str, typ: type, limits: dict, where: str, default: Any = None) -> Any:
        if key not in table:
            return default
        return check_value(table[key], typ, limits, where, err)

    def known_keys(table: dict, known: tuple, where: str) -> None:
        for key in table:
            if key not in known:
                raise err(f"{where}{key}: unknown key (known keys: {', '.join(known)})")

    if not isinstance(data, dict):
        raise err("a study is a TOML table")
    top = ("name", "description", "delta", "align", "seeds", "frames_per_task", "render", "scenario", "variant")
    known_keys(data, top, "")
    name = value(data, "name", str, {}, "name", src.stem)
    description = value(data, "description", str, {}, "description", "")
    delta = value(data, "delta", float, {"lo": 0.0, "lo_open": True, "hi": 1e4}, "delta", DEFAULT_RPE_DELTA)
    align = value(data, "align", str, {"choices": ALIGNMENTS}, "align", "sim3")
    frames_per_task = value(data, "frames_per_task", int, {"lo": 1, "hi": 100000}, "frames_per_task", 20)
    seeds = _seeds(data, "seeds", err)
    render = data.get("render", {})
    if not isinstance(render, dict):
        raise err("render must be a table ([render])")
    known_keys(render, tuple(RENDER_KEYS), "render.")
    render_defaults = {k: value(render, k, t, lim, f"render.{k}", d) for k, (t, lim, d) in RENDER_KEYS.items()}

    entries = data.get("scenario")
    if not isinstance(entries, list) or not entries or not all(isinstance(e, dict) for e in entries):
        raise err("needs at least one [[scenario]] table (a bundled scenario, a scenario file or a dataset)")
    variants_data = data.get("variant")
    if not isinstance(variants_data, list) or not variants_data or not all(isinstance(e, dict) for e in variants_data):
        raise err("needs at least one [[variant]] table (a VO configuration)")

    sequences: list[Sequence] = []
    for k, entry in enumerate(entries):
        sequences.extend(_sequences(entry, k, base, seeds, render_defaults, err, value, known_keys, check_flights))
    ids = [s.id for s in sequences]
    for s in sequences:
        if ids.count(s.id) > 1:
            raise err(f"sequence {s.id} appears twice (give the scenario entries different labels)")

    variants: list[Variant] = []
    for k, entry in enumerate(variants_data):
        where = f"variant[{k}]."
        known_keys(entry, ("name", "config", "finest_level_only", "current_frame_keyframe", "overrides"), where)
        if "name" not in entry:
            raise err(f"{where}name: missing (every variant needs a name, e.g. \"ours\")")
        vname = value(entry, "name", str, {}, where + "name")
        if not vname.strip():
            raise err(f"{where}name: must not be empty")
        config = value(entry, "config", str, {}, where + "config", "default")
        if config not in BUILTIN_CONFIGS:
            p = ((base / config) if not Path(config).is_absolute() else Path(config)).resolve()
            if not p.is_file():
                raise err(f"{where}config: no configuration file {p} (or one of {', '.join(BUILTIN_CONFIGS)})")
            config = str(p)
        overrides = entry.get("overrides", {})
        if not isinstance(overrides, dict) or not all(isinstance(v, dict) for v in overrides.values()):
            raise err(f"{where}overrides: must be a table of tables, e.g. "
                      "{ optical_flow = { detect_all_levels = false } }")
        variant = Variant(vname, config,
                          value(entry, "finest_level_only", bool, {}, where + "finest_level_only", False),
                          value(entry, "current_frame_keyframe", bool, {}, where + "current_frame_keyframe", False),
                          overrides)
        try:
            variant.build()
        except GraniteError as error:
            raise err(f"{where[:-1]} ({vname}): {error}") from None
        variants.append(variant)
    slugs = [v.slug for v in variants]
    for v in variants:
        if slugs.count(v.slug) > 1:
            raise err(f"variant name {v.name!r} is not unique (folder name {v.slug})")
    return Study(name, description, src, delta, align, frames_per_task, tuple(sequences), tuple(variants))


def _seeds(table: dict, key: str, err, where: str = "") -> tuple[int, ...] | None:
    if key not in table:
        return None
    seeds = table[key]
    if not isinstance(seeds, list) or not seeds:
        raise err(f"{where}{key}: must be a non-empty list of integers, got {seeds!r}")
    out = tuple(check_value(s, int, {"lo": 0, "hi": 2**31 - 1}, f"{where}{key}[{i}]", err)
                for i, s in enumerate(seeds))
    if len(set(out)) != len(out):
        raise err(f"{where}{key}: a seed appears twice")
    return out


def _sequences(entry: dict, k: int, base: Path, study_seeds, render_defaults: dict, err, value, known_keys,
               check_flights: bool) -> list[Sequence]:
    from granite.io import open_dataset

    where = f"scenario[{k}]."
    known_keys(entry, ("scenario", "dataset", "label", "frames", "seeds", "overrides", *RENDER_KEYS), where)
    if ("scenario" in entry) == ("dataset" in entry):
        raise err(f"{where[:-1]}: give exactly one of scenario (a bundled name or a .toml file) "
                  "and dataset (a pre-rendered folder)")
    label = value(entry, "label", str, {}, where + "label")
    if label is not None and not label.strip():
        raise err(f"{where}label: must not be empty")
    if "dataset" in entry:
        for key in ("frames", "seeds", "overrides", *RENDER_KEYS):
            if key in entry:
                raise err(f"{where}{key}: not for a dataset entry (it is not rendered)")
        p = Path(value(entry, "dataset", str, {}, where + "dataset"))
        p = (p if p.is_absolute() else base / p).resolve()
        try:
            ds = open_dataset(p)
        except GraniteError as error:
            raise err(f"{where}dataset: {error}") from None
        if ds.ground_truth is None:
            raise err(f"{where}dataset: {p} has no ground truth (a study evaluates every run)")
        label = label or p.name
        return [Sequence(slugify(label), label, None, "all", dataset=str(p))]

    from simulation.scenario import parse_scenario, resolve_scenario_path, with_overrides
    from simulation.run import parse_frames
    from simulation.writer import fingerprint

    name = value(entry, "scenario", str, {}, where + "scenario")
    try:
        is_file = name.endswith(".toml") or "/" in name
        path = resolve_scenario_path(base / name if is_file and not Path(name).is_absolute() else name)
        scen_data = tomllib.loads(path.read_text(encoding="utf-8"))
    except GraniteError as error:
        raise err(f"{where}scenario: {error}") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as error:
        raise err(f"{where}scenario: cannot read {name}: {error}") from None
    opts = {key: value(entry, key, t, lim, where + key, render_defaults[key])
            for key, (t, lim, _) in RENDER_KEYS.items()}
    overrides = entry.get("overrides", {})
    if not isinstance(overrides, dict) or not all(isinstance(v, dict) for v in overrides.values()):
        raise err(f"{where}overrides: must be a table of scenario tables, e.g. {{ sensor = {{ read_noise = 3.0 }} }}")
    seeds = _seeds(entry, "seeds", err, where) or study_seeds
    merged = {key: (dict(v) if isinstance(v, dict) else v) for key, v in scen_data.items()}
    for table, values in overrides.items():
        if table == "flight" and "type" in values:
            raise err(f"{where}overrides.flight.type: the flight type cannot be overridden")
        merged.setdefault(table, {})
        if not isinstance(merged[table], dict):
            raise err(f"{where}overrides.{table}: {table} is not a table of the scenario")
        merged[table].update(values)
    render = merged.setdefault("render", {})
    render.update({"grayscale": opts["grayscale"], "depth_format": opts["depth_format"],
                   "threads": opts["threads"]})
    if opts["samples"] is not None:
        render["samples"] = opts["samples"]
    merged.setdefault("sensor", {})["enabled"] = opts["sensor"]
    out = []
    for seed in seeds or (None,):
        data = dict(merged)
        if seed is not None:
            data["seed"] = seed
        try:
            scenario = with_overrides(parse_scenario(data, path), width=opts["width"], height=opts["height"])
        except GraniteError as error:
            raise err(f"{where}scenario {name}: {error}") from None
        try:
            frame_range = parse_frames(value(entry, "frames", str, {}, where + "frames"), scenario.n_frames)
        except GraniteError as error:
            raise err(f"{where}frames: {error}") from None
        if check_flights:
            from simulation.plan import make_plan

            try:
                make_plan(scenario)
            except GraniteError as error:
                raise err(f"{where}scenario {name} with seed {scenario.seed}: {error}") from None
        lab = label or scenario.name
        a, b = frame_range.start, frame_range.stop
        cam = scenario.camera
        seq_id = slugify(f"{lab}_seed{scenario.seed}_{cam.width}x{cam.height}_{a}-{b}")
        out.append(Sequence(seq_id, lab, scenario.seed, f"{a}:{b}", scenario_text=scenario_toml(data),
                            width=opts["width"], height=opts["height"], frame_range=(a, b),
                            fingerprint=fingerprint(scenario)))
    return out


def check_existing_sequences(study: Study, out: Path) -> None:
    """A sequence folder of ``out`` holding a render of another scenario (the study or the
    scenario file changed since) is one error line before any work."""
    for s in study.sequences:
        if not s.rendered:
            continue
        manifest = s.folder(out) / "manifest.json"
        if not manifest.is_file():
            continue
        try:
            old = json.loads(manifest.read_text(encoding="utf-8")).get("fingerprint")
        except (OSError, json.JSONDecodeError) as error:
            raise ConfigError(f"{manifest}: cannot read: {error}") from None
        if old != s.fingerprint:
            raise ConfigError(f"{s.folder(out)}: holds a render of a different scenario or settings "
                              f"(fingerprint {old} != {s.fingerprint}); delete it or use another --out")
