"""Which uncertainty signal foresees a failure, and the gate's thresholds from a budget.

A signals file (`ditch-drake gate-signals`, `save_signals`) holds, for every control step of
the learned policy's own validation rollouts (the policy driving, ungated), every uncertainty
signal its checkpoint has (`ditch_drake.learning.uncertainty`), the step's time, and each
episode's outcome and end time. From it:

- `failure_labels`: a step is positive where its episode ends rolled over within `horizon_s`
  after it;
- `roc_auc`: how well a signal ranks the positive steps above the others (the Mann-Whitney U
  over the product of the class sizes: 1 a perfect predictor, 0.5 one that knows nothing),
  with `bootstrap_auc_interval` resampling whole episodes, since the steps of one episode are
  far from independent;
- `budget_thresholds`: ThriftyDAgger's rule with the gate's hysteresis counted in: the
  thresholds are the (1 - s) and (1 - 2 s) quantiles of the signal over the recorded steps
  (`quantile_thresholds`), at the largest share s for which the gate, replayed over each
  recorded episode in order (`replay_fallback_share`, the same rule as the `SharedControl`
  block's, `gate_step`), hands the fallback at most `budget` of the steps. The quantiles alone
  (s = budget) ignore that the fallback keeps control until the signal has stayed low for
  `calm_steps`: on the paper clones' validation rollouts, budget 0.1 handed over 12-24 % of the
  steps at seeds 300-309.
"""

import json
import math
import os
from pathlib import Path

import numpy as np

from ditch_drake.common.errors import ConfigError
from ditch_drake.common.files import atomic_output, atomic_write_text
from ditch_drake.learning.uncertainty import threshold_for_budget

# The episode status that counts as the failure a gate should foresee (`EpisodeStatus`).
ROLLED_OVER = "rolled_over"
# A step is labelled a coming failure where its episode rolls over within this long after it:
# about the last two metres at the policy's speed, when a fallback can still turn away.
FAILURE_HORIZON_S = 2.0
# Bootstrap resamples of the episodes for the AUC's interval, and the interval's coverage.
BOOTSTRAP_RESAMPLES = 2000
CONFIDENCE = 0.95
# The schema of a signals file, written into it (`save_signals`).
SIGNALS_SCHEMA = "ditch_drake.gate_signals"
SIGNALS_VERSION = 1
# The arrays of a signals file besides one per signal (named by the signal), N steps and E episodes.
STEP_ARRAYS = ("time_s", "episode")
EPISODE_ARRAYS = ("episode_environment", "episode_task", "episode_seed", "episode_status", "episode_end_time_s")
# Who drives, as the gate's `who_drives` output says it.
POLICY, FALLBACK = 0, 1
# Halvings of the share s in `budget_thresholds`' search: s to within 2^-40.
SHARE_SEARCH_STEPS = 40


def failure_labels(time_s, episode, end_time_s, status, horizon_s: float = FAILURE_HORIZON_S) -> np.ndarray:
    """Whether each step's episode ends rolled over within `horizon_s` after the step.

    Args:
        time_s: (N,) each step's time (s).
        episode: (N,) each step's episode index into `end_time_s` and `status`.
        end_time_s: (E,) when each episode ended (s).
        status: (E,) each episode's outcome (`EpisodeStatus` names, lower case).
        horizon_s: how long before the rollover a step counts (s).

    Returns:
        (N,) bool.
    """
    time_s, episode = np.asarray(time_s, dtype=float), np.asarray(episode, dtype=int)
    end_time_s = np.asarray(end_time_s, dtype=float)
    rolled = np.asarray(status) == ROLLED_OVER
    # A nanosecond's slack: step times are sums of periods, and one on the horizon counts.
    return rolled[episode] & (end_time_s[episode] - time_s <= horizon_s + 1e-9)


def roc_auc(scores, labels) -> float:
    """The ROC AUC of `scores` for the positive `labels`: the chance that a positive step's score
    is above a negative one's, ties counted half (Mann-Whitney U / (positives x negatives)).
    NaN where either class is empty."""
    from scipy.stats import mannwhitneyu  # Here: the gate imports this module, and scipy takes a while.

    scores, labels = np.asarray(scores, dtype=float), np.asarray(labels, dtype=bool)
    positives, negatives = scores[labels], scores[~labels]
    if positives.size == 0 or negatives.size == 0:
        return math.nan
    statistic = mannwhitneyu(positives, negatives, alternative="two-sided", method="asymptotic").statistic
    return float(statistic) / (positives.size * negatives.size)


