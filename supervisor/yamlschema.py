"""Strict YAML loading and a small typed reader for schema validation.

`load_yaml` reads YAML 1.2 core-schema scalars (only `true`/`false` are booleans,
only `0o17` is octal, no sexagesimal numbers), rejects duplicate keys, and refuses
what a hostile or careless file could do to the reader: files that are not regular
files or larger than `MAX_BYTES`, nesting deeper than `MAX_DEPTH`, and aliases that
expand to more than `MAX_NODES` nodes (a "billion laughs"). Plain scalars that
YAML 1.1 reads differently (`020` = 16, `1:00` = 60, `no` = false) become
`Ambiguous` strings: a string field takes them as written, a number or boolean field
rejects them with the key and the reason, so a threshold means what it says.
`Node` walks a mapping, converting each value exactly once and raising
`ConfigError(file, "dotted.key", expectation)` on anything unexpected; calling
`Node.done()` rejects keys nobody asked for. Downstream code only ever sees the
frozen objects built from a `Node`, never raw dicts.
"""

from __future__ import annotations

import math
import os
import re
import stat
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from supervisor.errors import ConfigError

MAX_BYTES = 1 << 20  # configs, scenes and motion files are a few kB
MAX_DEPTH = 64  # nesting levels, counted after alias expansion
MAX_NODES = 100_000  # nodes after alias expansion

_STR = "tag:yaml.org,2002:str"
_INT = "tag:yaml.org,2002:int"
_FLOAT = "tag:yaml.org,2002:float"
_BOOL = "tag:yaml.org,2002:bool"
_NULL = "tag:yaml.org,2002:null"
_INT_RE = re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$")
_FLOAT_RE = re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
                       r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$")
_BOOL_VALUES = {"true": True, "True": True, "TRUE": True, "false": False, "False": False, "FALSE": False}
_MAX_INT_DIGITS = 30


class Ambiguous(str):
    """A plain scalar that YAML 1.1 and YAML 1.2 read differently; `reason` says how."""

    reason: str

    def __new__(cls, value: str, reason: str) -> Ambiguous:
        self = super().__new__(cls, value)
        self.reason = reason
        return self

    def __reduce__(self):
        return Ambiguous, (str(self), self.reason)


class _Core12Resolver(yaml.resolver.BaseResolver):
    """The YAML 1.2 core schema's implicit tags (PyYAML implements YAML 1.1's)."""


_Core12Resolver.yaml_implicit_resolvers = {}
for _tag, _regexp, _first in (
    (_BOOL, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), "tTfF"),
    (_INT, _INT_RE, "-+0123456789"),
    (_FLOAT, _FLOAT_RE, "-+0123456789."),
    (_NULL, re.compile(r"^(?:~|null|Null|NULL|)$"), ["~", "n", "N", ""]),
):
    _Core12Resolver.add_implicit_resolver(_tag, _regexp, list(_first))

_YAML11 = yaml.resolver.Resolver()


def _yaml11_reading(value: str, tag12: str) -> str | None:
    """Why the plain scalar `value` is ambiguous between YAML 1.1 and YAML 1.2, or None if it is not."""
    tag11 = _YAML11.resolve(yaml.ScalarNode, value, (True, False))
    leading_zero = tag12 == _INT and re.match(r"^[-+]?0[0-9]", value) is not None
    if tag11 == tag12 and not leading_zero:
        return None
    v11: Any = value
    if tag11 not in (_STR, yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG) and not tag11.endswith(":merge"):
        try:
            v11 = yaml.constructor.SafeConstructor().construct_object(yaml.ScalarNode(tag11, value))
        except (yaml.YAMLError, ValueError, TypeError, OverflowError):
            v11 = value
    if leading_zero:
        octal = f"as the octal {v11}" if isinstance(v11, int) else "as a string"
        return (f"{value!r} is ambiguous: YAML 1.1 reads it {octal}, YAML 1.2 as {int(value, 10)}; "
                f"write it without leading zeros (or as 0o... for octal)")
    if isinstance(v11, str):
        return None
    kind = {bool: "boolean", int: "integer", float: "number"}.get(type(v11), type(v11).__name__)
    shown = str(v11).lower() if isinstance(v11, bool) else str(v11)
    fix = "true or false for a boolean" if isinstance(v11, bool) else f"{shown} for the {kind}"
    return f"{value!r} is the {kind} {shown} in YAML 1.1 but a string in YAML 1.2; write {fix}, or quote a string"


