"""How the results pages name the controllers of records: a checkpoint by its file stem (its
folder too where stems clash), and the experiment's `<environments>_<N>` models parsed back.

Every results table names its rows by `controller_labels`, which marks a row in one way: the
label, then in brackets where a side-conditioned clone was told its crossing side ("perceived
side", "oracle side": `RolloutRecord.crossing_side_source`), what the controller declared it
reads beyond its sensors, pose and goal ("privileged: analytic terrain":
`RolloutRecord.privileged`), a window search ("window search", "window search, first leg 40 m, way held
0.5 m, off seen drops"),
an MPPI's nose-up threshold where set ("climb margin 11 deg")
and, for a gated policy, its gate's signal, budget and fallback, e.g. "expert (privileged:
analytic terrain)", "generalist (oracle side; privileged: analytic terrain)" or "crater_40_k5
(gate random, budget 0.05, fallback mppi)", "sine_40_k5 (gate tip_risk_ahead, budget 0.02,
watchdog 20 s, fallback expert)". Records that differ in any are different rows.
"""

import itertools
import re
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

from ditch_drake.diagrams.controllers import privileged_words
from ditch_drake.evaluation.results import RolloutRecord
from ditch_drake.learning.uncertainty import SIGNAL_UNITS
from ditch_drake.systems.shared_control import WATCHDOGS, SharedControlConfig
from ditch_drake.systems.window_search import WindowSearchConfig

# What a page says beside a table with a marked row.
MARKS_NOTE = ("A row marked \"privileged: ...\" is a controller that reads what the robot cannot sense (it declares "
              "it, and is given only that): a reference, not a competitor. \"perceived side\" / \"oracle side\": a "
              "side-conditioned clone told its crossing side from the lidar's points, or from the analytic ditch.")
SEARCH_NOTE = ("\"window search\": a controller driven toward the targets of the search for a way in and out "
               "(`WindowSearch`, on a map of the lidar's points).")


def model_label(record: RolloutRecord) -> str:
    """A short name of the controller: the checkpoint's file stem, or the controller."""
    return Path(record.checkpoint).stem if record.checkpoint else record.controller


def searches(record: RolloutRecord) -> bool:
    """Whether the record's controller ran with the window search (a top-level `search:` in its
    config, which is written only when set)."""
    return any(line.startswith("search:") for line in (record.controller_config or "").splitlines())


def search_words(record: RolloutRecord) -> str:
    """A searching record's mark: "window search", with ", first leg 40 m" where its first leg
    was not the default's (`WindowSearchConfig.first_leg_m`), ", way held 0.5 m" where its
    search held a crossing's way along (`hold_way_m`) and ", off seen drops" where it kept off
    the drops it saw (`keep_off_seen_drops`; both written only when set); "" for a record that
    did not search."""
    if not searches(record):
        return ""
    config = record.controller_config or ""
    words = "window search"
    found = re.search(r"first_leg_m: ([-+.0-9eE]+)", config)
    if found and float(found.group(1)) != WindowSearchConfig.first_leg_m:
        words += f", first leg {float(found.group(1)):g} m"
    if found := re.search(r"hold_way_m: ([-+.0-9eE]+)", config):
        words += f", way held {float(found.group(1)):g} m"
    if re.search(r"keep_off_seen_drops: true", config):
        words += ", off seen drops"
    return words


def climb_words(record: RolloutRecord) -> str:
    """An MPPI record's nose-up fore-aft threshold where one was set, e.g. "climb margin 11 deg"
    (`MppiPlannerConfig.climb_fore_aft_margin_threshold_deg`, written only when set); "" otherwise."""
    found = re.search(r"climb_fore_aft_margin_threshold_deg: ([-+.0-9eE]+)", record.controller_config or "")
    return f"climb margin {float(found.group(1)):g} deg" if found else ""


def config_section(record: RolloutRecord, key: str) -> list[str]:
    """The lines of the top-level `key:` of a record's controller config and those indented
    under it; [] where the config has no such key."""
    lines = (record.controller_config or "").splitlines()
    start = next((i for i, line in enumerate(lines) if line.startswith(f"{key}:")), None)
    if start is None:
        return []
    return [lines[start], *itertools.takewhile(lambda line: line.startswith(" "), lines[start + 1:])]


