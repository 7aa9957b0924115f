"""Strict YAML loading and a small typed reader for schema validation.

`load_yaml` uses `yaml.safe_load` semantics but rejects duplicate keys.
`Node` walks a mapping, converting each value exactly once and raising
`ConfigError(file, "dotted.key", expectation)` on anything unexpected; calling
`Node.done()` rejects keys nobody asked for. Downstream code only ever sees the
frozen objects built from a `Node`, never raw dicts.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from supervisor.errors import ConfigError


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate mapping keys."""


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    loader.flatten_mapping(node)
    mapping: dict = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in mapping:
            mark = key_node.start_mark
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (line {mark.line + 1})", mark
            )
        mapping[key] = loader.construct_object(value_node, deep=deep)
    return mapping


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def load_yaml_text(text: str, file: str | Path | None = None) -> Any:
    """Parse YAML text, rejecting duplicate keys; errors name the file."""
    try:
        return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - SafeLoader subclass
    except yaml.YAMLError as exc:
        raise ConfigError(file, "", f"invalid YAML: {exc}") from exc


def load_yaml(path: str | Path) -> Any:
    """Read and parse a YAML file, rejecting duplicate keys."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(path, "", f"cannot read file: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(path, "", f"not UTF-8 text: {exc}") from exc
    return load_yaml_text(text, path)


_MISSING = object()


def _type_name(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"boolean {value}"
    return f"{type(value).__name__} {value!r}"


class Node:
    """A typed view on one YAML mapping, tracking which keys were read."""

    def __init__(self, data: Any, file: str | Path | None = None, path: str = "") -> None:
        self.file = str(file) if file is not None else None
        self.path = path
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(self.file, path or "<root>", f"expected a mapping, got {_type_name(data)}")
        for key in data:
            if not isinstance(key, str):
                raise ConfigError(self.file, self._key(str(key)), f"keys must be strings, got {_type_name(key)}")
        self.data: dict[str, Any] = data
        self._seen: set[str] = set()

    # -- helpers -----------------------------------------------------------
    def _key(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def error(self, key: str, problem: str) -> ConfigError:
        """A ConfigError for `key` under this node."""
        return ConfigError(self.file, self._key(key), problem)

    def has(self, key: str) -> bool:
        return key in self.data

    def is_null(self, key: str) -> bool:
        """True when `key` is absent or null (and marks it read, for optional keys)."""
        self._seen.add(key)
        return self.data.get(key) is None

    def keys(self) -> list[str]:
        return list(self.data)

    def _get(self, key: str, default: Any) -> Any:
        self._seen.add(key)
        if key in self.data:
            return self.data[key]
        if default is _MISSING:
            raise self.error(key, "required key is missing")
        return default

    # -- scalars -----------------------------------------------------------
    def number(
        self,
        key: str,
        default: Any = _MISSING,
        *,
        min: float | None = None,
        max: float | None = None,
        min_exclusive: bool = False,
    ) -> float:
        """A finite real number within [min, max] (or (min, max] if min_exclusive)."""
        value = self._get(key, default)
        return _check_number(value, self.error, key, min, max, min_exclusive)

    def integer(self, key: str, default: Any = _MISSING, *, min: int | None = None, max: int | None = None) -> int:
        value = self._get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, got {_type_name(value)}")
        if min is not None and value < min:
            raise self.error(key, f"must be >= {min}, got {value}")
        if max is not None and value > max:
            raise self.error(key, f"must be <= {max}, got {value}")
        return int(value)

    def boolean(self, key: str, default: Any = _MISSING) -> bool:
        value = self._get(key, default)
        if not isinstance(value, bool):
            raise self.error(key, f"expected true or false, got {_type_name(value)}")
        return value

    def string(self, key: str, default: Any = _MISSING, *, choices: Sequence[str] | None = None) -> str:
        value = self._get(key, default)
        if not isinstance(value, str) or not value:
            raise self.error(key, f"expected a non-empty string, got {_type_name(value)}")
        if choices is not None and value not in choices:
            raise self.error(key, f"expected one of {', '.join(sorted(choices))}, got {value!r}")
        return value

    def optional_string(self, key: str) -> str | None:
        if self.data.get(key) is None:
            self._seen.add(key)
            return None
        return self.string(key)

    def vector(
        self,
        key: str,
        length: int,
        default: Any = _MISSING,
        *,
        min: float | None = None,
        max: float | None = None,
    ) -> np.ndarray:
        """A list of `length` finite numbers, returned as a read-only float array."""
        value = self._get(key, default)
        if not isinstance(value, (list, tuple)) or len(value) != length:
            raise self.error(key, f"expected a list of {length} numbers, got {_type_name(value)}")
        out = np.array(
            [_check_number(v, lambda _k, p: self.error(f"{key}[{i}]", p), key, min, max, False) for i, v in enumerate(value)],
            dtype=float,
        )
        out.setflags(write=False)
        return out

    def number_list(self, key: str, default: Any = _MISSING, *, min: float | None = None, max: float | None = None,
                    min_length: int = 1) -> tuple[float, ...]:
        value = self._get(key, default)
        if not isinstance(value, (list, tuple)) or len(value) < min_length:
            raise self.error(key, f"expected a list of at least {min_length} numbers, got {_type_name(value)}")
        return tuple(
            _check_number(v, lambda _k, p, i=i: self.error(f"{key}[{i}]", p), key, min, max, False)
            for i, v in enumerate(value)
        )

    # -- structure ---------------------------------------------------------
    def child(self, key: str, default: Any = _MISSING) -> Node:
        """The mapping under `key` as a Node (an absent optional child is an empty mapping)."""
        value = self._get(key, default)
        return Node(value, self.file, self._key(key))

    def children(self, key: str) -> Iterator[tuple[str, Node]]:
        """(name, Node) for each entry of the mapping under `key`."""
        parent = self.child(key)
        for name in parent.keys():
            parent._seen.add(name)
            yield name, parent.child(name)

    def done(self) -> None:
        """Reject keys that no reader asked for."""
        unknown = [k for k in self.data if k not in self._seen]
        if unknown:
            expected = ", ".join(sorted(self._seen)) or "no keys"
            raise self.error(unknown[0], f"unknown key (expected one of: {expected})")


def _check_number(value: Any, error, key: str, min: float | None, max: float | None, min_exclusive: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise error(key, f"expected a number, got {_type_name(value)}")
    value = float(value)
    if not math.isfinite(value):
        raise error(key, f"must be a finite number, got {value}")
    if min is not None and (value <= min if min_exclusive else value < min):
        raise error(key, f"must be {'>' if min_exclusive else '>='} {min:g}, got {value:g}")
    if max is not None and value > max:
        raise error(key, f"must be <= {max:g}, got {value:g}")
    return value
