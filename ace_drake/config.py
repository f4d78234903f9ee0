"""Typed configuration: the YAML loader shared by every domain's frozen-dataclass configs.

Each domain keeps its configs beside its code (``physics/params.py``, ``robot/params.py``,
``perception/params.py``, ``control/params.py``, ``learning/params.py``, ``play/params.py``; see
docs/architecture.md); this module, at the bottom of the layers, only turns YAML into those
dataclasses with errors that name the field, and holds the checks their ``__post_init__`` share.
Defaults are the paper's values (paper, Methods *Simulation*) as completed by the authors'
published code (``../shared/paper/notes.md``); a fitted parameter set is a YAML file in
``models/`` that overrides some of them (``load_config(BallPhysicsParams, path)``).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

T = TypeVar("T")

# The repository's models/ folder: robot, table and camera files, scenario and training YAMLs, and
# the shipped artefacts with their sidecars.
MODELS_DIR = Path(__file__).resolve().parent.parent / "models"
# Measured results the product reads: the held-out evaluations that choose ``ace-drake rally``'s
# controller (``evaluation.controllers.best_controller``), beside the other stored results.
RESULTS_DIR = Path(__file__).resolve().parent.parent / "docs" / "results"


class InputError(ValueError):
    """What the user gave is wrong: a config value, a data or artefact file, a command-line value;
    the message names it and what was expected. The command line reports these (and a missing
    file) as ``error: ...`` with exit status 2; any other exception is a bug and keeps its
    traceback."""


class ConfigError(InputError):
    """A configuration value is missing, misspelt or out of range; the message names the field."""


def require_latency_interval(config: Any) -> None:
    if not config.latency_min <= config.latency_max:
        raise ConfigError(f"latency_min ({config.latency_min} s) must be <= latency_max ({config.latency_max} s)")


def require_probability(config: Any, name: str, allow_one: bool) -> None:
    value = getattr(config, name)
    if not (0.0 <= value < 1.0 or (allow_one and value == 1.0)):
        raise ConfigError(f"{name} must be in [0, {'1]' if allow_one else '1)'}, got {value}")


def from_dict(cls: type[T], data: Any, path: str = "") -> T:
    """Builds dataclass ``cls`` from a nested dict, checking names and types.

    Missing fields keep their defaults; unknown fields, wrong types and values rejected by a
    dataclass's own checks raise ConfigError naming the dotted field (``aero.drag_coefficient``).
    """
    where = path or cls.__name__
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown field(s) {unknown}; expected some of {sorted(fields)}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _coerce(hints[name], value, f"{path}.{name}" if path else name)
    try:
        return cls(**kwargs)
    except ConfigError as error:
        raise ConfigError(f"{where}: {error}") from None


def load_config(cls: type[T], path: str | Path, section: str | None = None) -> T:
    """Loads dataclass ``cls`` from a YAML file (optionally from one top-level ``section``), its
    ``base:`` composed first (``load_yaml``)."""
    path = Path(path)
    data = load_yaml(path)
    if section is not None:
        if not isinstance(data, dict) or section not in data:
            raise ConfigError(f"{path}: no top-level section '{section}'")
        data = data[section]
    try:
        return from_dict(cls, data)
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None


def load_yaml(path: str | Path) -> Any:
    """The data of a YAML file with its top-level ``base:`` composed: ``base: other.yaml`` (a path
    relative to this file) names a file whose mapping, itself composed the same way, this file's
    mapping is deep-merged over (``merge``). So a config can be written as another with some fields
    changed. Raises ConfigError naming the file for a missing or invalid file, a ``base`` that is
    not a file name or a mapping, and a cycle of bases."""
    return _load_composed(Path(path), ())


def merge(base: dict, overrides: dict) -> dict:
    """``overrides`` deep-merged over ``base`` (neither is changed): mappings merge key by key;
    any other value, a list included, replaces the base's."""
    merged = dict(base)
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def _load_composed(path: Path, including: tuple[Path, ...]) -> Any:
    if path.resolve() in including:
        chain = " -> ".join(str(p) for p in (*including, path.resolve()))
        raise ConfigError(f"{path}: a cycle of base: files ({chain})")
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}" + (f" (the base of {including[-1]})" if including else ""))
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {error}") from None
    if not isinstance(data, dict) or "base" not in data:
        return data
    data = dict(data)
    base = data.pop("base")
    if not isinstance(base, str) or not base:
        raise ConfigError(f"{path}: base: expected a YAML file's name (relative to this file), got {base!r}")
    base_data = _load_composed(path.parent / base, (*including, path.resolve()))
    if base_data is None:
        base_data = {}
    if not isinstance(base_data, dict):
        raise ConfigError(f"{path.parent / base}: expected a mapping (the base of {path}), got {type(base_data).__name__}")
    return merge(base_data, data)


def to_dict(config: Any) -> dict:
    """The plain-dict (YAML-ready) form of a config dataclass."""
    return dataclasses.asdict(config)


def _coerce(hint: Any, value: Any, name: str) -> Any:
    if dataclasses.is_dataclass(hint):
        return from_dict(hint, value, name)
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(hint)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _coerce(option, value, name)
            except ConfigError as error:
                errors.append(str(error))
        raise ConfigError("; ".join(errors))
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{name}: expected true or false, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{name}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{name}: expected a finite number, got {value!r}")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{name}: expected an integer, got {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{name}: expected a string, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{name}: expected a list, got {value!r}")
        (item,) = typing.get_args(hint)[:1]
        return tuple(_coerce(item, v, f"{name}[{i}]") for i, v in enumerate(value))
    return value


def require_positive(config: Any, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        if not value > 0:
            raise ConfigError(f"{name} must be > 0, got {value}")


def require_non_negative(config: Any, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        if not value >= 0:
            raise ConfigError(f"{name} must be >= 0, got {value}")
