"""Seeds: every random choice in the project takes one, and Drake's `RandomGenerator` takes
an unsigned 32-bit integer."""

from ditch_drake.common.errors import ConfigError

SEED_LIMIT = 2**32


def check_seed(seed: int, count: int = 1, where: str = "seed") -> None:
    """Raises ConfigError unless seeds seed .. seed + count - 1 all fit Drake's RandomGenerator."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0 or seed + count - 1 >= SEED_LIMIT:
        raise ConfigError(f"{where}={seed!r}: expected an integer in 0..{SEED_LIMIT - count} (seeds seed..seed+"
                          f"{count - 1} seed Drake's RandomGenerator)")
