"""One config mechanism for every job (train, distill, adapt): a dataclass holds the defaults, a
JSON file given with --config overrides some of them, and each --set NAME=VALUE overrides one
field of that (dotted names reach nested configs: segment.weights, model.width)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


def _nested(cls) -> dict[str, type]:
    """Fields of a config dataclass that are config dataclasses themselves."""
    out = {}
    for f in dataclasses.fields(cls):
        if f.default_factory is not dataclasses.MISSING:
            v = f.default_factory()
            if dataclasses.is_dataclass(v):
                out[f.name] = type(v)
    return out


def from_dict(cls: type[T], d: dict, where: str = "config") -> T:
    """cls(**d) with nested configs built too; an unknown field is an error that names the known ones."""
    if not isinstance(d, dict):
        raise ValueError(f"{where} must be a JSON object of fields, got {type(d).__name__}")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f"{where}: unknown fields {unknown}; known: {sorted(known)}")
    d = dict(d)
    for name, sub in _nested(cls).items():
        if name in d:
            d[name] = from_dict(sub, d[name], f"{where}.{name}")
    return cls(**d)


def apply_sets(d: dict, sets: list[str] | None) -> dict:
    """--set NAME=VALUE over a config dict (VALUE read as JSON, else as text; NAME may be dotted for
    a nested field, e.g. segment.mirror=false)."""
    for item in sets or []:
        name, eq, value = item.partition("=")
        if not eq or not name:
            raise ValueError(f"--set takes NAME=VALUE, got {item!r}")
        try:
            v = json.loads(value)
        except json.JSONDecodeError:
            v = value
        *path, last = name.split(".")
        node = d
        for p in path:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ValueError(f"--set {item!r}: {p} is not a nested config")
        node[last] = v
    return d


def load(cls: type[T], path: str | Path | None = None, sets: list[str] | None = None) -> T:
    """The config of a job: cls's defaults, then the JSON file at path, then the --set items."""
    d = {}
    if path:
        try:
            d = json.loads(Path(path).read_text())
        except OSError as e:
            raise FileNotFoundError(f"{path}: cannot read the config ({e.strerror}); configs/ holds the shipped ones") from None
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not valid JSON ({e}); fix the file") from None
    return from_dict(cls, apply_sets(d, sets), str(path or cls.__name__))
