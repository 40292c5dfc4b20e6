"""Range checks shared by the config dataclasses and the functions the commands call, each
raising `ConfigError` with the bad value and what was expected."""

import dataclasses
import math

from ditch_drake.common.errors import ConfigError


def check_finite_positive(value, where: str, unit: str = "seconds") -> float:
    """`value` as a float, if it is a finite number > 0.

    Infinity is refused as well as NaN: an episode without a limit never ends, and a record's
    JSON cannot hold inf (it would be written as null and never match its key again).

    Raises:
        ConfigError: naming `where`, the value and what was expected.
    """
    number = value if isinstance(value, (int, float)) and not isinstance(value, bool) else None
    if number is None or not math.isfinite(number) or number <= 0:
        raise ConfigError(f"{where}={value!r}: expected a finite positive number of {unit}")
    return float(number)


def check_count(value, where: str, lowest: int = 1) -> int:
    """`value`, if it is an integer >= `lowest`.

    Raises:
        ConfigError: naming `where`, the value and what was expected.
    """
    if isinstance(value, bool) or not isinstance(value, int) or value < lowest:
        raise ConfigError(f"{where}={value!r}: expected an integer >= {lowest}")
    return value


def check_no_nan(config, where: str) -> None:
    """Raises ConfigError naming the first NaN float in a config dataclass, its nested
    dataclasses, lists and dicts: no option means anything as NaN, and every comparison with
    it is false, so a range check written as `if value < low` lets it through."""
    for key, value in _floats(config, ""):
        if math.isnan(value):
            raise ConfigError(f"{where}: {key}=nan; expected a number")


def _floats(value, key: str):
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            yield from _floats(getattr(value, f.name), f"{key}.{f.name}" if key else f.name)
    elif isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            yield from _floats(item, f"{key}[{index}]")
    elif isinstance(value, dict):
        for name, item in value.items():
            yield from _floats(item, f"{key}.{name}" if key else str(name))
    elif isinstance(value, float):
        yield key, value
