"""The whole configuration: typed dataclasses with the papers' values as defaults, loaded from YAML.

Each half keeps its settings in its own dataclass (``vo_core/<half>/config.py``); this module composes
them, reads YAML and ``key=value`` overrides onto them, and dumps the resolved result beside the outputs.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from vo_core.direct.config import DirectConfig
from vo_core.errors import InputError
from vo_core.init.config import InitConfig
from vo_core.klt.config import KltConfig

METHODS = ("fdmo", "direct", "features", "klt")


@dataclass
class DatasetConfig:
    on_bad_image: str = "skip"  # "skip": drop an unreadable image with an event; "abort": stop with an error
    read_ahead: int = 8  # frames decoded ahead on a background thread
    undistort_output: str = "crop"  # DSO's choices: "crop", "full", "none" or "WxH"


@dataclass
class Config:
    method: str = "direct"  # the main job until fdmo lands: DSO-style direct odometry with its window optimization
    seed: int = 0  # every random choice (RANSAC, sampling) draws from generators seeded with this
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    klt: KltConfig = field(default_factory=KltConfig)
    direct: DirectConfig = field(default_factory=DirectConfig)
    init: InitConfig = field(default_factory=InitConfig)


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(value: Any, annotation: Any, key: str) -> Any:
    """Convert a YAML or command-line value to the annotated type, or say which key is wrong."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(annotation) if a is not type(None)]
        if value is None:
            return None
        annotation = options[0]
        origin = typing.get_origin(annotation)
    try:
        if annotation is bool:
            if isinstance(value, str):
                if value.lower() in ("true", "1", "yes", "on"):
                    return True
                if value.lower() in ("false", "0", "no", "off"):
                    return False
                raise ValueError(value)
            return bool(value)
        if annotation in (int, float, str):
            return annotation(value)
        if origin in (list, tuple):
            if isinstance(value, str):
                value = yaml.safe_load(value)
            (item_type, *_) = typing.get_args(annotation) or (Any,)
            items = [v if item_type is Any else _coerce(v, item_type, key) for v in value]
            return tuple(items) if origin is tuple else items
    except (TypeError, ValueError) as exc:
        raise InputError(f"config key '{key}': cannot read {value!r} as {annotation}") from exc
    return value


def _apply(obj: Any, values: dict[str, Any], prefix: str, source: str) -> None:
    hints = _field_types(type(obj))
    for name, value in values.items():
        key = f"{prefix}{name}"
        if name not in hints:
            raise InputError(f"{source}: unknown config key '{key}'")
        current = getattr(obj, name)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise InputError(f"{source}: config key '{key}' is a section, got {value!r}")
            _apply(current, value, key + ".", source)
        else:
            setattr(obj, name, _coerce(value, hints[name], key))


def _validate(config: Config) -> None:
    if config.method not in METHODS:
        raise InputError(f"config key 'method': {config.method!r} is not one of {', '.join(METHODS)}")


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults, then the YAML file, then ``key.sub=value`` overrides (as from ``--set``)."""
    config = Config()
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: config file not found")
        try:
            values = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise InputError(f"{path}: malformed YAML ({str(exc).splitlines()[0]})") from exc
        if not isinstance(values, dict):
            raise InputError(f"{path}: the config must be a mapping of keys to values")
        _apply(config, values, "", str(path))
    for item in overrides or []:
        if "=" not in item:
            raise InputError(f"--set {item}: expected key=value")
        key, raw = item.split("=", 1)
        nested: dict[str, Any] = {}
        cursor = nested
        parts = key.strip().split(".")
        for part in parts[:-1]:
            cursor = cursor.setdefault(part, {})
        cursor[parts[-1]] = yaml.safe_load(raw) if raw.strip() else raw
        _apply(config, nested, "", f"--set {item}")
    _validate(config)
    return config


def config_to_dict(config: Config) -> dict[str, Any]:
    return dataclasses.asdict(config)


def dump_config(config: Config, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(config_to_dict(config), sort_keys=False))
