"""Config dataclasses from files and ``KEY=VALUE`` pairs: every field reachable by its name.

A config file is TOML (``.toml``) or JSON (anything else): a mapping of the dataclass's field names to
values. Nested configs (``CompressConfig.merge``, ``CompressConfig.lengths``) are tables, or dotted keys
(``merge.grid_size``). A file that holds the config under one key — a training run's ``config.json``
(``train_config``) or a compression's ``<out>.config.json`` (``compress_config``) — is read from that key,
so a run's own record reproduces it. Unknown keys and values of the wrong type are one-line
:class:`~omg4.errors.OMG4Error` s naming the closest valid keys. A config class may list settings that moved
(``MOVED_SETTINGS``: earlier name → dotted name now); those are read under their new names, with a one-line
deprecation message. It may list settings it no longer has (``REMOVED_SETTINGS``: name → (the value that meant
"off", why it went)): an earlier record or file that holds one at that value is read without it; any other value is
a one-line error saying why, since the run it describes cannot be made again.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import logging
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

from omg4.errors import OMG4Error

logger = logging.getLogger(__name__)
_told: set[str] = set()


def tell_moved(old: str, new: str) -> None:
    """The one-line deprecation message, once per process and name, that the setting ``old`` is now ``new``."""
    if old not in _told:
        _told.add(old)
        logger.warning(f"the setting '{old}' is now '{new}'; the old name is deprecated")


def drop_removed(cls, values: dict[str, Any]) -> dict[str, Any]:
    """``values`` without the settings ``cls`` no longer has (``REMOVED_SETTINGS``) that hold their "off" value; one
    that holds another is a one-line error naming why it was removed."""
    removed = getattr(cls, "REMOVED_SETTINGS", {})
    for key in [k for k in values if k in removed]:
        off, why = removed[key]
        if values[key] != off:
            raise OMG4Error(f"the setting '{key}' ({values[key]!r}) was removed: {why}")
        del values[key]
    return values


def knob(default, help: str):
    """A config field with its help text (shown by the commands' ``--help``)."""
    return dataclasses.field(default=default, metadata={"help": help})


@dataclasses.dataclass(frozen=True)
class Setting:
    """One settable field: its dotted name, type, default and help text."""

    name: str
    type: Any
    default: Any
    help: str


def settings_of(cls, prefix: str = "") -> dict[str, Setting]:
    """Every field of the dataclass ``cls`` by dotted name; nested dataclass fields (also optional ones) expand, and a
    field typed as a union of dataclasses (the training config's ``strategy``) expands every member's fields once (a
    name two members share is one setting: theirs agree, the members being subclasses of one another's base)."""
    hints = typing.get_type_hints(cls)
    out: dict[str, Setting] = {}
    for f in dataclasses.fields(cls):
        kind = hints[f.name]
        nested = _dataclasses_in(kind)
        if nested:
            for member in nested:
                for name, setting in settings_of(member, prefix + f.name + ".").items():
                    out.setdefault(name, setting)
            continue
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        out[prefix + f.name] = Setting(prefix + f.name, kind, default, f.metadata.get("help", ""))
    return out


def _dataclasses_in(kind) -> list[type]:
    """The dataclasses of an annotation ``C``, ``C | None`` or ``C | D | …`` (empty when it holds none)."""
    if dataclasses.is_dataclass(kind):
        return [kind]
    if not _is_union(kind):
        return []
    members = [a for a in typing.get_args(kind) if a is not type(None)]
    return members if all(dataclasses.is_dataclass(a) for a in members) else []


def _is_union(kind) -> bool:
    return typing.get_origin(kind) in (typing.Union, types.UnionType)


def read_config_file(path: str | Path, section: str, extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """The flat (dotted) mapping of a config file; ``section`` is the key under which a run's record holds it (the
    record's top-level keys named in ``extra``, a command's own options, join it)."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise OMG4Error(f"cannot read the config file {path} ({type(e).__name__})") from None
    try:
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as e:
        kind = "TOML" if path.suffix.lower() == ".toml" else "JSON"
        raise OMG4Error(f"{path} is not valid {kind}: {str(e).splitlines()[0]}") from None
    if isinstance(data, dict) and isinstance(data.get(section), dict):
        data = {**data[section], **{k: v for k, v in data.items() if k in extra}}
    if not isinstance(data, dict):
        raise OMG4Error(f"{path} must hold a mapping of setting names to values")
    return flatten(data)


def flatten(data: dict, prefix: str = "") -> dict[str, Any]:
    """``{"merge": {"grid_size": 0.2}}`` → ``{"merge.grid_size": 0.2}``."""
    out = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def parse_assignments(items: list[str] | None) -> dict[str, Any]:
    """``["iterations=3000", "background=[1, 1, 1]", "backbone=freetimegs"]`` → a flat mapping (values read as JSON,
    else taken as text)."""
    out = {}
    for item in items or ():
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise OMG4Error(f"--set expects KEY=VALUE, got '{item}'")
        try:
            value = json.loads(text)
        except ValueError:
            value = text
        out[key.strip()] = value
    return out


def check_settings(cls, values: dict[str, Any], *, extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """``values`` with each value converted to its field's type; unknown keys (beyond ``extra``) and values of the
    wrong type are one-line errors."""
    table, moved = settings_of(cls), getattr(cls, "MOVED_SETTINGS", {})
    out = {}
    for key, value in drop_removed(cls, dict(values)).items():
        if key in moved and key not in table:
            tell_moved(key, moved[key])
            key = moved[key]
        if key in extra:
            out[key] = value
            continue
        if key not in table and value is None and any(name.startswith(key + ".") for name in table):
            continue  # an optional nested config left unset (a record's ``"lengths": null``)
        if key not in table:
            close = difflib.get_close_matches(key, [*table, *extra], n=3, cutoff=0.5)
            hint = f"; did you mean {' or '.join(close)}?" if close else f" (see the {cls.__name__} fields)"
            raise OMG4Error(f"unknown setting '{key}'{hint}")
        out[key] = convert(key, value, table[key].type)
    return out


def convert(key: str, value: Any, kind) -> Any:
    """``value`` as the annotation ``kind`` (int, float, bool, str, tuples, optional values), or a one-line error."""
    if _is_union(kind):
        args = typing.get_args(kind)
        if value is None and type(None) in args:
            return None
        for option in (a for a in args if a is not type(None)):
            try:
                return convert(key, value, option)
            except OMG4Error:
                continue
        raise OMG4Error(f"setting '{key}' expects {type_name(kind)}, got {value!r}")
    origin = typing.get_origin(kind)
    if origin is tuple:
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise OMG4Error(f"setting '{key}' expects a list, got {value!r}")
        args = typing.get_args(kind)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(convert(key, v, args[0]) for v in value)
        if len(args) != len(value):
            raise OMG4Error(f"setting '{key}' expects {len(args)} values, got {len(value)}")
        return tuple(convert(key, v, a) for v, a in zip(value, args))
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
    elif kind is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif kind is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
    elif kind is str:
        if isinstance(value, str):
            return value
    elif kind is Any:
        return value
    raise OMG4Error(f"setting '{key}' expects {type_name(kind)}, got {value!r}")


def type_name(kind) -> str:
    if _is_union(kind):
        return " or ".join(type_name(a) for a in typing.get_args(kind))
    if kind is type(None):
        return "null"
    if typing.get_origin(kind) is tuple:
        return "a list"
    names = {int: "an integer", float: "a finite number", bool: "true or false", str: "text"}
    return names.get(kind, getattr(kind, "__name__", str(kind)))


def apply_settings(config, values: dict[str, Any]):
    """A copy of the dataclass instance ``config`` with the flat, checked ``values`` applied: its own fields first, then
    the nested ones (an unset nested config starts from its class's defaults), so that a nested config its own fields
    decide (the training config's ``strategy``, by the backbone) takes its settings as that class's. A nested name
    that class lacks is a one-line error."""
    top: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for key, value in values.items():
        head, dot, rest = key.partition(".")
        if dot:
            nested.setdefault(head, {})[rest] = value
        else:
            top[head] = value
    config = dataclasses.replace(config, **top)
    hints = typing.get_type_hints(type(config))
    changed: dict[str, Any] = {}
    for head, inner in nested.items():
        current = getattr(config, head)
        if current is None:
            current = _dataclasses_in(hints[head])[0]()
        names = {f.name for f in dataclasses.fields(current)}
        unknown = sorted(f"{head}.{key}" for key in inner if key.partition(".")[0] not in names)
        if unknown:
            raise OMG4Error(f"{type(config).__name__}'s {head} is {type(current).__name__}, which has no setting "
                            f"{', '.join(unknown)} (its settings: {', '.join(sorted(names))})")
        changed[head] = apply_settings(current, inner)
    return dataclasses.replace(config, **changed) if changed else config


def config_dict(config) -> dict[str, Any]:
    """A dataclass instance as JSON-ready nested dicts (tuples as lists)."""
    return json.loads(json.dumps(dataclasses.asdict(config)))


__all__ = ["knob", "tell_moved", "drop_removed", "Setting", "settings_of", "read_config_file", "flatten",
           "parse_assignments", "check_settings", "convert", "type_name", "apply_settings", "config_dict"]
