"""Metadata-driven validation of configuration dataclasses (the VO tables and the scenarios).

A key's type comes from its dataclass field annotation (``bool``, ``int``, ``float``, ``str``
or ``tuple`` of numbers); its allowed values from metadata, a dict with the optional entries

=============  ====================================================================
``lo``, ``hi``  bounds (closed unless ``lo_open`` / ``hi_open`` is true; ``None`` = none)
``choices``     allowed values (strings)
``length``      number of elements of a tuple
``doc``         one-line description
=============  ====================================================================

:func:`spec_field` makes a field carrying such metadata, :func:`limits` the dict alone (for
callers that keep the ranges beside a dataclass they do not own). :func:`check_value` checks
one value, :func:`check_table` / :func:`build_dataclass` a whole TOML table. Errors are built by the caller's ``err``
callable from a one-line message, so every user of this module chooses its own prefix (file
name, table) while the wording of the messages stays the same everywhere.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import field
from pathlib import Path
from typing import Any, get_origin, get_type_hints


def limits(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False, choices: tuple | None = None, length: int | None = None,
           doc: str = "", **extra: Any) -> dict[str, Any]:
    """Validation metadata (see the module docstring); ``extra`` entries are kept as given."""
    return {"lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open, "choices": choices,
            "length": length, "doc": doc, **extra}


def spec_field(default: Any, lo: float | None = None, hi: float | None = None, **meta: Any) -> Any:
    """A dataclass field with validation metadata (closed range ``[lo, hi]`` by default)."""
    metadata = limits(lo, hi, **meta)
    if isinstance(default, (list, tuple)):
        return field(default_factory=lambda d=tuple(default): d, metadata=metadata)
    return field(default=default, metadata=metadata)


def has_limits(meta: Mapping[str, Any]) -> bool:
    """Whether ``meta`` restricts the values (a bound or a list of choices)."""
    return any(meta.get(k) is not None for k in ("lo", "hi", "choices"))


def range_text(meta: Mapping[str, Any]) -> str:
    """``in [lo, hi]``, ``in (lo, hi]``, ``>= lo``, ``< hi`` ... (empty without bounds)."""
    lo, hi = meta.get("lo"), meta.get("hi")
    lo_open, hi_open = bool(meta.get("lo_open")), bool(meta.get("hi_open"))
    if lo is not None and hi is not None:
        return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f"{'<' if hi_open else '<='} {hi:g}"
    return ""


def normalise_type(typ: Any) -> Any:
    """The checked type of an annotation: ``tuple[...]`` -> ``tuple``, others unchanged."""
    return tuple if get_origin(typ) is tuple or typ is tuple else typ


def check_value(value: Any, typ: Any, meta: Mapping[str, Any], where: str,
                err: Callable[[str], Exception]) -> Any:
    """``value`` checked against ``typ`` and ``meta``; returns it (ints become floats for
    ``float`` keys, lists tuples). Raises ``err(f"{where} must be ...")`` otherwise."""
    if typ is bool:
        if not isinstance(value, bool):
            raise err(f"{where} must be true or false, got {value!r}")
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise err(f"{where} must be an integer, got {value!r}")
    elif typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise err(f"{where} must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise err(f"{where} must be finite, got {value!r}")
    elif typ is str:
        if not isinstance(value, str):
            raise err(f"{where} must be a string, got {value!r}")
    elif typ is tuple:
        if not isinstance(value, (list, tuple)) or not value:
            raise err(f"{where} must be a non-empty list of numbers, got {value!r}")
        n = meta.get("length")
        if n is not None and len(value) != n:
            raise err(f"{where} must have {n} elements, got {len(value)}")
        return tuple(check_value(v, float, meta, f"{where}[{i}]", err) for i, v in enumerate(value))
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        raise err(f"{where} must be one of {', '.join(map(repr, choices))}, got {value!r}")
    lo, hi = meta.get("lo"), meta.get("hi")
    below = lo is not None and (value <= lo if meta.get("lo_open") else value < lo)
    above = hi is not None and (value >= hi if meta.get("hi_open") else value > hi)
    if below or above:
        raise err(f"{where} must be {range_text(meta)}, got {value!r}")
    return value


def field_types(cls: type) -> dict[str, Any]:
    """Checked type (:func:`normalise_type`) of every field of dataclass ``cls``."""
    hints = get_type_hints(cls)
    return {f.name: normalise_type(hints[f.name]) for f in dataclasses.fields(cls)}


def validate_instance(
    instance: Any,
    section: str,
    meta: Callable[[dataclasses.Field], Mapping[str, Any]] = lambda f: f.metadata,
) -> None:
    """Check every field of a (frozen) dataclass instance: type and range from ``meta(field)``
    (default: the field's own metadata); ints given for ``float`` keys become floats. Raises
    ``ConfigError("[section] key: must be ...")``."""
    from granite.errors import ConfigError

    types = field_types(type(instance))
    for f in dataclasses.fields(instance):
        current = getattr(instance, f.name)
        value = check_value(current, types[f.name], dict(meta(f)), f"[{section}] {f.name}:",
                            ConfigError)
        if value is not current:
            object.__setattr__(instance, f.name, value)


def check_table(
    cls: type,
    table: Any,
    err: Callable[[str], Exception],
    where: Callable[[str], str],
    unknown: Callable[[str, str], str],
    name: str,
    meta: Callable[[dataclasses.Field], Mapping[str, Any]] = lambda f: f.metadata,
    skip: tuple = (),
) -> dict[str, Any]:
    """The checked keyword arguments of dataclass ``cls`` given in the TOML ``table``.

    ``where(key)`` labels a key in value messages, ``unknown(key, known_keys)`` is the message
    for a key ``cls`` does not have, ``name`` the table's name in "[name] must be a table";
    ``meta(field)`` gives a field's validation metadata (default: the field's own).
    """
    if not isinstance(table, dict):
        raise err(f"[{name}] must be a table")
    types = field_types(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name not in skip}
    kwargs = {}
    for key, value in table.items():
        if key not in fields:
            raise err(unknown(key, ", ".join(sorted(fields))))
        kwargs[key] = check_value(value, types[key], dict(meta(fields[key])), where(key), err)
    return kwargs


def build_dataclass(cls: type, table: Any, err: Callable[[str], Exception], **options: Any) -> Any:
    """``cls(**table)`` after :func:`check_table` (same options)."""
    return cls(**check_table(cls, table, err, **options))


def toml_value(value: Any) -> str:
    """``value`` (bool, int, float, str or a list of them) written as a TOML value."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a JSON string is a valid TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def resolve_bundled_toml(name_or_path: str | Path, folder: Path, kind: str) -> Path:
    """A path to an existing ``.toml`` file, or the name of a bundled one (``folder/NAME.toml``);
    otherwise a :class:`granite.errors.ConfigError` naming the bundled ``kind`` files."""
    from granite.errors import ConfigError

    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.is_file():
            raise ConfigError(f"{p}: {kind} file not found")
        return p
    bundled = folder / f"{p.name}.toml"
    if not bundled.is_file():
        names = ", ".join(sorted(q.stem for q in folder.glob("*.toml")))
        raise ConfigError(f"{name_or_path}: no such {kind} file or bundled {kind} ({names})")
    return bundled


def read_toml_file(path: Path, what: str) -> dict:
    """The decoded TOML file ``path``; an unreadable or invalid file is one
    :class:`granite.errors.ConfigError` line (``what``: e.g. "scenario", for the message)."""
    import tomllib

    from granite.errors import ConfigError

    try:
        return tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: invalid TOML: {error}") from None
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path}: cannot read {what}: {error}") from None
