"""Reading configs: YAML with limits, plain values converted to typed, frozen dataclasses.

YAML is plain data, read with ``yaml.safe_load``'s loader under limits that make any file,
however hostile, cheap to read. :func:`from_dict` builds a config dataclass from it: unknown
keys, wrong types, non-finite and out-of-range values are errors that name the key and the
allowed range. The sections themselves are defined elsewhere (:mod:`lfm_env.config.world`,
each world's ``config.py``, :mod:`controllers.config`); what a whole file holds is read
above this layer (:func:`controllers.config.load_config`).
"""

from __future__ import annotations

import dataclasses
import functools
import io
import math
import os
import reprlib
import types
import typing
import warnings
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is unknown, of the wrong type or out of range."""


_REPR = reprlib.Repr()
_REPR.maxlevel = 3  # nested lists shown this deep ...
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 8  # ... this wide
_REPR.maxstring = _REPR.maxlong = _REPR.maxother = 100


def _show(value: Any, limit: int = 80) -> str:
    """A short ``repr(value)`` for an error message, cut to ``limit`` characters; never raises.

    Bounded in time and memory whatever the value: containers are shown at most 3 levels
    deep and 8 items wide (a YAML alias bomb expands to billions of items, whose full
    repr takes minutes and gigabytes); an integer beyond ``sys.get_int_max_str_digits()``
    has no repr (ValueError), and a megabyte-long string would drown the message.
    """
    try:
        text = _REPR.repr(value)
    except (ValueError, RecursionError):
        if isinstance(value, int):
            return f"<an integer of about {round(value.bit_length() * math.log10(2))} digits>"
        return f"<a {type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _key(key: Any) -> str:
    """A mapping key as text for an error message, shortened like :func:`_show`."""
    text = key if isinstance(key, str) else _show(key)
    return text if len(text) <= 80 else text[:77] + "..."


# --------------------------------------------------------------------------- loading


def _check_unique_keys(root: yaml.Node | None) -> None:
    """Raise a YAML error for a key written twice in one mapping.

    YAML requires unique keys, but PyYAML keeps the last value silently, so a repeated
    key (a typo's twin) would pass unnoticed. Works on the composed node graph, which
    shares aliased nodes, so each node is visited once.
    """
    seen: set[int] = set()
    todo = [] if root is None else [root]
    while todo:
        node = todo.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            keys: set[tuple[str, str]] = set()
            for key, value in node.value:
                if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                    if (key.tag, key.value) in keys:
                        raise yaml.constructor.ConstructorError(
                            "while reading a mapping",
                            node.start_mark,
                            f"found the key {_key(key.value)!r} twice",
                            key.start_mark,
                        )
                    keys.add((key.tag, key.value))
                todo += [key, value]
        elif isinstance(node, yaml.SequenceNode):
            todo += node.value


#: Limits of a config file: its size [bytes], the nesting depth of its lists and mappings,
#: and the number of values it expands to once its aliases are followed. Real configs are
#: a few kB, 3 levels deep and a few hundred values; the limits make the reading of any
#: file, however hostile, take well under a second and a few MB.
MAX_CONFIG_BYTES = 64_000
MAX_CONFIG_DEPTH = 50
MAX_CONFIG_VALUES = 10_000


def _check_size(root: yaml.Node | None) -> None:
    """Raise ``ConfigError`` when the node graph nests deeper than
    :data:`MAX_CONFIG_DEPTH` or expands (aliases followed) to more than
    :data:`MAX_CONFIG_VALUES` values; iterative, each shared node is counted once."""
    if root is None:
        return
    expanded: dict[int, int] = {}  # id(node) -> values it expands to
    todo: list[tuple[yaml.Node, int, bool]] = [(root, 1, False)]
    while todo:
        node, depth, children_done = todo.pop()
        if depth > MAX_CONFIG_DEPTH:
            raise ConfigError(
                f"nests lists or mappings deeper than {MAX_CONFIG_DEPTH} levels "
                f"(line {node.start_mark.line + 1})"
            )
        if isinstance(node, yaml.MappingNode):
            children = [n for pair in node.value for n in pair]
        elif isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        else:
            expanded[id(node)] = 1
            continue
        if children_done:
            total = 1 + sum(expanded[id(c)] for c in children)
            if total > MAX_CONFIG_VALUES:
                raise ConfigError(
                    f"expands to more than {MAX_CONFIG_VALUES} values once its aliases are "
                    f"followed (line {node.start_mark.line + 1})"
                )
            expanded[id(node)] = total
        elif id(node) not in expanded:
            todo.append((node, depth, True))
            todo += [(c, depth + 1, False) for c in children if id(c) not in expanded]


def load_yaml(path: str | os.PathLike) -> dict:
    """Read a YAML file with the safe loader; the top level must be a mapping.

    A key given twice in one mapping is an error, as are bytes that are not UTF-8 or
    UTF-16 text, a file over :data:`MAX_CONFIG_BYTES`, nesting deeper than
    :data:`MAX_CONFIG_DEPTH` and more than :data:`MAX_CONFIG_VALUES` values once the
    aliases are followed (a "billion laughs" file).

    Raises:
        ConfigError: naming the file and the problem; an unreadable file too (``OSError``).
    """
    path = Path(path)
    try:
        if not path.is_file():
            problem = "is not a file" if path.exists() else "does not exist"
            raise ConfigError(f"config file {str(path)!r} {problem}")
        size = path.stat().st_size
        if size > MAX_CONFIG_BYTES:
            raise ConfigError(
                f"config file {str(path)!r} has {size} bytes: must be <= {MAX_CONFIG_BYTES}"
            )
        # Binary streams: PyYAML reads the encoding from the byte order mark.
        with path.open("rb") as fh:
            text = fh.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"config file {str(path)!r} cannot be read: {exc.strerror}") from None
    if len(text) > MAX_CONFIG_BYTES:  # grew since stat
        raise ConfigError(f"config file {str(path)!r}: must be <= {MAX_CONFIG_BYTES} bytes")
    try:
        # Bytes: PyYAML reads the encoding from the byte order mark. Parsed once; the
        # checks run on the node graph before any Python value is built from it.
        loader = yaml.SafeLoader(io.BytesIO(text))
        try:
            try:
                root = loader.get_single_node()
            except RecursionError:
                raise ConfigError(
                    f"nests lists or mappings deeper than {MAX_CONFIG_DEPTH} levels"
                ) from None
            _check_size(root)
            _check_unique_keys(root)
            data = None if root is None else loader.construct_document(root)
        finally:
            loader.dispose()
    except ConfigError as exc:
        raise ConfigError(f"config file {str(path)!r} {exc}") from None
    except (yaml.YAMLError, ValueError) as exc:  # ValueError: an int over 4300 digits
        raise ConfigError(f"config file {str(path)!r} is not valid YAML: {exc}") from exc
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {str(path)!r}: top level must be a mapping of sections")
    return data


def _is_float_text(text: str) -> bool:
    """Whether Python reads ``text`` (a short one) as a finite float, e.g. ``"1.0e6"``."""
    if len(text) > 100:
        return False
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _convert(value: Any, tp: Any, key: str) -> Any:
    """Convert a plain YAML value to the annotated type ``tp``, or raise naming ``key``."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return _convert_optional(value, typing.get_args(tp), key)
    if dataclasses.is_dataclass(tp):
        return _convert_section(value, tp, key)
    if origin is tuple:
        return _convert_tuple(value, typing.get_args(tp), key)
    if tp in _SCALARS:
        return _SCALARS[tp](value, key)
    raise TypeError(f"unsupported config type {tp!r} for {key}")  # a bug, not user input


#: What :func:`from_dict` reads a config field's value into, for the message of a refused one.
SUPPORTED_ANNOTATIONS = (
    "bool, int, float, str, tuple[float, ...] (any length) or tuple[float, float] (fixed; of "
    "any of these), a nested config dataclass, and any of them | None"
)


def _annotation_supported(tp: Any) -> bool:
    """Whether :func:`_convert` reads a plain value into the annotation ``tp``."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return all(a is type(None) or _annotation_supported(a) for a in typing.get_args(tp))
    if dataclasses.is_dataclass(tp):
        return True
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            args = args[:1]
        return bool(args) and all(_annotation_supported(a) for a in args)
    return tp in _SCALARS


def annotation_problem(cls: type, seen: tuple[type, ...] = ()) -> str | None:
    """Why a config file cannot be read into the dataclass ``cls`` (a field whose
    annotation :func:`from_dict` does not read, named ``Class.field``, nested sections
    included), else ``None``."""
    try:
        hints = typing.get_type_hints(cls)
    except Exception as exc:  # an annotation that does not resolve
        return f"{cls.__name__}: its annotations do not resolve ({type(exc).__name__}: {exc})"
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp = hints.get(f.name)
        if not _annotation_supported(tp):
            shown = getattr(tp, "__name__", None) if typing.get_origin(tp) is None else None
            return (
                f"{cls.__name__}.{f.name} is annotated {shown or tp!s}, which a config file "
                f"cannot be read into; annotate it with one of: {SUPPORTED_ANNOTATIONS}"
            )
        inner = [tp, *typing.get_args(tp)]
        for section in (a for a in inner if dataclasses.is_dataclass(a) and a not in seen):
            problem = annotation_problem(section, (*seen, cls))
            if problem is not None:
                return problem
    return None


def _convert_optional(value: Any, args: tuple, key: str) -> Any:
    """``None`` where the type allows it, else the value as the first of the union's other
    types that takes it (``float | str``: a number, else a text), else the first type's
    error."""
    if value is None and type(None) in args:
        return None
    inner = [a for a in args if a is not type(None)]
    try:
        return _convert(value, inner[0], key)
    except ConfigError:
        for tp in inner[1:]:  # (a plain X | None has no other type to try)
            try:
                return _convert(value, tp, key)
            except ConfigError:
                pass
        raise


def _convert_section(value: Any, tp: type, key: str) -> Any:
    """A nested config dataclass from its mapping (or the dataclass itself)."""
    if isinstance(value, tp):
        return value
    if not isinstance(value, dict):
        raise ConfigError(f"{key}: expected a mapping, got {_show(value)}")
    return from_dict(tp, value, prefix=key)


def _convert_bool(value: Any, key: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{key}={_show(value)}: expected true or false")
    return value


def _convert_int(value: Any, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(f"{key}={_show(value)}: expected an integer")
    return int(value)


def _float_hint(value: Any) -> str:
    """Why a text is not a number here: PyYAML reads ``1e-3`` (no dot) as text."""
    if not isinstance(value, str):
        return ""
    if _is_float_text(value):
        return (
            f" (PyYAML, a YAML 1.1 reader, takes {_show(value)} for text: write"
            " floats with a dot and a signed exponent, e.g. 1.0e+6 or 1.0e-3)"
        )
    return " (write floats with a dot, e.g. 1.0e-3)"


def _convert_float(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(f"{key}={_show(value)}: expected a number{_float_hint(value)}")
    try:
        value = float(value)
    except OverflowError:
        raise ConfigError(f"{key}={_show(value)}: too large for a float") from None
    if not math.isfinite(value):
        raise ConfigError(f"{key}={_show(value)}: must be finite")
    return value


def _convert_str(value: Any, key: str) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"{key}={_show(value)}: expected a string")
    return value


_SCALARS = {bool: _convert_bool, int: _convert_int, float: _convert_float, str: _convert_str}


def _convert_tuple(value: Any, args: tuple, key: str) -> tuple:
    """A fixed-length tuple (one type per entry) or a variable-length one (``tuple[T, ...]``)."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    variable = len(args) == 2 and args[1] is Ellipsis
    if variable and isinstance(value, (int, float)):
        value = [value]  # a variable-length vector may be given as one number
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{key}={_show(value)}: expected a list")
    if variable:
        return tuple(_convert(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
    if len(value) != len(args):
        raise ConfigError(f"{key}={_show(list(value))}: expected a list of {len(args)} values")
    return tuple(
        _convert(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
    )


def _renamed_keys(cls: type, data: dict, prefix: str) -> dict:
    """``data`` with the keys ``cls.RENAMED_KEYS`` lists under their new names.

    A section may declare ``RENAMED_KEYS = {"old": "new"}`` for a field that was renamed:
    a file written with the old name still reads, with a ``FutureWarning`` naming both.

    Raises:
        ConfigError: when a section gives both names.
    """
    renamed = getattr(cls, "RENAMED_KEYS", {})
    if not any(old in data for old in renamed):
        return data
    data = dict(data)
    where = f"{prefix}." if prefix else ""
    for old, new in renamed.items():
        if old not in data:
            continue
        if new in data:
            raise ConfigError(f"{where}{old} and {where}{new} are one setting: give only {new}")
        warnings.warn(
            f"config key {where}{old} is now {where}{new}; the old name still reads for now",
            FutureWarning,
            stacklevel=2,
        )
        data[new] = data.pop(old)
    return data


def from_dict(cls: type[T], data: dict | None, prefix: str = "") -> T:
    """Build the frozen dataclass ``cls`` from a plain mapping, validating every key.

    Args:
        cls: the dataclass to build.
        data: mapping of field names to plain values; missing fields keep their defaults.
        prefix: dotted path of the section, used in error messages (e.g. ``"env"``).

    Raises:
        ConfigError: for unknown keys, wrong types, non-finite or out-of-range values.
    """
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix or cls.__name__}: expected a mapping, got {_show(data)}")
    data = _renamed_keys(cls, data, prefix)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(_key(k) for k in data if k not in names)
    if unknown:
        where = f"{prefix}." if prefix else ""
        raise ConfigError(
            f"unknown config key(s) {[where + k for k in unknown]}; allowed keys: {sorted(names)}"
        )
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        kwargs[name] = _convert(value, hints[name], key)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        if prefix and not str(exc).startswith(prefix):
            raise ConfigError(f"{prefix}.{exc}") from None
        raise


def to_dict(obj: Any) -> dict:
    """Plain (YAML-ready) mapping of a config dataclass, tuples as lists."""

    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v) if f.init}
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        return v

    return plain(obj)


def to_dict_fields(changes: dict) -> dict:
    """Plain values of a partial mapping of config fields (dataclasses become dicts)."""
    return {k: (to_dict(v) if dataclasses.is_dataclass(v) else v) for k, v in changes.items()}


@functools.cache
def _coercible_fields(cls: type) -> tuple[tuple[str, Any], ...]:
    """The init fields of a config dataclass whose values :class:`FieldChecker` converts:
    vectors (``tuple[...]``) and nested sections (dataclasses), optional ones too."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        tp = hints.get(f.name)
        union = typing.get_origin(tp) in (typing.Union, types.UnionType)
        inner = [a for a in typing.get_args(tp) if a is not type(None)] if union else [tp]
        if f.init and any(typing.get_origin(a) is tuple or dataclasses.is_dataclass(a)
                          for a in inner):  # fmt: skip
            out.append((f.name, tp))
    return tuple(out)


def _coerce_fields(obj: Any) -> None:
    """Give a config dataclass built in Python the values a YAML file would give it.

    ``AgentConfig(Q=[1, 1, 1, 0])`` or ``Q=np.array(...)``: a list or an array for a vector
    field becomes the tuple of numbers the field holds, and a mapping for a nested section
    its dataclass, each checked as :func:`from_dict` checks a file (a wrong length or a
    text is a :class:`ConfigError` naming the field, not a bare ``TypeError`` later).
    """
    if not dataclasses.is_dataclass(obj):
        return
    for name, tp in _coercible_fields(type(obj)):
        value = getattr(obj, name)
        if value is None or dataclasses.is_dataclass(value):
            continue  # None where allowed, a section built already: checked by their owners
        numbers = isinstance(value, tuple) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
        )
        if not numbers:
            object.__setattr__(obj, name, _convert(value, tp, name))


class FieldChecker:
    """Collects range checks of one dataclass and raises with the field's name.

    Made first in a config's ``__post_init__``, it also converts the values a Python caller
    may give where a file gives lists: a list or an array for a vector field, a mapping for
    a nested section (:func:`_coerce_fields`).
    """

    def __init__(self, obj: Any) -> None:
        self.obj = obj
        _coerce_fields(obj)

    def __call__(self, name: str, ok: bool, allowed: str) -> None:
        if not ok:
            raise ConfigError(f"{name}={_show(getattr(self.obj, name))}: must be {allowed}")

    def positive(self, *names: str) -> None:
        for n in names:
            self(n, getattr(self.obj, n) > 0, "> 0")

    def non_negative(self, *names: str) -> None:
        for n in names:
            v = getattr(self.obj, n)
            ok = all(x >= 0 for x in v) if isinstance(v, tuple) else v >= 0
            self(n, ok, ">= 0" if not isinstance(v, tuple) else "all >= 0")


#: Public name of the short value shown in error messages (the helpers of other rooms use it).
show_value = _show

__all__ = [
    "SUPPORTED_ANNOTATIONS",
    "annotation_problem",
    "MAX_CONFIG_BYTES",
    "MAX_CONFIG_DEPTH",
    "MAX_CONFIG_VALUES",
    "ConfigError",
    "FieldChecker",
    "from_dict",
    "load_yaml",
    "show_value",
    "to_dict",
    "to_dict_fields",
]
