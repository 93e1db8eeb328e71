"""How every stage's options are declared, checked and turned into command-line flags.

Each stage has one frozen dataclass of options (``ExtractOptions``, ``MatchOptions``, ...) that
derives from :class:`Options` and declares each field with :func:`option`: its default, one or
two sentences of help, and what values it allows (``choices``, ``min``, ``max``).  The values are
checked when the object is built, so a mistake fails before any work starts, with a
:class:`OptionError` naming the field and what is allowed.  The command line
(``sfm.cli``) makes one ``--flag`` per field from the same declaration (the field's name with
dashes for underscores, its type, choices, help and default), and :func:`options_from` builds
the dataclass back from keyword arguments (the Python API) with unknown names refused, so the
flags, the keywords and the checks cannot drift apart.
"""

from __future__ import annotations

import dataclasses
import difflib
import typing
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


class OptionError(ValueError):
    """A value an options dataclass does not allow; ``field`` names the option."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


def option(default: Any, help: str, *, choices: tuple[str, ...] | None = None, min: float | None = None,
           max: float | None = None, above: float | None = None) -> Any:
    """A dataclass field with its help and allowed values: ``choices`` for text, ``min`` and
    ``max`` (inclusive) or ``above`` (exclusive lower bound) for numbers.  ``None`` as the
    default makes the field optional (None allowed)."""
    meta = {"help": help, "choices": choices, "min": min, "max": max, "above": above}
    return dataclasses.field(default=default, metadata=meta)


def base_type(annotation: Any) -> type:
    """``int`` of ``int``, ``int | None`` and ``Optional[int]``."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    return args[0] if args else annotation


def allowed(field: dataclasses.Field) -> str:
    """What ``field`` allows, in words (for errors and help)."""
    m = field.metadata
    if m.get("choices"):
        return "one of " + ", ".join(m["choices"])
    parts = []
    if m.get("above") is not None:
        parts.append(f"> {m['above']:g}")
    if m.get("min") is not None:
        parts.append(f">= {m['min']:g}")
    if m.get("max") is not None:
        parts.append(f"<= {m['max']:g}")
    return " and ".join(parts)


def _check(field: dataclasses.Field, kind: type, value: Any) -> Any:
    """``value`` checked against the field's type and limits (a path given as text becomes a
    ``Path``, an integer given for a float field a float)."""
    m = field.metadata
    if value is None:
        if field.default is None:
            return None
        raise OptionError(field.name, f"must be given (a {kind.__name__})")
    if kind is bool:
        if not isinstance(value, bool):
            raise OptionError(field.name, f"must be True or False, got {value!r}")
        return value
    if kind is Path:
        if not isinstance(value, (str, Path)):
            raise OptionError(field.name, f"must be a path, got {value!r}")
        return Path(value)
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise OptionError(field.name, f"must be an integer, got {value!r}")
    elif kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
            raise OptionError(field.name, f"must be a number, got {value!r}")
        value = float(value)
    elif kind is str and not isinstance(value, str):
        raise OptionError(field.name, f"must be text, got {value!r}")
    if m.get("choices") and value not in m["choices"]:
        raise OptionError(field.name, f"must be {allowed(field)}; got {value!r}")
    too_low = (m.get("min") is not None and value < m["min"]) or (m.get("above") is not None and value <= m["above"])
    if too_low or (m.get("max") is not None and value > m["max"]):
        raise OptionError(field.name, f"must be {allowed(field)}; got {value!r}")
    return value


class Options:
    """Base of the stages' frozen option dataclasses: checks every field declared with
    :func:`option` when the object is built (see the module docstring)."""

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            if "help" not in f.metadata:
                continue
            value = _check(f, base_type(hints[f.name]), getattr(self, f.name))
            object.__setattr__(self, f.name, value)


def option_fields(cls: type) -> list[dataclasses.Field]:
    """The fields of an options dataclass declared with :func:`option`."""
    return [f for f in dataclasses.fields(cls) if "help" in f.metadata]


def unknown_names(names, known) -> str:
    """``'x' (did you mean 'y'?)`` for each of ``names`` not in ``known``."""
    out = []
    for name in sorted(names):
        close = difflib.get_close_matches(name, list(known), n=1)
        out.append(f"{name!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
    return ", ".join(out)


def options_from(cls: type[T], values: dict[str, Any]) -> T:
    """``cls`` built from those of ``values`` that are its fields (the rest are ignored)."""
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in values.items() if k in names})