def gate_settings(record: RolloutRecord) -> dict:
    """A shared-control record's gate as its config wrote it (the `gate:` section: "signal",
    "fallback", "budget" where one set the thresholds, ...); {} for any other record."""
    import yaml

    section = config_section(record, "gate")
    if not section:
        return {}
    try:
        gate = yaml.safe_load("\n".join(section))["gate"]
    except yaml.YAMLError:
        return {}
    return gate if isinstance(gate, dict) else {}


def gate_budget(gate: dict) -> float | None:
    """The budget that set a gate's thresholds (`gate_settings`), or None for fixed thresholds."""
    budget = gate.get("budget")
    return float(budget) if isinstance(budget, (int, float)) and not isinstance(budget, bool) else None


# What `record_matches` can select records by: the record's own fields, and a gated record's gate.
RECORD_FIELDS = ("controller", "environment")
GATE_FIELDS = ("signal", "budget", "fallback")


def parse_selection(text: str, option: str) -> dict[str, str]:
    """"signal=random,budget=0.05" as {"signal": "random", "budget": "0.05"}; raises ConfigError
    naming `option` for a term that is not KEY=VALUE with a key of `RECORD_FIELDS` or
    `GATE_FIELDS`, or a budget that is not a number."""
    from ditch_drake.common.errors import ConfigError

    selection = {}
    for term in text.split(","):
        key, equals, value = (part.strip() for part in term.partition("="))
        if not equals or not value or key not in RECORD_FIELDS + GATE_FIELDS:
            raise ConfigError(f"{option} {text!r}: {term.strip()!r} is not KEY=VALUE with KEY one of "
                              f"{', '.join(RECORD_FIELDS + GATE_FIELDS)}")
        if key == "budget":
            try:
                float(value)
            except ValueError:
                raise ConfigError(f"{option} {text!r}: budget {value!r} is not a number") from None
        selection[key] = value
    return selection


def record_matches(record: RolloutRecord, selection: dict[str, str]) -> bool:
    """Whether a record has every value of a `parse_selection`; a gate's key matches only a
    shared-control record whose gate has that value (a budget compared as a number)."""
    gate = gate_settings(record)
    for key, value in selection.items():
        if key in RECORD_FIELDS:
            if str(getattr(record, key)) != value:
                return False
        elif key == "budget":
            if gate_budget(gate) is None or gate_budget(gate) != float(value):
                return False
        elif str(gate.get(key)) != value:
            return False
    return True


# The expert's options (`ExpertVariation`) that change how it takes over, as a row names them.
EXPERT_TAKEOVER_WORDS = {"replan_each_step": "replanning", "keep_facing_side": "keeping the facing side"}


def fallback_words(record: RolloutRecord, gate: dict) -> str:
    """A shared-control record's fallback, e.g. "mppi"; an expert's with the options set in its
    config's `expert:` section that change how it takes over (`EXPERT_TAKEOVER_WORDS`), e.g.
    "expert, replanning" for one that decides its side and phase afresh from the pose it is
    handed rather than keeping the plan it latched before the wall."""
    fallback = str(gate.get("fallback"))
    if fallback != "expert":
        return fallback
    section = config_section(record, "expert")
    options = [words for option, words in EXPERT_TAKEOVER_WORDS.items()
               if any(re.search(rf"\b{option}: true\b", line) for line in section)]
    return ", ".join([fallback, *options])


def signal_words(record: RolloutRecord, gate: dict) -> str:
    """A shared-control record's gate signal, e.g. "angular_rate_spread"; a tip-risk signal on
    arcs of another length than the default with it, e.g. "tip_risk_ahead on 1 s arcs" (the
    `tip_risk:` line of its config's `policy:` section)."""
    import yaml

    from ditch_drake.systems.tip_risk import TipRiskConfig

    signal = str(gate.get("signal"))
    section = config_section(record, "policy")
    try:
        policy = yaml.safe_load("\n".join(section))["policy"] if section else None
    except yaml.YAMLError:
        policy = None
    tip_risk = policy.get("tip_risk") if isinstance(policy, dict) else None
    horizon = tip_risk.get("horizon_s") if isinstance(tip_risk, dict) else None
    if isinstance(horizon, (int, float)) and horizon != TipRiskConfig.horizon_s:
        return f"{signal} on {horizon:g} s arcs"
    return signal


