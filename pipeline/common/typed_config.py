"""Typed configuration sections from `params.yaml` mappings.

Each concern declares its section as nested dataclasses whose defaults are the documented values;
`replace_from_mapping` overlays what the user wrote, refusing unknown keys and values of the wrong
type with an error that names the dotted key (e.g. `env.rewards.sigma2.feet_pos`).
"""

from __future__ import annotations

import dataclasses
import types
import typing

from pipeline.common.errors import PipelineInputError


def replace_from_mapping(base, raw, where: str):
    """A copy of dataclass instance `base` (it holds the defaults) with the keys of mapping `raw`
    replaced, recursively, checking keys and scalar types against the field annotations.
    `where` is the dotted params path, e.g. "env", used in every error."""
    cls = type(base)
    if not isinstance(raw, dict):
        raise PipelineInputError(where.split(".")[0], where, f"expected a mapping, got {type(raw).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(raw) - names)
    if unknown:
        raise PipelineInputError(where.split(".")[0], f"{where}.{unknown[0]}", f"unknown key (known: {sorted(names)})")
    kwargs = {}
    for key, value in raw.items():
        kwargs[key] = _convert(hints[key], value, f"{where}.{key}", getattr(base, key))
    return dataclasses.replace(base, **kwargs)


def _convert(hint, value, key: str, default=None):
    source = key.split(".")[0]
    if dataclasses.is_dataclass(hint):
        return replace_from_mapping(default, value, key)
    origin = typing.get_origin(hint)
    if origin is list:
        if not isinstance(value, (list, tuple)):
            raise PipelineInputError(source, key, f"expected a list, got {value!r}")
        (item,) = typing.get_args(hint)
        return [_convert(item, v, f"{key}[{i}]") for i, v in enumerate(value)]
    if origin in (typing.Union, types.UnionType):
        raise PipelineInputError(source, key, "unsupported type")  # none are used
    if hint is bool:
        if not isinstance(value, bool):
            raise PipelineInputError(source, key, f"expected true/false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise PipelineInputError(source, key, f"expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise PipelineInputError(source, key, f"expected a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise PipelineInputError(source, key, f"expected a string, got {value!r}")
        return value
    return value
