"""How unsure an ensemble of clones is of a state: signals of its members' probabilities.

Every signal takes the members' softmax probabilities, shape (K, ..., labels) (members first,
labels last; any batch axes between), and the action table's angular rates (labels,) in rad/s,
and returns one value per batch entry, shape (...). Higher is less sure.

- `angular_rate_spread` (rad/s): the standard deviation over the members of the angular rate
  each one commands (the rate of its most probable label). It respects the labels' order:
  members choosing neighbouring turn rates barely disagree, members turning opposite ways (the
  fluctuation between two opposing actions that the paper saw before a rollover) disagree most.
- `vote_entropy` (nats): the entropy of the members' votes (each member's most probable label),
  0 when all agree, log K at most.
- `mean_softmax_entropy` (nats): the mean over the members of each one's own softmax entropy,
  its spread over the labels; 0 for certain members, log(labels) at most. The only one that a
  single clone (K = 1) has.

`threshold_for_budget` turns a budget (the share of control steps a fallback may drive) into
the threshold that hands over that share of the steps a signal was measured on: ThriftyDAgger's
rule for its novelty threshold.
"""

import math
from collections.abc import Callable

import numpy as np

from ditch_drake.common.errors import ConfigError


def _check(probabilities, angular_rates, min_members: int) -> tuple[np.ndarray, np.ndarray]:
    """The inputs as float arrays.

    Raises:
        ConfigError: fewer than `min_members` members, or shapes that do not fit.
    """
    probabilities = np.asarray(probabilities, dtype=float)
    angular_rates = np.asarray(angular_rates, dtype=float)
    if probabilities.ndim < 2:
        raise ConfigError(f"probabilities of shape {probabilities.shape}; expected (members, ..., labels)")
    if probabilities.shape[0] < min_members:
        raise ConfigError(f"{probabilities.shape[0]} member(s); this signal needs at least {min_members} (it is "
                          "their disagreement)")
    if angular_rates.shape != (probabilities.shape[-1],):
        raise ConfigError(f"angular rates of shape {angular_rates.shape}; expected one per label "
                          f"({probabilities.shape[-1]},)")
    return probabilities, angular_rates


def angular_rate_spread(probabilities, angular_rates) -> np.ndarray:
    """Standard deviation over the members of each one's commanded angular rate (rad/s).

    Raises:
        ConfigError: fewer than two members, or shapes that do not fit.
    """
    probabilities, angular_rates = _check(probabilities, angular_rates, 2)
    return angular_rates[np.argmax(probabilities, axis=-1)].std(axis=0)


def vote_entropy(probabilities, angular_rates=None) -> np.ndarray:
    """Entropy (nats) of the members' votes for their most probable labels.

    Raises:
        ConfigError: fewer than two members, or shapes that do not fit.
    """
    probabilities = np.asarray(probabilities, dtype=float)
    rates = np.zeros(probabilities.shape[-1]) if angular_rates is None else angular_rates
    probabilities, _ = _check(probabilities, rates, 2)
    members, labels = probabilities.shape[0], probabilities.shape[-1]
    votes = np.argmax(probabilities, axis=-1)
    shares = (votes[..., None] == np.arange(labels)).sum(axis=0) / members
    return _entropy(shares)


def mean_softmax_entropy(probabilities, angular_rates=None) -> np.ndarray:
    """Mean over the members of each one's softmax entropy (nats).

    Raises:
        ConfigError: no members, or shapes that do not fit.
    """
    probabilities = np.asarray(probabilities, dtype=float)
    rates = np.zeros(probabilities.shape[-1]) if angular_rates is None else angular_rates
    probabilities, _ = _check(probabilities, rates, 1)
    return _entropy(probabilities).mean(axis=0)


def _entropy(shares: np.ndarray) -> np.ndarray:
    """-sum p log p over the last axis, with 0 log 0 = 0."""
    logs = np.log(np.where(shares > 0, shares, 1.0))
    return -(shares * logs).sum(axis=-1)