class _StrictLoader(yaml.reader.Reader, yaml.scanner.Scanner, yaml.parser.Parser, yaml.composer.Composer,
                    yaml.constructor.SafeConstructor, _Core12Resolver):
    """A safe loader with YAML 1.2 core scalars, no duplicate keys and a bounded depth."""

    def __init__(self, stream: str) -> None:
        yaml.reader.Reader.__init__(self, stream)
        yaml.scanner.Scanner.__init__(self)
        yaml.parser.Parser.__init__(self)
        yaml.composer.Composer.__init__(self)
        yaml.constructor.SafeConstructor.__init__(self)
        _Core12Resolver.__init__(self)
        self._depth = 0

    def compose_node(self, parent, index):
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise yaml.composer.ComposerError(None, None, f"nested deeper than {MAX_DEPTH} levels",
                                                  self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _mark_error(problem: str, node: yaml.Node) -> yaml.constructor.ConstructorError:
    return yaml.constructor.ConstructorError(None, None, problem, node.start_mark)


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    mapping: dict = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            hash(key)
        except TypeError:
            raise _mark_error(f"a mapping key must be a scalar, got a {type(key).__name__}", key_node) from None
        if key in mapping:
            raise _mark_error(f"duplicate key {_type_name(key, bare=True)} (line {key_node.start_mark.line + 1})",
                              key_node)
        mapping[key] = loader.construct_object(value_node, deep=deep)
    return mapping


def _construct_str(loader: _StrictLoader, node: yaml.ScalarNode) -> str:
    value = loader.construct_scalar(node)
    if node.style is None:  # plain: the only style YAML 1.1 resolves implicitly
        reason = _yaml11_reading(value, _STR)
        if reason:
            return Ambiguous(value, reason)
    return value


def _construct_int(loader: _StrictLoader, node: yaml.ScalarNode) -> int | Ambiguous:
    value = loader.construct_scalar(node)
    if not _INT_RE.match(value):
        raise _mark_error(f"{_type_name(value, bare=True)} is not a YAML 1.2 integer", node)
    if len(value) > _MAX_INT_DIGITS:
        raise _mark_error(f"integer with more than {_MAX_INT_DIGITS} digits", node)
    reason = _yaml11_reading(value, _INT)
    if reason:
        return Ambiguous(value, reason)
    if value.startswith(("0o", "0x")):
        return int(value[2:], 8 if value[1] == "o" else 16)
    return int(value, 10)


def _construct_float(loader: _StrictLoader, node: yaml.ScalarNode) -> float:
    value = loader.construct_scalar(node)
    if not (_FLOAT_RE.match(value) or _INT_RE.match(value)) or len(value) > 100:
        raise _mark_error(f"{_type_name(value, bare=True)} is not a YAML 1.2 number", node)
    low = value.lower()
    if low.endswith(".inf"):
        return -math.inf if low.startswith("-") else math.inf
    if low == ".nan":
        return math.nan
    return float(int(value, 0) if value.startswith(("0o", "0x")) else value)


def _construct_bool(loader: _StrictLoader, node: yaml.ScalarNode) -> bool:
    value = loader.construct_scalar(node)
    if value not in _BOOL_VALUES:
        raise _mark_error(f"{_type_name(value, bare=True)} is not a YAML 1.2 boolean (true or false)", node)
    return _BOOL_VALUES[value]


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_StrictLoader.add_constructor(_STR, _construct_str)
_StrictLoader.add_constructor(_INT, _construct_int)
_StrictLoader.add_constructor(_FLOAT, _construct_float)
_StrictLoader.add_constructor(_BOOL, _construct_bool)


def _check_expansion(root: yaml.Node) -> None:
    """Refuse a document whose aliases expand beyond MAX_NODES nodes or MAX_DEPTH levels, or loop."""
    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]

    def kids(node: yaml.Node) -> list[yaml.Node]:
        if isinstance(node, yaml.SequenceNode):
            return list(node.value)
        if isinstance(node, yaml.MappingNode):
            return [n for pair in node.value for n in pair]
        return []

    while stack:
        node, finished = stack.pop()
        nid = id(node)
        if finished:
            children = kids(node)
            size[nid] = 1 + sum(size[id(k)] for k in children)
            depth[nid] = 1 + max((depth[id(k)] for k in children), default=0)
            path.discard(nid)
            if size[nid] > MAX_NODES:
                raise _mark_error(f"aliases expand to more than {MAX_NODES} nodes", node)
            if depth[nid] > MAX_DEPTH:
                raise _mark_error(f"aliases nest deeper than {MAX_DEPTH} levels", node)
            continue
        if nid in size:
            continue
        path.add(nid)
        stack.append((node, True))
        for k in kids(node):
            if id(k) in path:
                raise _mark_error("an alias refers to the node that contains it (a recursive structure)", k)
            if id(k) not in size:
                stack.append((k, False))


