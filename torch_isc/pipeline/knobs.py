"""Config sections as plain dataclasses whose fields declare their bounds.

A stage owns its section (``TestConfig`` lives beside the test); :func:`knob` puts the bounds
in the field's metadata and :func:`check_section` enforces them with the key named, so a
section checks itself when it is built. Nothing more: YAML loading, unknown keys and the flat
keys of older files are handled by :mod:`torch_isc.pipeline.config`.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Optional, Sequence

__all__ = ["ConfigError", "knob", "check_section", "check_bounds", "INT_LIMIT", "Base60Text", "OctalText", "non_ascii_digit"]


class ConfigError(ValueError):
    """A configuration key or value that cannot be used."""


class Base60Text(str):
    """A YAML 1.1 base-60 scalar (``1:30``), kept as its text by the config loader: PyYAML
    would read it as 90, which nobody writing a tolerance means. Refused with the key named."""


class UnderscoreText(str):
    """A number written with ``_`` (``1_000``), kept as its text: PyYAML reads it as 1000, YAML
    1.2 as a string, and the rest of the project (text point files, the CLI's numbers) refuses
    it. Refused with the key named."""


class Bool11Text(str):
    """A YAML 1.1 boolean word (``yes``, ``no``, ``on``, ``off``), kept as its text: YAML 1.2
    reads it as a string. Refused with the key named (write ``true`` or ``false``)."""


class OctalText(str):
    """A YAML 1.1 octal scalar (``010``), kept as its text: PyYAML reads it as 8, YAML 1.2 and
    most tools as 10. Refused with the key named."""


def non_ascii_digit(text: str) -> Optional[str]:
    """The first digit of ``text`` that is not ASCII 0-9 (Arabic-Indic, full-width, ...), or None.
    Python's ``float``/``int`` read them; YAML, numpy and other tools do not, so they are refused."""
    if text.isascii():
        return None
    for ch in text:
        if ch.isdigit() and not ch.isascii():
            return ch
    return None


def _digit_message(name: str, text: str, ch: str) -> str:
    return (f"config key '{name}': {_short(text)} has the non-ASCII digit {ch!r} (U+{ord(ch):04X}); "
            f"write numbers with the digits 0-9")


_TYPES = {"int": int, "float": float, "str": str, "bool": bool}
#: Every integer setting must be below this in magnitude: torch holds them as int64.
INT_LIMIT = 2 ** 63


def knob(default: Any, *, gt: Optional[float] = None, ge: Optional[float] = None, lt: Optional[float] = None,
         le: Optional[float] = None, choices: Optional[Sequence[str]] = None) -> Any:
    """A config field with its bounds (``gt``: > , ``ge``: >=, ``lt``: <, ``le``: <=) or its
    allowed ``choices``."""
    return dataclasses.field(default=default, metadata={"gt": gt, "ge": ge, "lt": lt, "le": le, "choices": choices})


def _short(v: Any) -> str:
    """A bounded description of ``v`` for a message: never the repr of a large container (a
    YAML alias bomb expands to a value whose repr would take minutes and gigabytes)."""
    if isinstance(v, (list, tuple, dict, set, frozenset)):
        return f"({len(v)} items)"
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 10 ** 30:
        return f"an integer of {len(str(abs(v))) if abs(v) < 10 ** 4000 else 'over 4000'} digits"
    if isinstance(v, (str, bytes)) and len(v) > 60:
        v = v[:57]
        return repr(v) + "..."
    r = repr(v)
    return r if len(r) <= 60 else r[:57] + "..."


_OPS = (("gt", lambda x, b: x <= b, ">"), ("ge", lambda x, b: x < b, ">="),
        ("lt", lambda x, b: x >= b, "<"), ("le", lambda x, b: x > b, "<="))


def check_bounds(name: str, v: Any, gt: Optional[float] = None, ge: Optional[float] = None,
                 lt: Optional[float] = None, le: Optional[float] = None) -> None:
    """Raise a :class:`ConfigError` naming ``name`` when ``v`` is outside the bounds."""
    for op, bad, word in _OPS:
        b = {"gt": gt, "ge": ge, "lt": lt, "le": le}[op]
        if b is not None and bad(v, b):
            raise ConfigError(f"config key '{name}': must be {word} {b:g}, got {_short(v)}")


def check_section(obj: Any) -> None:
    """Coerce (an int or a numeric string for a float) and check every field of the section
    ``obj``; a :class:`ConfigError` names the key."""
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        want = f.type if isinstance(f.type, type) else _TYPES[f.type]
        if isinstance(v, Base60Text):
            raise ConfigError(f"config key '{f.name}': {_short(str(v))} is a YAML 1.1 base-60 number (PyYAML reads it "
                              f"as a count of minutes or seconds); write the value itself")
        if isinstance(v, OctalText):
            raise ConfigError(f"config key '{f.name}': {_short(str(v))} has a leading zero (YAML 1.1 reads it as an "
                              f"octal number, YAML 1.2 as decimal); write it without the leading zero")
        if isinstance(v, Bool11Text):
            raise ConfigError(f"config key '{f.name}': {_short(str(v))} is a YAML 1.1 boolean word (YAML 1.2 reads "
                              f"it as text); write true or false")
        if isinstance(v, str) and want in (int, float) and "_" in v:
            # float("1_0") is 10.0: Python's reading, not a number anyone writes in a config
            raise ConfigError(f"config key '{f.name}': {_short(str(v))} has a '_' in a number "
                              f"(no _ in numbers; write {_short(str(v).replace('_', ''))})")
        if v is None:
            raise ConfigError(f"config key '{f.name}': no value given (expected {want.__name__})")
        if isinstance(v, str) and want in (int, float) and non_ascii_digit(v):
            raise ConfigError(_digit_message(f.name, v, non_ascii_digit(v)))
        if type(v).__module__ == "numpy" and getattr(v, "ndim", None) == 0:
            v = v.item()          # a numpy scalar (np.int64 from a parameter sweep): its Python value
        if want is float and isinstance(v, str):          # YAML 1.1 reads 1e-3 as a string
            try:
                v = float(v)
            except ValueError:
                pass
        if want is float and isinstance(v, int) and not isinstance(v, bool):
            try:
                v = float(v)
            except OverflowError:         # an integer beyond the float64 range
                raise ConfigError(f"config key '{f.name}': must be finite, got {_short(v)}") from None
        if not isinstance(v, want) or (want in (int, float) and isinstance(v, bool)):
            raise ConfigError(f"config key '{f.name}': expected {want.__name__}, got {type(v).__name__} {_short(v)}")
        object.__setattr__(obj, f.name, v)
        if want is float and not math.isfinite(v):
            raise ConfigError(f"config key '{f.name}': must be finite, got {v!r}")
        if want is int and not -INT_LIMIT < v < INT_LIMIT:
            raise ConfigError(f"config key '{f.name}': must be below 2**63 in magnitude (a 64-bit integer), "
                              f"got {_short(v)}")
        m = f.metadata
        if m.get("choices") and v not in m["choices"]:
            raise ConfigError(f"config key '{f.name}': must be one of {', '.join(m['choices'])}, got {_short(v)}")
        if want in (int, float):
            check_bounds(f.name, v, m.get("gt"), m.get("ge"), m.get("lt"), m.get("le"))
