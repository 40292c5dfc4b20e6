"""The ensemble's uncertainty signals on hand-made probabilities, and thresholds from a budget."""

import math

import numpy as np
import pytest

from ditch_drake.common.errors import ConfigError
from ditch_drake.learning.uncertainty import (
    DISAGREEMENT_SIGNALS,
    UNCERTAINTY_SIGNALS,
    angular_rate_spread,
    mean_softmax_entropy,
    threshold_for_budget,
    uncertainty_signal,
    vote_entropy,
)
from ditch_drake.spec import actions

RATES = actions.ANGULAR_RATES_RADPS


def _one_hot(labels) -> np.ndarray:
    """(K, 17) certain members voting `labels`."""
    return np.eye(actions.NUM_LABELS)[list(labels)]


def test_agreeing_members_have_no_uncertainty_and_opposing_ones_the_most():
    agree = _one_hot([8, 8, 8, 8])
    assert angular_rate_spread(agree, RATES) == 0.0
    assert vote_entropy(agree, RATES) == 0.0
    assert mean_softmax_entropy(agree, RATES) == 0.0
    # Two members turning hard left, two hard right: spread = |w|, vote entropy log 2.
    opposed = _one_hot([0, 0, 16, 16])
    assert angular_rate_spread(opposed, RATES) == pytest.approx(abs(RATES[0]))
    assert vote_entropy(opposed, RATES) == pytest.approx(math.log(2))
    # Neighbouring labels disagree in votes as much as opposite ones, but barely in rate.
    neighbours = _one_hot([8, 8, 9, 9])
    assert vote_entropy(neighbours, RATES) == pytest.approx(math.log(2))
    assert angular_rate_spread(neighbours, RATES) == pytest.approx(RATES[9] / 2)
    assert angular_rate_spread(neighbours, RATES) < angular_rate_spread(opposed, RATES) / 5


def test_the_signals_by_hand_on_a_batch():
    # Member 0 sure of label 8; member 1 split between labels 7 and 10, preferring 10.
    first = _one_hot([8])[0]
    second = np.zeros(17)
    second[[7, 10]] = [0.4, 0.6]
    probabilities = np.stack([np.stack([first, first]), np.stack([second, first])])  # (K=2, B=2, 17)
    assert probabilities.shape == (2, 2, 17)
    np.testing.assert_allclose(angular_rate_spread(probabilities, RATES), [np.std([0.0, RATES[10]]), 0.0])
    np.testing.assert_allclose(vote_entropy(probabilities, RATES), [math.log(2), 0.0])
    split = -(0.4 * math.log(0.4) + 0.6 * math.log(0.6))
    np.testing.assert_allclose(mean_softmax_entropy(probabilities, RATES), [split / 2, 0.0])
    uniform = np.full((3, 17), 1 / 17)
    assert mean_softmax_entropy(uniform, RATES) == pytest.approx(math.log(17))


def test_the_registry_and_bad_inputs():
    assert set(UNCERTAINTY_SIGNALS) == {"angular_rate_spread", "vote_entropy", "mean_softmax_entropy"}
    assert DISAGREEMENT_SIGNALS <= set(UNCERTAINTY_SIGNALS)
    assert uncertainty_signal("vote_entropy") is vote_entropy
    with pytest.raises(ConfigError, match="'spread'.*expected one of"):
        uncertainty_signal("spread")
    single = _one_hot([3])
    assert mean_softmax_entropy(single, RATES) == 0.0  # One clone has its own entropy ...
    for name in DISAGREEMENT_SIGNALS:  # ... but no disagreement.
        with pytest.raises(ConfigError, match="1 member.*at least 2"):
            UNCERTAINTY_SIGNALS[name](single, RATES)
    with pytest.raises(ConfigError, match=r"one per label \(17,\)"):
        angular_rate_spread(_one_hot([1, 2]), RATES[:5])


def test_a_budget_gives_the_quantile_that_hands_over_that_share():
    values = np.arange(100.0)
    threshold = threshold_for_budget(values, 0.05)
    assert threshold == pytest.approx(np.quantile(values, 0.95))
    assert np.mean(values > threshold) == pytest.approx(0.05)
    rng = np.random.default_rng(0)
    spreads = rng.gamma(2.0, 0.1, 5000)
    for budget in (0.01, 0.02, 0.1, 0.2):
        assert np.mean(spreads > threshold_for_budget(spreads, budget)) == pytest.approx(budget, abs=1e-3)
    assert threshold_for_budget(values, 0) == math.inf  # Never hands over.
    assert threshold_for_budget(values, 1) == -math.inf  # Always does.
    for bad in (-0.01, 1.5, math.nan, True, "0.1"):
        with pytest.raises(ConfigError, match=f"budget {bad!r}: expected a share of control steps in \\[0, 1\\]"):
            threshold_for_budget(values, bad)
    with pytest.raises(ConfigError, match="no signal values"):
        threshold_for_budget([], 0.1)
    with pytest.raises(ConfigError, match="1 of 3 signal values are not finite"):
        threshold_for_budget([0.1, math.nan, 0.2], 0.1)