def _describe_yaml_error(exc: yaml.YAMLError) -> str:
    """The parser's problem and position, without the snippet of the file it quotes."""
    if isinstance(exc, yaml.MarkedYAMLError):
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = exc.problem or exc.context or "malformed"
        context = f" ({exc.context})" if exc.context and exc.problem else ""
        return f"invalid YAML{where}: {problem}{context}"
    if isinstance(exc, yaml.reader.ReaderError):
        return f"invalid YAML: {exc.reason} at character {exc.position}"
    return f"invalid YAML: {type(exc).__name__}"


def load_yaml_text(text: str, file: str | Path | None = None) -> Any:
    """Parse YAML text (see the module docstring); errors name the file, never quote its content."""
    loader = None
    try:
        loader = _StrictLoader(text)  # the reader checks for unprintable characters here
        node = loader.get_single_node()
        if node is None:
            return None
        _check_expansion(node)
        return loader.construct_document(node)
    except yaml.YAMLError as exc:
        raise ConfigError(file, "", _describe_yaml_error(exc)) from exc
    except RecursionError as exc:  # belt and braces: MAX_DEPTH keeps every walk shallow
        raise ConfigError(file, "", "invalid YAML: nested too deeply") from exc
    finally:
        if loader is not None:
            loader.dispose()


