"""A stage function's keyword options, and plain config values (TOML) checked and typed as those options take them."""

from __future__ import annotations

import inspect
import tomllib
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from ..errors import UsageError

#: keyword arguments every stage function takes that are not options of the work itself
_NOT_OPTIONS = ("overwrite", "quiet")
#: the default of an option that has none (it must be given)
REQUIRED = inspect.Parameter.empty


def parse_value(text: str) -> Any:
    """The VALUE of a ``--set KEY=VALUE``: TOML syntax (``50``, ``[1, 2]``, ``true``, ``"007"``), or else the text
    itself as a string (``--set data.raw=/data/eth ucy``)."""
    try:
        return tomllib.loads(f"value = {text.strip()}")["value"]
    except tomllib.TOMLDecodeError:
        return text.strip()


def keyword_options(function: Callable[..., Any]) -> dict[str, Any]:
    """The keyword-only options of `function` (besides overwrite and quiet) with their defaults."""
    parameters = inspect.signature(function).parameters.values()
    return {p.name: p.default for p in parameters
            if p.kind is inspect.Parameter.KEYWORD_ONLY and p.name not in _NOT_OPTIONS}


def option_value(function: Callable[..., Any], name: str, value: Any) -> Any:
    """`value` (a string, number, boolean, list or table from a config) as option `name` of `function` takes it:
    a number or string of its default's type (samples = 3000.0 -> 3000; an int option refuses 2.5), a list as a
    tuple where the annotation says tuple, and otherwise refused unless the annotation admits it. A UsageError
    saying what was expected, without the key (the caller adds where)."""
    default = keyword_options(function)[name]
    if isinstance(default, (int, float, str)) and not isinstance(default, bool):
        return _scalar(type(default), value)
    hint = _hints(function).get(name)
    if hint is None:
        return value  # no annotation to check against: the function checks it
    accepted = _accept_any(hint, value)
    if accepted is _REFUSED:
        raise UsageError(f"must be {_describe(hint)}, got {value!r}")
    return accepted


def _scalar(kind: type, value: Any) -> Any:
    try:
        if isinstance(value, (list, dict, bool)) or (kind is int and float(value) != int(value)):
            raise ValueError(value)
        return kind(value)
    except (TypeError, ValueError):
        raise UsageError(f"must be {kind.__name__}, got {value!r}") from None


_REFUSED = object()


def _hints(function: Callable[..., Any]) -> dict[str, Any]:
    """The evaluated annotations of `function` ({} where they cannot be evaluated)."""
    try:
        return typing.get_type_hints(function)
    except Exception:  # an annotation naming something only imported for type checkers
        return {}


def _alternatives(hint: Any) -> tuple[Any, ...]:
    """The members of a union annotation (`float | None` -> float, NoneType), or the annotation alone."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return typing.get_args(hint)
    return (hint,)


def _accept(hint: Any, value: Any) -> Any:
    """`value` as a `hint` (one member of a union), or _REFUSED."""
    origin = typing.get_origin(hint) or hint
    if hint is type(None):
        return _REFUSED  # a config cannot spell None: leaving the key out gives the default
    if hint is Any:
        return value
    if origin is bool:
        return value if isinstance(value, bool) else _REFUSED
    if origin in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return _REFUSED
        if origin is int and value != int(value):
            return _REFUSED
        return origin(value)
    if origin is str:
        return value if isinstance(value, str) else _REFUSED
    if origin in (tuple, list, Sequence) or (isinstance(origin, type) and issubclass(origin, Sequence)
                                             and origin is not str):
        if not isinstance(value, list):
            return _REFUSED
        items = typing.get_args(hint)
        item = items[0] if items and (len(items) == 1 or items[-1] is Ellipsis) else None
        if item is not None and not all(_accept_any(item, v) is not _REFUSED for v in value):
            return _REFUSED
        if items and item is None and len(items) != len(value):
            return _REFUSED
        return tuple(value) if origin is tuple else value
    if origin in (dict, Mapping) or (isinstance(origin, type) and issubclass(origin, Mapping)):
        return value if isinstance(value, dict) else _REFUSED
    return _REFUSED


def _accept_any(hint: Any, value: Any) -> Any:
    """`value` as the first member of the (union) annotation `hint` that takes it, or _REFUSED."""
    for option in _alternatives(hint):
        accepted = _accept(option, value)
        if accepted is not _REFUSED:
            return accepted
    return _REFUSED


def _describe(hint: Any) -> str:
    """The annotation in words for an error (without None: a config cannot give it)."""
    names = []
    for option in _alternatives(hint):
        if option is type(None):
            continue
        origin = typing.get_origin(option) or option
        names.append({int: "an integer", float: "a number", str: "a string", bool: "true or false", tuple: "a list",
                      list: "a list", dict: "a table"}.get(origin, "a list" if origin in (Sequence,) else
                                                          "a table" if origin in (Mapping,) else str(option)))
    return " or ".join(dict.fromkeys(names)) or "left out"