def bootstrap_auc_interval(scores, labels, episode, seed: int = 0, resamples: int = BOOTSTRAP_RESAMPLES,
                           confidence: float = CONFIDENCE) -> tuple[float, float, int]:
    """A percentile bootstrap interval of `roc_auc`, resampling whole episodes with replacement.

    Returns:
        (low, high, used): the interval, and how many resamples had both classes (the others
        have no AUC and are left out); (nan, nan, 0) where none had.
    """
    scores, labels = np.asarray(scores, dtype=float), np.asarray(labels, dtype=bool)
    episode = np.asarray(episode, dtype=int)
    episodes = np.unique(episode)
    steps = [np.flatnonzero(episode == e) for e in episodes]
    generator = np.random.default_rng(seed)
    values = []
    for _ in range(resamples):
        chosen = np.concatenate([steps[i] for i in generator.integers(0, len(episodes), len(episodes))])
        value = roc_auc(scores[chosen], labels[chosen])
        if not math.isnan(value):
            values.append(value)
    if not values:
        return math.nan, math.nan, 0
    tail = 100.0 * (1.0 - confidence) / 2.0
    low, high = np.percentile(values, [tail, 100.0 - tail])
    return float(low), float(high), len(values)


def signal_aucs(signals: dict, horizon_s: float = FAILURE_HORIZON_S, seed: int = 0,
                resamples: int = BOOTSTRAP_RESAMPLES) -> list[dict]:
    """One row per signal of a signals file's contents (`load_signals`): the AUC of "a rollover
    within `horizon_s`", its bootstrap interval, and the counts it rests on."""
    labels = failure_labels(signals["time_s"], signals["episode"], signals["episode_end_time_s"],
                            signals["episode_status"], horizon_s)
    rolled = int(np.sum(np.asarray(signals["episode_status"]) == ROLLED_OVER))
    rows = []
    for name in signals["signals"]:
        low, high, used = bootstrap_auc_interval(signals[name], labels, signals["episode"], seed, resamples)
        rows.append({"signal": str(name), "auc": roc_auc(signals[name], labels), "ci_low": low, "ci_high": high,
                     "bootstrap_resamples": used, "positive_steps": int(labels.sum()), "steps": int(labels.size),
                     "rolled_over_episodes": rolled, "episodes": len(signals["episode_status"])})
    return rows


def auc_report(signals: dict, horizon_s: float = FAILURE_HORIZON_S, seed: int = 0,
               resamples: int = BOOTSTRAP_RESAMPLES) -> dict:
    """The JSON beside a signals file: what was measured (`signal_aucs`) and how."""
    return {"schema": f"{SIGNALS_SCHEMA}.auc", "version": SIGNALS_VERSION, "checkpoint": str(signals["checkpoint"]),
            "checkpoint_sha256": str(signals["checkpoint_sha256"]), "horizon_s": horizon_s,
            "confidence": CONFIDENCE, "bootstrap": "episodes resampled with replacement", "bootstrap_seed": seed,
            "rows": signal_aucs(signals, horizon_s, seed, resamples)}


def gate_step(driver: int, calm: int, uncertainty: float, upper_threshold: float, lower_threshold: float,
              calm_steps: int, forced: bool = False) -> tuple[int, int, bool]:
    """One control step of the gate's hysteresis (`ditch_drake.systems.shared_control.SharedControl`).

    While the policy drives, an uncertainty above `upper_threshold` hands over to the fallback.
    While the fallback drives, a step below `lower_threshold` counts one calm step and any other
    step (a NaN too) resets the count; the step on which it reaches `calm_steps` hands back.
    A `forced` step (one of the gate's watchdogs firing) hands over whatever the uncertainty,
    and is never calm.

    Args:
        driver: who drove the step before, `POLICY` or `FALLBACK`.
        calm: calm steps counted so far.
        uncertainty: this step's signal.
        forced: whether something besides the signal demands the fallback at this step.

    Returns:
        (who drives this step, the calm count after it, whether it switched).
    """
    if driver == POLICY:
        if forced or uncertainty > upper_threshold:
            return FALLBACK, 0, True
        return POLICY, calm, False
    calm = calm + 1 if uncertainty < lower_threshold and not forced else 0
    if calm >= calm_steps:
        return POLICY, 0, True
    return FALLBACK, calm, False


