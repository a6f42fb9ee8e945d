"""Validation of configuration values at the boundary: each check raises
:class:`~bftaichi.errors.ConfigError` naming the key. Used by every ``[section]`` dataclass."""

from __future__ import annotations

import math
import typing

from .errors import ConfigError

__all__ = ["check_range", "check_choice", "check_finite"]


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
