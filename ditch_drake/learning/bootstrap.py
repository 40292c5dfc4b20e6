"""Bootstrap resamples of the demonstrations for an ensemble: each member's draw, recorded.

Whole demonstrations are drawn, with replacement, N out of N: steps of one demonstration are
strongly correlated, and a member that never saw a demonstration is the one whose disagreement
tells that such a state is unfamiliar (`ditch_drake.learning.ensemble`).
"""

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ditch_drake.common.errors import ConfigError

MIN_MEMBERS = 2


@dataclass
class BootstrapDraw:
    """One member's resample.

    Attributes:
        member: its index in the ensemble.
        seed: the seed its training uses (`TrainConfig.seed`).
        indices: (N,) the demonstrations drawn, with replacement, in the order drawn.
    """

    member: int
    seed: int
    indices: np.ndarray

    def distinct(self) -> np.ndarray:
        """The demonstrations it holds at least once, sorted."""
        return np.unique(self.indices)

    def out_of_bag(self, count: int) -> np.ndarray:
        """The demonstrations of 0..count-1 it never drew."""
        return np.setdiff1d(np.arange(count), self.indices)


@dataclass
class Bootstrap:
    """The resamples of an ensemble: what `bootstrap_demonstrations` drew, as recorded in the file.

    Attributes:
        seed: the seed everything was drawn from.
        demonstrations: the names of the demonstrations drawn from (index i is `indices` value i),
            or their count when they have no names.
        draws: one per member.
    """

    seed: int
    demonstrations: list[str] | int
    draws: list[BootstrapDraw] = field(default_factory=list)

    @property
    def count(self) -> int:
        """How many demonstrations there were to draw from."""
        return self.demonstrations if isinstance(self.demonstrations, int) else len(self.demonstrations)

    def to_dict(self) -> dict:
        """Plain values, for the ensemble file."""
        demonstrations = self.demonstrations if isinstance(self.demonstrations, int) else list(self.demonstrations)
        return {"seed": self.seed, "demonstrations": demonstrations,
                "draws": [{"member": d.member, "seed": d.seed, "indices": d.indices.tolist()} for d in self.draws]}

    @classmethod
    def from_dict(cls, values: dict) -> "Bootstrap":
        """The record of `to_dict`'s output.

        Raises:
            KeyError, TypeError, ValueError: a malformed record.
        """
        draws = [BootstrapDraw(int(d["member"]), int(d["seed"]), np.asarray(d["indices"], dtype=np.int64))
                 for d in values["draws"]]
        demonstrations = values["demonstrations"]
        return cls(int(values["seed"]), demonstrations if isinstance(demonstrations, int) else list(demonstrations),
                   draws)


def check_member_count(members, what: str = "--ensemble") -> int:
    """`members` as an int >= `MIN_MEMBERS`.

    Raises:
        ConfigError: anything else, naming `what`: disagreement needs at least two members.
    """
    if isinstance(members, bool) or not isinstance(members, (int, np.integer)) or members < MIN_MEMBERS:
        raise ConfigError(f"{what} {members!r}: expected an integer >= {MIN_MEMBERS} members (an ensemble's "
                          "uncertainty is its members' disagreement)")
    return int(members)


def bootstrap_demonstrations(
    names_or_count: Sequence[str] | int, members: int, seed: int, min_distinct: int = 2
) -> Bootstrap:
    """Each member's resample of the demonstrations: N drawn with replacement out of N.

    Whole demonstrations are drawn, not samples: steps of one demonstration are strongly
    correlated, and a member that never saw a demonstration is the one whose disagreement
    tells that such a state is unfamiliar. Member k's draw comes from numpy's generator seeded
    by (seed, k) alone, so it is the same whatever K is, and its training seed is seed + k.

    Args:
        names_or_count: the demonstrations' names, or how many there are.
        members: K, at least 2.
        seed: a non-negative integer.
        min_distinct: a draw with fewer distinct demonstrations (possible with few of them; with
            two, half the draws) is drawn again from the same generator: training holds whole
            demonstrations out for validation, so it needs two. Capped at N.

    Raises:
        ConfigError: K < 2, a negative or non-integer seed, or no demonstrations.
    """
    members = check_member_count(members)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed {seed!r}: expected a non-negative integer")
    names = None if isinstance(names_or_count, (int, np.integer)) else [str(name) for name in names_or_count]
    count = int(names_or_count) if names is None else len(names)
    if count < 1:
        raise ConfigError(f"{count} demonstrations to resample; expected at least 1")
    draws = []
    for member in range(members):
        generator = np.random.default_rng([int(seed), member])
        indices = generator.integers(0, count, count)
        while len(np.unique(indices)) < min(min_distinct, count):
            indices = generator.integers(0, count, count)
        draws.append(BootstrapDraw(member, int(seed) + member, indices.astype(np.int64)))
    return Bootstrap(int(seed), count if names is None else names, draws)