def replay_fallback_share(sequences, upper_threshold: float, lower_threshold: float, calm_steps: int,
                          warmup_steps: int = 0) -> float:
    """The share of the steps the gate hands the fallback, replayed over recorded episodes.

    Each sequence is one episode's signal, step by step, as the policy saw it driving alone;
    the gate starts each with the policy driving and reads the first `warmup_steps` values as
    NaN (it ignores them, as `SharedControl` does). A replay is an estimate: once the fallback
    drives, the real robot goes elsewhere than the recorded one.

    Args:
        sequences: one (T_e,) array of the signal per episode.
        upper_threshold, lower_threshold, calm_steps: the gate's (`gate_step`).
        warmup_steps: control steps at each episode's start whose signal the gate ignores.
    """
    fallback_steps = total_steps = 0
    for sequence in sequences:
        driver, calm = POLICY, 0
        for step, value in enumerate(np.asarray(sequence, dtype=float).tolist()):
            value = math.nan if step < warmup_steps else value
            driver, calm, _ = gate_step(driver, calm, value, upper_threshold, lower_threshold, calm_steps)
            fallback_steps += driver
        total_steps += len(sequence)
    return fallback_steps / total_steps if total_steps else 0.0


def rollover_warnings(signals: dict, signal: str, upper_threshold: float, lower_threshold: float, calm_steps: int,
                      warmup_steps: int = 0) -> np.ndarray:
    """How long before each recorded rollover the gate, replayed over the episode, had handed
    over: the time (s) from the start of the fallback's last spell to the episode's end, where
    the fallback drives the last recorded step; NaN where the policy does (the gate never
    handed over, or handed back before the end). The time a fallback would have had to recover,
    on the path the policy alone took (after a real handover the robot goes elsewhere).

    Args:
        signals: a signals file as `load_signals` reads it.
        signal: the signal the gate reads (one the file recorded).
        upper_threshold, lower_threshold, calm_steps, warmup_steps: the gate's (`gate_step`).

    Returns:
        One time per episode that rolled over, in episode order.
    """
    warnings = []
    for times, values, end_time in _rolled_over_episodes(signals, signal):
        driver, calm, spell_start = POLICY, 0, math.nan
        for step, (value, time) in enumerate(zip(values.tolist(), times.tolist())):
            value = math.nan if step < warmup_steps else value
            driver, calm, switched = gate_step(driver, calm, value, upper_threshold, lower_threshold, calm_steps)
            if switched:
                spell_start = time if driver == FALLBACK else math.nan
        warnings.append(end_time - spell_start)
    return np.asarray(warnings, dtype=float)


