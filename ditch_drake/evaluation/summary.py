"""Success rates with Wilson score intervals, and failure breakdowns, from rollout records."""

import math
from collections import Counter
from dataclasses import dataclass, field

from scipy.stats import binomtest

from ditch_drake.evaluation.results import RolloutRecord
from ditch_drake.world.regions import REGIONS

# A rollout that reached the goal with the chassis never tilted this far went around the
# ditch's end instead of through it: a 55 deg wall tilts it by 20 deg or more however
# shallow the crossing (docs/concepts/physics.md).
AROUND_TILT_DEG = 15.0


def wilson_interval(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (scipy's `binomtest(...).proportion_ci`).

    Raises:
        ValueError: counts out of range or a confidence outside (0, 1).
    """
    if trials < 0 or not 0 <= successes <= trials or not 0 < confidence < 1:
        raise ValueError(f"successes={successes}, trials={trials}, confidence={confidence}: "
                         "need 0 <= successes <= trials and 0 < confidence < 1")
    if trials == 0:
        return 0.0, 1.0
    interval = binomtest(successes, trials).proportion_ci(confidence_level=confidence, method="wilson")
    return float(interval.low), float(interval.high)


@dataclass
class GroupSummary:
    """Rollouts of one group (e.g. one controller in one environment).

    Attributes:
        trials, successes: counts (error records are counted apart, not as trials).
        rate: successes / trials (nan without trials).
        low, high: the 95 % Wilson interval.
        statuses: count per status, errors included.
        failure_regions: count per failure region of the failed trials.
        errors: rollouts that raised (not trials).
        around: successes that went around the ditch (peak tilt below `AROUND_TILT_DEG`).
        halts_by_region: the controller's halts per region, summed over the trials whose
            records count them (`RolloutRecord.halts_by_region`); empty when none does.
        halts_counted: the trials whose records count halts (older records do not).
    """

    trials: int
    successes: int
    rate: float
    low: float
    high: float
    statuses: dict[str, int] = field(default_factory=dict)
    failure_regions: dict[str, int] = field(default_factory=dict)
    errors: int = 0
    around: int = 0
    halts_by_region: dict[str, int] = field(default_factory=dict)
    halts_counted: int = 0


def summarize(records: list[RolloutRecord]) -> GroupSummary:
    """The summary of a group of records."""
    valid = [r for r in records if r.status != "error"]
    counted = [r for r in valid if r.halts_by_region]
    halts: Counter[str] = Counter()
    for record in counted:
        halts.update(record.halts_by_region)
    successes = sum(r.success for r in valid)
    low, high = wilson_interval(successes, len(valid))
    return GroupSummary(
        trials=len(valid), successes=successes, rate=successes / len(valid) if valid else math.nan, low=low, high=high,
        statuses=dict(Counter(r.status for r in records)),
        failure_regions=dict(Counter(f"{r.status}@{r.failure_region}" for r in valid if not r.success)),
        errors=len(records) - len(valid),
        around=sum(r.success and r.peak_tilt_deg < AROUND_TILT_DEG for r in valid),
        halts_by_region={region: halts[region] for region in REGIONS} if counted else {},
        halts_counted=len(counted))


def group_by(records: list[RolloutRecord], *names: str) -> dict[tuple, list[RolloutRecord]]:
    """Records grouped by the values of the named fields, groups in sorted key order."""
    groups: dict[tuple, list[RolloutRecord]] = {}
    for record in records:
        groups.setdefault(tuple(getattr(record, name) for name in names), []).append(record)
    return dict(sorted(groups.items()))
