"""Command-line flags made from the stages' frozen option dataclasses.

Each stage has one frozen dataclass of options whose docstring documents every field as a
``name: text`` line.  :func:`add_options` turns the fields into ``--flags`` (underscores become
dashes, types and defaults come from the field, help from the docstring) and
:func:`options_from_args` builds the dataclass back, so the CLI and the Python API cannot drift.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import typing
from typing import Any, TypeVar

T = TypeVar("T")


def _field_help(cls: type) -> dict[str, str]:
    """``name: text`` entries of a dataclass docstring (continuation lines are joined)."""
    helps: dict[str, str] = {}
    current = None
    names = {f.name for f in dataclasses.fields(cls)}
    for line in (cls.__doc__ or "").splitlines():
        m = re.match(r"\s*([a-z_][a-z0-9_, ]*):\s*(.*)", line)
        if m and all(n.strip() in names for n in m.group(1).split(",")):
            current = [n.strip() for n in m.group(1).split(",")]
            for n in current:
                helps[n] = m.group(2).strip()
        elif current and line.strip():
            for n in current:
                helps[n] += " " + line.strip()
        else:
            current = None
    return helps


def _base_type(annotation: Any) -> type:
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    return args[0] if args else annotation


def add_options(parser: argparse.ArgumentParser, cls: type, flags: dict[str, str] | None = None,
                skip: tuple[str, ...] = ()) -> None:
    """Add one ``--flag`` per field of ``cls`` (``flags`` renames fields, ``skip`` omits some)."""
    flags = flags or {}
    helps = _field_help(cls)
    hints = typing.get_type_hints(cls)
    group = parser.add_argument_group(cls.__name__)
    for f in dataclasses.fields(cls):
        if f.name in skip or f.name.startswith("_"):
            continue
        flag = "--" + flags.get(f.name, f.name.replace("_", "-"))
        if flag in parser._option_string_actions:  # shared by several stages (e.g. --seed)
            continue
        kind = _base_type(hints[f.name])
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        text = helps.get(f.name, "").replace("%", "%%")
        if kind is bool:
            group.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=default, help=text)
            continue
        choices = None
        m = re.search(r"one of ([a-z0-9_|-]+)", text)
        if m:
            choices = m.group(1).split("|")
        group.add_argument(flag, dest=f.name, type=kind, default=default, choices=choices,
                           metavar=None if choices else f.name.upper(), help=f"{text} (default: {default})")


def options_from_args(cls: type[T], args: argparse.Namespace) -> T:
    """The dataclass ``cls`` built from the parsed flags that belong to it."""
    from sfm.errors import InputError

    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)}
    try:
        return cls(**values)
    except ValueError as exc:  # an option the dataclass rejects is a bad argument (exit 2)
        raise InputError(str(exc)) from exc
