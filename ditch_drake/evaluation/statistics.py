"""The statistics behind the results pages: percentages as printed, Boschloo's two-proportion
test, comparisons of a learned model with a classical controller, the "beats" verdict, and the
paired comparison of two runs on the same rollouts (McNemar's exact test)."""

import math
from dataclasses import dataclass

from scipy.stats import binomtest, boschloo_exact

from ditch_drake.evaluation.summary import GroupSummary

# Significance level of the two-proportion tests behind the findings' verdicts.
ALPHA = 0.05


def percent(value: float, missing: str = "n/a") -> str:
    """A rate in [0, 1] as a whole percentage ("85%"); `missing` for NaN (a group without trials)."""
    return missing if math.isnan(value) else f"{100 * value:.0f}%"


def p_value_text(value: float) -> str:
    """A p-value to two significant digits."""
    return f"{value:.2g}"


def two_proportion_test(successes_a: int, trials_a: int, successes_b: int, trials_b: int) -> float:
    """Two-sided p-value of "both groups succeed at the same rate": Boschloo's exact test
    (`scipy.stats.boschloo_exact`) on the 2x2 table whose columns are the two groups.

    Exact, so it holds at 30 trials a group and at rates of 0 or 1, where a z-test's normal
    approximation does not; unconditional (each group's trials are fixed by the design, the
    total of successes is not), and uniformly more powerful than Fisher's exact test, whose
    p-value it takes as its statistic. A table without evidence either way (both groups all
    successes, or all failures: scipy gives nan) has p = 1, as in Fisher's test.

    Raises:
        ValueError: counts out of range, or a group without trials.
    """
    if not (0 <= successes_a <= trials_a and 0 <= successes_b <= trials_b and trials_a and trials_b):
        raise ValueError(f"successes {successes_a}/{trials_a} and {successes_b}/{trials_b}: need "
                         "0 <= successes <= trials and trials >= 1 in each group")
    table = [[successes_a, successes_b], [trials_a - successes_a, trials_b - successes_b]]
    p_value = float(boschloo_exact(table, alternative="two-sided").pvalue)
    return 1.0 if math.isnan(p_value) else p_value


def counted(summary: GroupSummary | None) -> GroupSummary | None:
    """The summary if it has trials (to test, or to draw), else None."""
    return summary if summary is not None and summary.trials else None


@dataclass
class Comparison:
    """A learned model against a classical controller in one environment (both with trials)."""

    environment: str
    model: str
    learned: GroupSummary
    controller: str
    baseline: GroupSummary
    p_value: float

    @property
    def beats(self) -> bool:
        """The learned model's rate is higher and the difference significant at `ALPHA`."""
        return self.learned.rate > self.baseline.rate and self.p_value < ALPHA


def compare(environment: str, model: str, learned: GroupSummary | None, controller: str,
            baseline: GroupSummary | None) -> Comparison | None:
    """The comparison of two groups, tested (`two_proportion_test`); None if one has no trials."""
    if not (counted(learned) and counted(baseline)):
        return None
    p_value = two_proportion_test(learned.successes, learned.trials, baseline.successes, baseline.trials)
    return Comparison(environment, model, learned, controller, baseline, p_value)


def beats_verdict(comparisons: list[Comparison]) -> str:
    """The verdict on "every learned model beats move_base": "yes" when every learned model's
    rate is higher with p < `ALPHA`; "no" when some learned model's rate is not higher; "not
    significant" when all are higher but some p >= `ALPHA`.

    Requiring every pair to pass at `ALPHA` is an intersection-union test: the claim about all
    of them together is tested at level `ALPHA`, with no correction for their number.
    """
    if not all(c.learned.rate > c.baseline.rate for c in comparisons):
        return "no"
    return "yes" if all(c.beats for c in comparisons) else "not significant"


def verdict_rule(alpha: float = ALPHA) -> str:
    """The rule of `beats_verdict` as the results page states it."""
    return (f"Verdict on \"beats move_base\": each learned model is compared with the classical controller in its own "
            f"environment, pair by pair, by a two-sided Boschloo exact test (`scipy.stats.boschloo_exact`; the "
            f"2x2 table of successes and failures of the two groups). 'yes' when every learned model's success "
            f"rate is higher and every pair's p < {alpha:g}; 'no' when some learned model's rate is not higher; "
            f"'not significant' when all are higher but some p >= {alpha:g}. Requiring every pair to pass is an "
            f"intersection-union test, so the claim about all of them is tested at level {alpha:g} without a "
            "correction for their number. Why Boschloo: it is exact (a z-test's normal approximation fails with 30 "
            "rollouts a group and rates at 0 or 1), unconditional (each group's rollouts are fixed by the design, "
            "the total of successes is not, which Fisher's test conditions on), and uniformly more powerful than "
            "Fisher's exact test. Both groups all successes or all failures: p = 1.")


@dataclass(frozen=True)
class PairedComparison:
    """Two runs on the same rollouts (matched by environment, task and seed).

    Attributes:
        matched: rollouts that both runs recorded an outcome of.
        both, neither: matched rollouts that both, or neither, reached the goal.
        only_a, only_b: matched rollouts that only the first, or only the second, reached it.
        unmatched_a, unmatched_b: rollouts with an outcome in one run only (left out).
        p_value: two-sided p of "either run is as likely to be the one that succeeds where the
            two differ": McNemar's exact test, a binomial test of `only_a` in `only_a + only_b`
            at 1/2 (1.0 where they never differ).
    """

    matched: int
    both: int
    neither: int
    only_a: int
    only_b: int
    unmatched_a: int
    unmatched_b: int
    p_value: float


def paired_comparison(a: list, b: list) -> PairedComparison:
    """McNemar's exact test of two runs' records (`RolloutRecord`s) on the rollouts both have an
    outcome of. Paired, it sees what two Wilson intervals cannot: on the same ditches, tasks and
    seeds most outcomes agree, and only the rollouts where they differ carry the comparison."""
    def outcomes(records) -> dict:
        return {(r.environment, r.task, r.seed): r.success for r in records if not r.is_error}

    first, second = outcomes(a), outcomes(b)
    keys = first.keys() & second.keys()
    only_a = sum(first[k] and not second[k] for k in keys)
    only_b = sum(second[k] and not first[k] for k in keys)
    both = sum(first[k] and second[k] for k in keys)
    differ = only_a + only_b
    return PairedComparison(matched=len(keys), both=both, neither=len(keys) - both - differ, only_a=only_a,
                            only_b=only_b, unmatched_a=len(first.keys() - keys), unmatched_b=len(second.keys() - keys),
                            p_value=binomtest(only_a, differ).pvalue if differ else 1.0)