def signal_before_rollovers(signals: dict, signal: str, window_s: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """What a gate reading `signal` saw coming: for each episode that rolled over, in episode
    order, its steps within `window_s` (> 0) of the episode's end as (time before the end (s,
    <= 0), the signal's value), in time order. On the path the policy alone took, as
    `rollover_warnings`.
    """
    traces = []
    for times, values, end_time in _rolled_over_episodes(signals, signal):
        before = times - end_time
        kept = before >= -window_s
        traces.append((before[kept], values[kept]))
    return traces


def _rolled_over_episodes(signals: dict, signal: str):
    """Each episode of a signals file that rolled over, in episode order, as (its steps' times
    (s), `signal` at them, in time order; the episode's end time (s))."""
    for index, times, values in _episodes(signals, signal):
        if signals["episode_status"][index] == ROLLED_OVER:
            yield times, values, float(signals["episode_end_time_s"][index])


def _episodes(signals: dict, signal: str):
    """Every episode of a signals file, in episode order, as (its index, its steps' times (s),
    `signal` at them, in time order)."""
    values, times = np.asarray(signals[signal], dtype=float), np.asarray(signals["time_s"], dtype=float)
    episode = np.asarray(signals["episode"], dtype=int)
    for index in range(len(signals["episode_status"])):
        steps = np.flatnonzero(episode == index)
        steps = steps[np.argsort(times[steps], kind="stable")]
        yield index, times[steps], values[steps]


def episode_peaks(signals: dict, signal: str, warmup_steps: int = 0) -> list[dict]:
    """`signal`'s largest value in each episode of a signals file, by how the episodes ended: one
    row per outcome (in the order of first appearance), with how many episodes ended so and the
    least, median and largest of their peaks. The first `warmup_steps` of each episode are left
    out, as the gate ignores them. What a fixed threshold on a signal that grows while something
    goes wrong (a watchdog's) must lie between: above the peaks of the episodes that succeeded,
    below those of the ones that failed.

    Raises:
        ConfigError: the file has no `signal`.
    """
    if signal not in signals["signals"]:
        raise ConfigError(f"signals file has no signal {signal!r}: it recorded {signals['signals']}")
    peaks: dict[str, list[float]] = {}
    for index, _, values in _episodes(signals, signal):
        kept = values[warmup_steps:]
        peaks.setdefault(str(signals["episode_status"][index]), []).append(float(kept.max()) if kept.size else math.nan)
    return [{"signal": signal, "status": status, "episodes": len(found), "least_peak": float(np.min(found)),
             "median_peak": float(np.median(found)), "largest_peak": float(np.max(found))}
            for status, found in peaks.items()]


def quantile_thresholds(values, share: float) -> tuple[float, float]:
    """(upper, lower): the (1 - share) quantile of `values` (`threshold_for_budget`), above which
    `share` of them lie, and the (1 - 2 share) quantile, the smallest value for shares of 0.5
    or more. A quantile of the signal's own distribution, not a ratio of the upper threshold,
    so the band means the same for every signal, unit and model: a single clone's softmax
    entropy never falls near 0 (the shipped `wide`'s median is about 1 nat), so a fixed ratio
    would put the lower threshold in the bulk for one model and in the tail for another."""
    upper = threshold_for_budget(values, share)
    lower = float(np.quantile(np.asarray(values, dtype=float).ravel(), max(0.0, 1.0 - 2.0 * share)))
    return upper, min(lower, upper)


def budget_thresholds(sequences, budget: float, calm_steps: int = 1, warmup_steps: int = 0) -> tuple[float, float]:
    """The gate's (upper, lower) thresholds that a budget sets on a signal's recorded episodes.

    `quantile_thresholds` at the largest share s (found by bisection, `SHARE_SEARCH_STEPS`
    halvings) for which the gate with `calm_steps`, replayed over the episodes
    (`replay_fallback_share`), hands the fallback at most `budget` of their steps. The replayed
    share grows with s (both thresholds fall), and the hysteresis makes s smaller than the
    budget: each handover holds the fallback for at least `calm_steps`.

    Args:
        sequences: one array of the signal per recorded episode, in step order (a single 1-D
            numpy array is one episode).
        budget: the share of control steps the fallback may drive, in (0, 1).
        calm_steps: the gate's hysteresis (`SharedControlConfig.calm_steps`).
        warmup_steps: control steps at each episode's start whose signal the gate ignores
            (`SharedControlConfig.warmup_steps`); their values count in no quantile either.

    Raises:
        ConfigError: a budget outside (0, 1), no values, or values that are not finite.
    """
    if isinstance(budget, bool) or not isinstance(budget, (int, float)) or not 0.0 < budget < 1.0:
        raise ConfigError(f"budget {budget!r}: expected a share of control steps in (0, 1)")
    if isinstance(sequences, np.ndarray) and sequences.ndim == 1:
        sequences = [sequences]
    sequences = [np.asarray(sequence, dtype=float).ravel() for sequence in sequences]
    values = np.concatenate([sequence[warmup_steps:] for sequence in sequences]) if sequences else np.zeros(0)
    threshold_for_budget(values, budget)  # Refuses no values or non-finite ones, as the quantiles would.
    low, high = 0.0, 1.0  # Replayed shares: 0 at s = 0 (never hands over), 1 at s = 1 (always does).
    for _ in range(SHARE_SEARCH_STEPS):
        middle = (low + high) / 2.0
        if replay_fallback_share(sequences, *quantile_thresholds(values, middle), calm_steps, warmup_steps) <= budget:
            low = middle
        else:
            high = middle
    return quantile_thresholds(values, low)


def save_signals(path: str | os.PathLike, checkpoint: str, checkpoint_sha256: str, signals: dict[str, np.ndarray],
                 steps: dict[str, np.ndarray], episodes: dict[str, list],
                 tip_risk_horizon_s: float | None = None) -> Path:
    """Writes a signals file atomically (.npz, no pickled objects).

    Args:
        signals: each signal's values, (N,) by name.
        steps: `STEP_ARRAYS`, (N,) each.
        episodes: `EPISODE_ARRAYS`, (E,) each.
        tip_risk_horizon_s: with the tip-risk signals, how long their commanded arcs were
            held (s), kept as "tip_risk_horizon_s" (a file without it was recorded at the
            default, 2 s).
    """
    arrays = {"schema": np.array(SIGNALS_SCHEMA), "version": np.array(SIGNALS_VERSION),
              "checkpoint": np.array(checkpoint), "checkpoint_sha256": np.array(checkpoint_sha256),
              "signals": np.array(list(signals), dtype=str),
              "time_s": np.asarray(steps["time_s"], dtype=float), "episode": np.asarray(steps["episode"], dtype=int),
              "episode_environment": np.array(episodes["episode_environment"], dtype=str),
              "episode_task": np.asarray(episodes["episode_task"], dtype=int),
              "episode_seed": np.asarray(episodes["episode_seed"], dtype=np.int64),
              "episode_status": np.array(episodes["episode_status"], dtype=str),
              "episode_end_time_s": np.asarray(episodes["episode_end_time_s"], dtype=float),
              **{name: np.asarray(values, dtype=float) for name, values in signals.items()}}
    if tip_risk_horizon_s is not None:
        arrays["tip_risk_horizon_s"] = np.array(float(tip_risk_horizon_s))
    with atomic_output(path) as file:
        np.savez(file, **arrays)
    return Path(path)


def load_signals(path: str | os.PathLike, what: str = "signals file") -> dict:
    """A signals file's arrays by name ("signals": the signal names, a list of str; the scalars as
    Python values).

    Raises:
        ConfigError: no such file, or not a signals file, naming `what` and the path.
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError) as error:
        raise ConfigError(f"{what} {path!s}: cannot read it ({error}); expected a .npz of ditch-drake "
                          "gate-signals") from error
    missing = [name for name in ("schema", "signals", *STEP_ARRAYS, *EPISODE_ARRAYS) if name not in arrays]
    if missing or str(arrays["schema"]) != SIGNALS_SCHEMA:
        raise ConfigError(f"{what} {path!s}: not a signals file (missing {missing or ['its schema']}); expected a "
                          ".npz of ditch-drake gate-signals")
    arrays["signals"] = [str(name) for name in arrays["signals"]]
    for name in ("schema", "checkpoint", "checkpoint_sha256"):
        arrays[name] = str(arrays.get(name, ""))
    if "tip_risk_horizon_s" in arrays:
        arrays["tip_risk_horizon_s"] = float(arrays["tip_risk_horizon_s"])
    return arrays


def calibration_values(path: str | os.PathLike, signal: str, what: str = "gate.calibration") -> list[np.ndarray]:
    """The values of `signal` over the steps a signals file recorded, one array per episode in
    step order.

    Raises:
        ConfigError: no such readable signals file, or one without `signal` (naming the ones it
            has: a single clone's has only "mean_softmax_entropy"), naming `what`.
    """
    signals = load_signals(path, what)
    if signal not in signals["signals"]:
        raise ConfigError(f"{what} {path!s} has no signal {signal!r}: it recorded {signals['signals']}; expected a "
                          "file of the gated policy (an ensemble's for the disagreement signals, one recorded with "
                          "gate-signals --risk for the risk signals, one recorded since gate-signals records "
                          "command_reversals, seconds_without_progress or metres_regressed for those signals: "
                          "record it again)")
    values, episode = np.asarray(signals[signal], dtype=float), np.asarray(signals["episode"], dtype=int)
    order = np.lexsort((np.asarray(signals["time_s"], dtype=float), episode))
    values, episode = values[order], episode[order]
    return np.split(values, np.flatnonzero(np.diff(episode)) + 1) if values.size else []


def write_auc_report(path: str | os.PathLike, report: dict) -> Path:
    """Writes `auc_report`'s JSON atomically (NaN as null)."""
    return atomic_write_text(path, json.dumps(_nan_as_none(report), indent=2) + "\n")


def _nan_as_none(value):
    if isinstance(value, dict):
        return {key: _nan_as_none(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_nan_as_none(item) for item in value]
    if isinstance(value, float) and math.isnan(value):
        return None
    return value

