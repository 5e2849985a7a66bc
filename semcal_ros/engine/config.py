"""Parameters: dataclasses with defaults, filled from ROS parameter YAML files.

One file format serves both doors: ``config/*.yaml`` are ROS 2 parameter files
(``node_name: {ros__parameters: {...}}``), read by ``ros2 run ... --params-file`` and by the
``semcal`` command's ``--config``. Nested groups become dotted names, as ROS flattens them.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, TypeVar

import yaml

from semcal_ros.errors import UnknownParameter

T = TypeVar("T")


def flatten(data: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out


def load_node_params(path: str | Path, node_name: str) -> dict[str, Any]:
    """Flat parameters for ``node_name`` from a ROS 2 parameter file (``/**`` applies to all)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"parameter file not found: {path}")
    data = yaml.safe_load(path.read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a ROS 2 parameter file (a mapping)")
    out: dict[str, Any] = {}
    for key in ("/**", node_name, "/" + node_name):
        section = data.get(key)
        if isinstance(section, dict):
            out.update(flatten(section.get("ros__parameters", {}) or {}))
    return out


def load_node_group(path: str | Path, node_name: str, group: str) -> dict[str, Any]:
    """The flat parameters of ``node_name``'s ``group:`` (e.g. ``mapping``, ``geometric``) in a
    ROS 2 parameter file, named as inside the group (the ``group.`` prefix taken off)."""
    prefix = group + "."
    return {k[len(prefix):]: v for k, v in load_node_params(path, node_name).items()
            if k.startswith(prefix)}


def dataclass_fields_flat(obj: Any, prefix: str = "") -> dict[str, Any]:
    """The flat (dotted) parameter names and values of a (nested) dataclass instance."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            out.update(dataclass_fields_flat(value, f"{prefix}{f.name}."))
        else:
            out[f"{prefix}{f.name}"] = value
    return out


def apply_flat(obj: T, flat: dict[str, Any], strict: bool = True) -> T:
    """A copy of the dataclass ``obj`` with dotted ``flat`` values applied (types coerced)."""
    known = dataclass_fields_flat(obj)
    unknown = sorted(set(flat) - set(known))
    if strict and unknown:
        raise UnknownParameter(f"unknown parameter(s): {', '.join(unknown)}")
    return _apply(obj, {k: v for k, v in flat.items() if k in known}, "")


def _apply(obj: Any, flat: dict[str, Any], prefix: str) -> Any:
    changes = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        name = prefix + f.name
        if dataclasses.is_dataclass(value):
            changes[f.name] = _apply(value, flat, name + ".")
        elif name in flat:
            changes[f.name] = _coerce(flat[name], value, name)
    return dataclasses.replace(obj, **changes)


def _coerce(new: Any, old: Any, name: str) -> Any:
    try:
        if isinstance(old, bool):
            if isinstance(new, str):
                return new.strip().lower() in ("1", "true", "yes", "on")
            return bool(new)
        if isinstance(old, int):
            return int(new)
        if isinstance(old, float):
            return float(new)
        if isinstance(old, tuple):
            return tuple(type(old[0])(v) for v in new) if old else tuple(new)
        if isinstance(old, str):
            return str(new)
    except (TypeError, ValueError):
        raise ValueError(f"parameter '{name}': cannot use {new!r}") from None
    return new


def check_rule(name: str, value: object, ok: bool, rule: str) -> None:
    """One parameter rule, its failure named: ``schedule.max_evaluations must be >= 1, got ...``"""
    if not ok:
        shown = list(value) if isinstance(value, tuple) else value
        raise ValueError(f"{name} must be {rule}, got {shown}")


def check_finite(params: object) -> None:
    """Every number of a parameter group is finite (NaN passes every < and > check)."""
    for name, value in vars(params).items():
        values = value if isinstance(value, tuple) else (value,)
        for v in values:
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{type(params).__name__.replace('Params', '').lower()}."
                                 f"{name} must be a finite number, got {v}")
