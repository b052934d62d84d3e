"""Node parameters: declared with defaults and help, set from launch files and the command line.

A node class declares ``PARAMS = {"rate": Param(1.0, "speed-up factor"), ...}``. Values arrive as
a dict (launch file, YAML-typed) and as ``name:=value`` strings (command line, parsed as YAML
scalars the way ``ros2 run ... --ros-args -p`` does). The declared default fixes the type; a
value that does not fit raises :class:`~twinfocus.errors.TwinFocusError` naming the node, the
parameter and the expected type.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import yaml

from twinfocus.errors import TwinFocusError
from twinfocus.focus.settings import Setting


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


REQUIRED: Any = _Required()


@dataclass(frozen=True)
class Param:
    """One declared parameter.

    default : the value when none is given (``REQUIRED`` for none; None: unset, which ``null``
        also gives); its type is the parameter's type unless ``type`` says otherwise (``"float"``,
        ``"int"``, ``"str"``, ``"bool"``, ``"list"``, ``"floats"`` (list of numbers), ``"strs"``
        (list of strings), ``"any"``).
    help : one line for ``--help`` and the docs.
    choices : allowed values, if limited.
    """

    default: Any
    help: str = ""
    type: str | None = None
    choices: tuple | None = None

    @property
    def kind(self) -> str:
        if self.type:
            return self.type
        d = self.default
        if isinstance(d, bool):
            return "bool"
        if isinstance(d, int):
            return "int"
        if isinstance(d, float):
            return "float"
        if isinstance(d, str):
            return "str"
        if isinstance(d, (list, tuple)):
            return "list"
        return "any"


def parse_assignment(text: str) -> tuple[str, Any]:
    """``name:=value`` -> (name, YAML-typed value). Plain strings stay strings."""
    if ":=" not in text:
        raise TwinFocusError(f"expected name:=value, got {text!r}")
    name, raw = text.split(":=", 1)
    name = name.strip()
    if not name:
        raise TwinFocusError(f"missing parameter name in {text!r}")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    if value is None and raw.strip() not in ("null", "~", "None"):
        value = raw
    return name, value


def param_of(setting: Setting) -> Param:
    """A focus setting (:data:`twinfocus.focus.settings.FOCUS_SETTINGS`) as a node parameter of the same
    name, default, choices and help, so a node takes it as ``twinfocus focus`` does."""

    def name(s: Setting) -> str:
        return s.name

    unit = f" ({setting.unit})" if setting.unit else ""
    unset = f"; unset: {setting.default_words(name)}" if setting.default is None else ""
    return Param(
        setting.default, setting.describe(name) + unit + unset, type=setting.type.__name__, choices=setting.choices
    )


def _coerce(node: str, name: str, p: Param, value: Any) -> Any:
    return coerce(f"node {node!r}: parameter {name!r}", p, value)


def coerce(label: str, p: Param, value: Any) -> Any:
    """``value`` as the type ``p`` declares; a value that does not fit raises
    :class:`~twinfocus.errors.TwinFocusError` ``"<label> must be <type>, got <value>"``."""
    kind = p.kind
    if value is None and p.default is None:
        return None

    def bad(expected: str):
        return TwinFocusError(f"{label} must be {expected}, got {value!r}")

    if kind == "bool":
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0", "yes", "no"):
            return value.lower() in ("true", "1", "yes")
        raise bad("true or false")
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise bad("an integer")
        try:
            f = float(value)
        except ValueError:
            raise bad("an integer") from None
        if f != int(f):
            raise bad("an integer")
        return int(f)
    if kind == "float":
        if isinstance(value, bool):
            raise bad("a number")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise bad("a number") from None
    if kind == "str":
        if value is None:
            return ""
        if isinstance(value, (list, dict)):
            raise bad("a string")
        return str(value)
    if kind in ("list", "strs", "floats"):
        if value is None or value == "":
            items: list = []
        elif isinstance(value, str):
            items = [v.strip() for v in value.split(",") if v.strip()]
        elif isinstance(value, (list, tuple)):
            items = list(value)
        else:
            items = [value]
        if kind == "strs":
            return [str(v) for v in items]
        if kind == "floats":
            try:
                return [float(v) for v in items]
            except (TypeError, ValueError):
                raise bad("a list of numbers") from None
        return items
    return value


def resolve(
    node: str,
    declared: Mapping[str, Param],
    given: Mapping[str, Any] | None = None,
    assignments: Iterable[str] = (),
    renamed: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """Final parameter values: defaults, then ``given`` (launch file), then ``name:=value`` strings.
    ``renamed``: old name -> what to write instead, for a clear error where an old name is given."""
    values: dict[str, Any] = {}
    merged: dict[str, Any] = dict(given or {})
    for a in assignments:
        k, v = parse_assignment(a)
        if k in declared and declared[k].kind == "str":
            v = a.split(":=", 1)[1]  # a string parameter keeps its text as typed ("007", "1e3")
        merged[k] = v
    renamed = renamed or {}
    old = sorted(set(merged) & set(renamed))
    if old:
        raise TwinFocusError(f"node {node!r}: parameter {old[0]!r} was renamed: use {renamed[old[0]]}")
    unknown = sorted(set(merged) - set(declared))
    if unknown:
        raise TwinFocusError(
            f"node {node!r}: unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(declared))}"
        )
    for name, p in declared.items():
        if name in merged:
            v = _coerce(node, name, p, merged[name])
        elif p.default is REQUIRED:
            raise TwinFocusError(f"node {node!r}: parameter {name!r} is required ({p.help})")
        else:
            v = list(p.default) if isinstance(p.default, (list, tuple)) else p.default
        if p.choices is not None and v not in p.choices:
            raise TwinFocusError(
                f"node {node!r}: parameter {name!r} must be one of {', '.join(map(str, p.choices))}, got {v!r}"
            )
        values[name] = v
    return values


def describe(declared: Mapping[str, Param]) -> str:
    """Parameter table for ``--help``."""
    lines = []
    for name, p in declared.items():
        default = "required" if p.default is REQUIRED else f"default {p.default!r}"
        choices = f"; one of {', '.join(map(str, p.choices))}" if p.choices else ""
        lines.append(f"  {name} ({p.kind}, {default}{choices})\n      {p.help}")
    return "\n".join(lines)