def read_bounded(path: str | Path, limit: int = MAX_BYTES, what: str = "file") -> bytes:
    """The bytes of a regular file of at most `limit` bytes; a FIFO, device or directory is refused
    before it is opened for reading (a FIFO would block, /dev/zero would never end)."""
    path = Path(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(path, "", f"cannot read {what}: {_file_kind(st.st_mode)}, not a regular file")
        if st.st_size > limit:
            raise ConfigError(path, "", f"cannot read {what}: {st.st_size} bytes, more than the "
                                        f"{limit} byte limit")
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
        with os.fdopen(fd, "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):  # swapped since the stat
                raise ConfigError(path, "", f"cannot read {what}: not a regular file")
            data = fh.read(limit + 1)
    except OSError as exc:
        raise ConfigError(path, "", f"cannot read {what}: {exc.strerror or exc}") from exc
    if len(data) > limit:
        raise ConfigError(path, "", f"cannot read {what}: more than the {limit} byte limit")
    return data


def _file_kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "a special file"


def decode_text(raw: bytes, file: str | Path) -> str:
    """UTF-8 text of a file's bytes, or a ConfigError naming the file."""
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(file, "", f"not UTF-8 text (byte {exc.start})") from exc


def load_yaml(path: str | Path) -> Any:
    """Read (bounded, see `read_bounded`) and parse a YAML file (see `load_yaml_text`)."""
    return load_yaml_text(decode_text(read_bounded(path), path), path)


_MISSING = object()


def _type_name(value: Any, bare: bool = False) -> str:
    """A short description of a YAML value for an error message: never the whole of a structure.

    `bare`: just the (shortened) repr of a string, for messages that already say what it is."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"boolean {str(value).lower()}"
    if isinstance(value, str):
        text = repr(str(value)) if len(value) <= 40 else f"{str(value)[:37]!r}... ({len(value)} characters)"
        return text if bare else f"str {text}"
    if isinstance(value, (int, float)):
        return f"{type(value).__name__} {value!r}" if abs(value) < 1e30 or not math.isfinite(value) \
            else f"{type(value).__name__} {value:.3g}"
    if isinstance(value, (list, tuple)):
        return f"a list of {len(value)} items"
    if isinstance(value, dict):
        return f"a mapping of {len(value)} keys"
    return f"a {type(value).__name__}"


def _kind_name(value: Any) -> str:
    """What a value is, without any of its content (for the top of a file that is not a mapping)."""
    if isinstance(value, str):
        return f"a string of {len(value)} characters"
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return "a number"
    return _type_name(value)


class Node:
    """A typed view on one YAML mapping, tracking which keys were read."""

    def __init__(self, data: Any, file: str | Path | None = None, path: str = "") -> None:
        self.file = str(file) if file is not None else None
        self.path = path
        if data is None:
            data = {}
        if not isinstance(data, dict):
            if not path:  # the whole file: describe it without quoting it
                raise ConfigError(self.file, "", f"expected a mapping (key: value lines) at the top of the file, "
                                                 f"got {_kind_name(data)}")
            raise ConfigError(self.file, path, f"expected a mapping, got {_type_name(data)}")
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

    def optional_number(self, key: str, *, min: float | None = None, max: float | None = None,
                        min_exclusive: bool = False) -> float | None:
        """Like `number`, but an absent key (or null) is None."""
        if self.data.get(key) is None:
            self._seen.add(key)
            return None
        return self.number(key, min=min, max=max, min_exclusive=min_exclusive)

    def integer(self, key: str, default: Any = _MISSING, *, min: int | None = None, max: int | None = None) -> int:
        value = self._get(key, default)
        if isinstance(value, Ambiguous):
            raise self.error(key, f"expected an integer: {value.reason}")
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, got {_type_name(value)}")
        if min is not None and value < min:
            raise self.error(key, f"must be >= {min}, got {value}")
        if max is not None and value > max:
            raise self.error(key, f"must be <= {max}, got {value}")
        return int(value)

    def boolean(self, key: str, default: Any = _MISSING) -> bool:
        value = self._get(key, default)
        if isinstance(value, Ambiguous):
            raise self.error(key, f"expected true or false: {value.reason}")
        if not isinstance(value, bool):
            raise self.error(key, f"expected true or false, got {_type_name(value)}")
        return value

    def string(self, key: str, default: Any = _MISSING, *, choices: Sequence[str] | None = None) -> str:
        value = self._get(key, default)
        if not isinstance(value, str) or not value:
            raise self.error(key, f"expected a non-empty string, got {_type_name(value)}")
        if choices is not None and value not in choices:
            raise self.error(key, f"expected one of {', '.join(sorted(choices))}, got {_type_name(value, bare=True)}")
        return str(value)

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

    def mappings(self, key: str) -> list[Node]:
        """The list of mappings under `key` as Nodes (`key[0]`, `key[1]`, ...); absent or null: no entries."""
        value = self._get(key, None)
        if value is None:
            return []
        if not isinstance(value, list):
            raise self.error(key, f"expected a list of mappings, got {_type_name(value)}")
        return [Node(v, self.file, f"{self._key(key)}[{i}]") for i, v in enumerate(value)]

    def done(self) -> None:
        """Reject keys that no reader asked for."""
        unknown = [k for k in self.data if k not in self._seen]
        if unknown:
            expected = ", ".join(sorted(self._seen)) or "no keys"
            raise self.error(unknown[0], f"unknown key (expected one of: {expected})")


def _check_number(value: Any, error, key: str, min: float | None, max: float | None, min_exclusive: bool) -> float:
    if isinstance(value, Ambiguous):
        raise error(key, f"expected a number: {value.reason}")
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
