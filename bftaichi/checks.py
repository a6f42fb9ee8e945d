"""Validation of configuration values at the boundary: each check raises
:class:`~bftaichi.errors.ConfigError` naming the key. Used by every ``[section]`` dataclass, and by
the parsers of ``--set`` overrides, typed values and frame slices."""

from __future__ import annotations

import math
import tomllib
import typing

from .errors import ConfigError

__all__ = ["check_range", "check_choice", "check_finite", "MAX_SEED", "coerce",
           "parse_override", "parse_slice"]

MAX_SEED = 2 ** 32 - 1
"""The largest seed a key accepts (numpy's and Taichi's generators take 32-bit seeds)."""


def check_range(key: str, value: float, lo: float | None = None, hi: float | None = None,
                lo_open: bool = False) -> None:
    """Raise ConfigError unless lo <= value <= hi (lo < value with ``lo_open``); names ``key``."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{key} = {value} is not a finite number")
    if lo is not None and (value <= lo if lo_open else value < lo):
        rel = ">" if lo_open else ">="
        raise ConfigError(f"{key} = {value} is out of range: must be {rel} {lo}")
    if hi is not None and value > hi:
        raise ConfigError(f"{key} = {value} is out of range: must be <= {hi}")


def check_finite(section: str, sub) -> None:
    """Raise ConfigError naming the key if a float (or list of floats) field of the section
    ``sub`` holds NaN or inf; also the fields no range check covers (e.g. a camera height)."""
    for key, typ in typing.get_type_hints(type(sub)).items():
        if typ is float or typ == list[float]:
            value = getattr(sub, key)
            for v in (value if isinstance(value, list) else [value]):
                if isinstance(v, float) and not math.isfinite(v):
                    raise ConfigError(f"{section}.{key} = {value} is not a finite number")


def check_choice(key: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"{key} = {value!r} is not one of {', '.join(choices)}")


def coerce(key: str, value, typ):
    """Convert a TOML value to the field type, or raise ConfigError naming ``key``."""
    origin = typing.get_origin(typ)
    if typ is bool:
        if isinstance(value, bool):
            return value
    elif typ is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif typ is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif typ is str:
        if isinstance(value, str):
            return value
    elif origin is list:
        (item,) = typing.get_args(typ)
        if isinstance(value, list):
            return [coerce(key, v, item) for v in value]
    else:  # pragma: no cover - all fields use the types above
        raise ConfigError(f"{key}: unsupported field type {typ}")
    tname = getattr(typ, "__name__", str(typ))
    raise ConfigError(f"{key} = {value!r} has the wrong type: expected {tname}")


def parse_override(text: str) -> tuple[str, str, typing.Any]:
    """Parse ``section.key=value``; the value is TOML (``0.01``, ``true``, ``[5, 10]``, ``"s"``),
    and a bare word that is not valid TOML is taken as a string."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected section.key=value")
    lhs, rhs = text.split("=", 1)
    lhs = lhs.strip()
    if lhs.count(".") != 1:
        raise ConfigError(f"--set {text!r}: the key must be section.key, e.g. tsdf.voxel_size_m")
    section, key = lhs.split(".")
    try:
        value = tomllib.loads(f"v = {rhs.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = rhs.strip()
    return section, key, value


def parse_slice(text: str, key: str = "frames") -> slice:
    """``"a:b:c"`` -> ``slice(a, b, c)``; a single integer ``"n"`` means the first n frames."""
    try:
        parts = [int(p) if p.strip() else None for p in text.split(":")]
    except ValueError:
        raise ConfigError(f"{key} = {text!r} is not a slice like '0:100:2'") from None
    if len(parts) == 1:
        return slice(0, parts[0])
    if len(parts) > 3:
        raise ConfigError(f"{key} = {text!r} is not a slice like '0:100:2'")
    s = slice(*parts)
    if s.step is not None and s.step <= 0:
        raise ConfigError(f"{key} = {text!r}: the step must be positive")
    return s