def gate_words(record: RolloutRecord) -> str:
    """A shared-control record's gate: its signal (`signal_words`), budget (where one set the
    thresholds), hold (`hold_words`), watchdogs (where set) and fallback (`fallback_words`), e.g. "gate
    angular_rate_spread, budget 0.05, watchdog 20 s, fallback expert", from the `gate:` line of
    its config; "" for any other record."""
    gate = gate_settings(record)
    if not gate:
        return ""
    budget = f", budget {gate['budget']:g}" if gate_budget(gate) is not None else ""
    return (f"gate {signal_words(record, gate)}{budget}{hold_words(gate)}{watchdog_words(gate)}, "
            f"fallback {fallback_words(record, gate)}")


def hold_words(gate: dict) -> str:
    """A gate's hold before it hands back (`SharedControlConfig.calm_steps`) where it differs
    from the default, e.g. ", 20 calm steps"; "" at the default, so that the rows of every
    gate run before the hold was varied keep their names."""
    calm = gate.get("calm_steps")
    if isinstance(calm, int) and not isinstance(calm, bool) and calm != SharedControlConfig.calm_steps:
        return f", {calm} calm steps"
    return ""


def watchdog_words(gate: dict) -> str:
    """A gate's watchdogs (`SharedControlConfig.progress_limit_s`, `regress_limit_m`), e.g.
    ", watchdog 20 s" or ", watchdog 20 s, 3 m"; "" for a gate without one."""
    limits = [f"{limit:g} {SIGNAL_UNITS[signal]}" for signal, key in WATCHDOGS.items()
              if isinstance(limit := gate.get(key), (int, float)) and not isinstance(limit, bool)]
    return f", watchdog {', '.join(limits)}" if limits else ""


def record_marks(record: RolloutRecord) -> list[str]:
    """What a record's row is marked with: the window search, an MPPI's climb threshold, its
    shared-control gate, its crossing side's source, its privileged inputs."""
    marks = [words] if (words := search_words(record)) else []
    if climb := climb_words(record):
        marks.append(climb)
    if gate := gate_words(record):
        marks.append(gate)
    if record.crossing_side_source:
        marks.append(f"{record.crossing_side_source} side")
    if record.privileged:
        marks.append(f"privileged: {privileged_words(record.privileged)}")
    return marks


def with_marks(name: str, record: RolloutRecord) -> str:
    """`name` followed by `record`'s marks in brackets, if it has any."""
    marks = record_marks(record)
    return f"{name} ({'; '.join(marks)})" if marks else name


def unmarked(label: str) -> str:
    """A `controller_labels` label without its marks ("generalist (oracle side)" -> "generalist")."""
    return label.split(" (", 1)[0]


def label_marks(label: str) -> str:
    """A `controller_labels` label's marks, the rest of `unmarked` ("generalist (oracle side)" ->
    "oracle side"); "" for a label without any."""
    _, bracket, marks = label.partition(" (")
    return marks.removesuffix(")") if bracket else ""


def controller_labels(records: list[RolloutRecord], marks: bool = True) -> Callable[[RolloutRecord], str]:
    """Each record's controller as the page names it: `model_label` (the checkpoint's file
    stem), preceded by its folder where checkpoints of one stem lie in several, followed by its
    `record_marks` in brackets (`with_marks`; unless not `marks`: a table of checkpoints, not of rows)."""
    paths = defaultdict(set)
    for record in records:
        if record.checkpoint:
            paths[model_label(record)].add(record.checkpoint)
    shared = {stem for stem, found in paths.items() if len(found) > 1}

    def label(record: RolloutRecord) -> str:
        stem = model_label(record)
        folder = Path(record.checkpoint).parent.name if stem in shared else ""
        name = f"{folder}/{stem}" if folder else stem
        return with_marks(name, record) if marks else name

    return label


def any_marked(records: list[RolloutRecord]) -> bool:
    """Whether a table of `records` has a marked row (then `marks_note` goes with it)."""
    return any(record_marks(record) for record in records)


def marks_note(records: list[RolloutRecord]) -> str:
    """What a page says beside a table of `records` with a marked row: `MARKS_NOTE`, and
    `SEARCH_NOTE` where a row searched."""
    return f"{MARKS_NOTE} {SEARCH_NOTE}" if any(searches(record) for record in records) else MARKS_NOTE


def model_demos(label: str) -> int | None:
    """N of a model named `<envs>_<N>` (as the experiment names them), else None."""
    tail = unmarked(label).rsplit("_", 1)[-1]
    return int(tail) if tail.isdigit() else None


def model_environments(label: str) -> list[str]:
    """The environments a model named `<env>+<env>_<N>` was trained in; any other name: itself."""
    label = unmarked(label)
    return label.rsplit("_", 1)[0].split("+") if model_demos(label) is not None else [label]