# The signals by the names that configs use (`SharedControlConfig.signal`).
UNCERTAINTY_SIGNALS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "angular_rate_spread": angular_rate_spread,
    "vote_entropy": vote_entropy,
    "mean_softmax_entropy": mean_softmax_entropy,
}
# Those that are the members' disagreement, so need an ensemble (K >= 2).
DISAGREEMENT_SIGNALS = frozenset({"angular_rate_spread", "vote_entropy"})
# The control for a gate's study: the gate reads a seeded uniform draw in [0, 1) each control
# step in place of the policy's uncertainty, so it hands over by chance, not by what the policy knows.
RANDOM_SIGNAL = "random"
# Signals of the robot's state, not of the members: minus the tip margin now and along the
# policy's commanded arc on the perceived map (deg; `ditch_drake.systems.tip_risk`).
RISK_SIGNALS = ("tip_risk_now", "tip_risk_ahead")
# A signal of the policy's commands over time, not of one view: how often its turn reversed over
# the last second (`ditch_drake.systems.command_reversals`), the paper's symptom of an unfamiliar state.
REVERSAL_SIGNAL = "command_reversals"
# A signal of the robot's progress, from its pose and goal alone: the seconds since it last came
# nearer the goal (`ditch_drake.systems.goal_progress`), for the failures after the crossing.
PROGRESS_SIGNAL = "seconds_without_progress"
# Its companion in metres: the most the robot has fallen back from the goal since it last came
# nearer, for a policy that drives away from its goal after the crossing.
REGRESS_SIGNAL = "metres_regressed"
# What a shared-control gate may read (`SharedControlConfig.signal`): the policy's uncertainty
# signals, the risk signals, the reversals, the progress, or the draw.
GATE_SIGNALS = (*UNCERTAINTY_SIGNALS, *RISK_SIGNALS, REVERSAL_SIGNAL, PROGRESS_SIGNAL, REGRESS_SIGNAL, RANDOM_SIGNAL)
# The unit each of them is in, for a table's or a figure's label.
SIGNAL_UNITS = {"angular_rate_spread": "rad/s", "vote_entropy": "nats", "mean_softmax_entropy": "nats",
                "tip_risk_now": "deg", "tip_risk_ahead": "deg", REVERSAL_SIGNAL: "reversals in 1 s",
                PROGRESS_SIGNAL: "s", REGRESS_SIGNAL: "m", RANDOM_SIGNAL: "draw in [0, 1)"}


def uncertainty_signal(name: str) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """The signal called `name`.

    Raises:
        ConfigError: an unknown name, listing the known ones.
    """
    if name not in UNCERTAINTY_SIGNALS:
        raise ConfigError(f"uncertainty signal {name!r}: expected one of {list(UNCERTAINTY_SIGNALS)}")
    return UNCERTAINTY_SIGNALS[name]


def check_budget(budget, what: str = "budget") -> float:
    """`budget` as a float in [0, 1].

    Raises:
        ConfigError: anything else (NaN, a bool, a string), naming the value.
    """
    if isinstance(budget, bool) or not isinstance(budget, (int, float, np.integer, np.floating)) or not (
            0.0 <= float(budget) <= 1.0):
        raise ConfigError(f"{what} {budget!r}: expected a share of control steps in [0, 1]")
    return float(budget)


def threshold_for_budget(signal_values, budget: float) -> float:
    """The upper threshold that hands over `budget` of the steps whose signal was `signal_values`.

    The gate hands over where the signal is above the threshold, so the threshold is the
    (1 - budget) quantile of the values (numpy's linear interpolation): over the values it came
    from, a share of about `budget` lies above it (exactly, where the values are distinct and
    budget * N is whole; a signal of few distinct values, as vote entropy is, hands over the
    share of the values above the quantile, which ties can make less). Budget 0 gives +inf (it
    never hands over), budget 1 gives -inf (it always does).

    Args:
        signal_values: the signal over the policy's own validation rollouts, one value per
            control step (any shape).
        budget: the share of control steps to hand over, in [0, 1].

    Raises:
        ConfigError: a budget outside [0, 1], or no values, or values that are not finite.
    """
    budget = check_budget(budget)
    values = np.asarray(signal_values, dtype=float).ravel()
    if values.size == 0:
        raise ConfigError("no signal values to set a threshold from; expected one per control step of the "
                          "validation rollouts")
    if not np.all(np.isfinite(values)):
        raise ConfigError(f"{int(np.sum(~np.isfinite(values)))} of {values.size} signal values are not finite; "
                          "expected finite values")
    if budget == 0.0:
        return math.inf
    if budget == 1.0:
        return -math.inf
    return float(np.quantile(values, 1.0 - budget))
