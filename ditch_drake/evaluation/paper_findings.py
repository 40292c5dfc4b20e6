"""The paper's findings beside ours on the results page, each verdict computed from the numbers.

"Every learned model beats move_base in its own environment" is tested pair by pair (each
learned model against the classical controller in the same environment, Boschloo's exact test:
`statistics.two_proportion_test`), in the walled environments of the must_cross study (every
route crosses the ditch: the like-for-like comparison, issue 20) and, beside them, in the open
field. The other findings: success rising with demonstrations, the Crater model generalizing
best and the Sine model worst, the amalgam beating the single models' average, and the paper's
move_base failing on the backslope after halting to replan (the must_cross study's halts by
region).
"""

from collections import defaultdict
from dataclasses import dataclass, field

from ditch_drake.common.errors import ConfigError
from ditch_drake.evaluation.model_labels import controller_labels, model_demos
from ditch_drake.evaluation.report_data import ReportData
from ditch_drake.evaluation.statistics import (
    ALPHA,
    Comparison,
    beats_verdict,
    compare,
    counted,
    p_value_text,
    percent,
    verdict_rule,
)
from ditch_drake.evaluation.summary import AROUND_TILT_DEG, GroupSummary
from ditch_drake.world.regions import REGIONS

# The paper's move_base (slope cost, flat = 0, no slope lethal; issue 20) and our DWA baseline
# (slopes from 45 deg lethal), the classical controllers the learned models are compared with.
PAPER_MOVE_BASE = "dwa_paper"
DWA = "dwa"
CONTROLLER_NAMES = {PAPER_MOVE_BASE: "the paper's move_base (dwa_paper: slope cost, no slope lethal)",
                     DWA: "our DWA baseline (dwa: slopes from 45 deg lethal)"}


def walled_base(environment: str, environments_file: str = "") -> str:
    """The open environment a walled one is made from (its `Environment.based_on`), "" for an
    open one; for a name that no longer resolves, the `<env>_walled` naming convention."""
    from ditch_drake.world.environments import get_environment

    try:
        return get_environment(environment, environments_file or None).based_on
    except ConfigError:
        return environment.removesuffix("_walled") if environment.endswith("_walled") else ""


@dataclass
class MustCross:
    """The must_cross study's groups (issue 20), sorted for the page.

    Attributes:
        walled: each walled environment evaluated -> the open environment it is made from.
        learned: per walled environment, its learned models' (label, summary): the shipped
            models (no number of demonstrations in the name), then the paper-method ones.
        controllers: per classical controller (`dwa_paper` first, then `dwa`, then any
            other), its summary per environment, walled and open.
        open_learned: per open environment, the learned models the study ran there (on the
            same seeds as in the walled ones), sorted as `learned`.
    """

    walled: dict[str, str]
    learned: dict[str, list[tuple[str, GroupSummary]]]
    controllers: dict[str, dict[str, GroupSummary]]
    open_learned: dict[str, list[tuple[str, GroupSummary]]] = field(default_factory=dict)

    def comparisons(self, controller: str) -> list[Comparison]:
        """Every learned model against `controller` in each walled environment where both ran."""
        found = [compare(env, model, s, controller, self.controllers.get(controller, {}).get(env))
                 for env in self.walled for model, s in self.learned.get(env, [])]
        return [c for c in found if c is not None]

    def open_field(self, controller: str) -> dict[str, GroupSummary]:
        """`controller`'s summaries in the open environments."""
        return {env: s for env, s in self.controllers.get(controller, {}).items() if env not in self.walled}


def must_cross_groups(data: ReportData) -> MustCross | None:
    """The must_cross study's groups (None without its results): a group is a learned model's
    when its records name a checkpoint, else a classical controller's."""
    records = data.records.get("must_cross")
    if not records:
        return None
    files = {record.environment: record.environments_file for record in records}
    walled = {env: base for env in sorted(files) if (base := walled_base(env, files[env]))}
    name_of = controller_labels(records)  # As `_table` named the study's groups.
    learned_labels = {name_of(record) for record in records if record.checkpoint}
    learned: dict[str, list[tuple[str, GroupSummary]]] = defaultdict(list)
    open_learned: dict[str, list[tuple[str, GroupSummary]]] = defaultdict(list)
    controllers: dict[str, dict[str, GroupSummary]] = defaultdict(dict)
    for (label, env), summary in data.summaries["must_cross"].items():
        if label not in learned_labels:
            controllers[label][env] = summary
        else:
            (learned if env in walled else open_learned)[env].append((label, summary))
    for models in (*learned.values(), *open_learned.values()):
        models.sort(key=lambda item: (model_demos(item[0]) is not None, item[0]))
    order = sorted(controllers, key=lambda name: (name != PAPER_MOVE_BASE, name != DWA, name))
    return MustCross(walled, dict(learned), {name: controllers[name] for name in order}, dict(open_learned))


def _comparisons_cell(comparisons: list[Comparison]) -> str:
    """'wide_walled: wide 90% (p=1e-05), wide_40 70% (p=0.003) vs 10%; ...; 2 of 2 pairs higher with p < 0.05'."""
    by_env: dict[str, list[Comparison]] = defaultdict(list)
    for c in comparisons:
        by_env[c.environment].append(c)
    parts = [f"{env}: " + ", ".join(f"{c.model} {percent(c.learned.rate)} (p={p_value_text(c.p_value)})" for c in group)
             + f" vs {percent(group[0].baseline.rate)}" for env, group in by_env.items()]
    passed = sum(c.beats for c in comparisons)
    return "; ".join(parts) + f"; {passed} of {len(comparisons)} pairs higher with p < {ALPHA:g}"


def _comparisons_table(named: list[tuple[str, list[Comparison]]]) -> list[str]:
    """Every pair behind the verdicts: (setting, its comparisons)."""
    lines = [("| setting | environment | learned model | success | 95 % Wilson | against | success | 95 % Wilson | "
             "p (Boschloo, two-sided) | higher, p < 0.05 |"),
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for setting, comparisons in named:
        for c in comparisons:
            lines.append(f"| {setting} | {c.environment} | {c.model} | {c.learned.successes}/{c.learned.trials} | "
                         f"{percent(c.learned.low)}-{percent(c.learned.high)} | {c.controller} | "
                         f"{c.baseline.successes}/{c.baseline.trials} | {percent(c.baseline.low)}-{percent(c.baseline.high)} | "
                         f"{p_value_text(c.p_value)} | {'yes' if c.beats else 'no'} |")
    return lines if len(lines) > 2 else []


def _halts(summary: GroupSummary) -> dict[str, int]:
    """A group's halts per region (`GroupSummary.halts_by_region`; empty where its records do
    not count them, or before the summaries had the field)."""
    return dict(getattr(summary, "halts_by_region", None) or {})


def _halts_table(must_cross: MustCross) -> list[str]:
    """The classical controllers' halts by region, walled environments first; empty when no
    group's records count halts ('-': this group's do not)."""
    rows = [(name, env, s) for name, by_env in must_cross.controllers.items()
            for env, s in sorted(by_env.items(), key=lambda item: (item[0] not in must_cross.walled, item[0]))]
    if not any(_halts(s) for _, _, s in rows):
        return []
    lines = ["| controller | environment | rollouts | " + " | ".join(REGIONS) + " | total |",
             "| --- | --- | ---: | " + " | ".join("---:" for _ in REGIONS) + " | ---: |"]
    for name, env, s in rows:
        counts = _halts(s)
        cells = [str(counts.get(region, 0)) if counts else "-" for region in REGIONS]
        lines.append(f"| {name} | {env} | {s.trials} | " + " | ".join(cells)
                     + f" | {sum(counts.values()) if counts else '-'} |")
    return lines


def _backslope_row(must_cross: MustCross) -> list[str]:
    """The paper's move_base mostly failed on the backslope after halting to replan (paper 5):
    where its failures in the walled environments ended, and where it halted."""
    groups = [s for env, s in must_cross.controllers.get(PAPER_MOVE_BASE, {}).items()
              if env in must_cross.walled and counted(s)]
    if not groups:
        return []
    failures = sum(s.trials - s.successes for s in groups)
    up = sum(n for s in groups for key, n in s.failure_regions.items() if key.endswith("@up_wall"))
    ours = f"{PAPER_MOVE_BASE} in the walled environments: {up} of its {failures} failures ended on the up wall"
    recorded = [_halts(s) for s in groups]
    halted = True
    if all(recorded):
        up_halts, halts = sum(h.get("up_wall", 0) for h in recorded), sum(sum(h.values()) for h in recorded)
        ours += f"; {up_halts} of its {halts} halts were on the up wall"
        halted = up_halts > 0
    else:
        ours += "; halts not recorded"
    agree = failures > 0 and 2 * up > failures and halted
    return [(f"| move_base mostly failed on the backslope, after halting to replan (walled) | {ours} | "
            f"{'yes' if agree else 'no'} |")]


def open_field_comparisons(scalability: dict, baseline: dict, must_cross: MustCross | None,
                            controller: str) -> list[Comparison]:
    """In the open field, each environment's learned models against `controller` there (the
    baseline study's `dwa`, or a controller of the must_cross study): the 40-demonstration
    model of the scalability study, and the learned models the must_cross study ran in the
    open environments (on its own seeds)."""
    if controller == DWA:
        summaries = {env: s for (label, env), s in baseline.items() if label == DWA}
    else:
        summaries = must_cross.open_field(controller) if must_cross else {}
    found = []
    for env, s in sorted(summaries.items()):
        models = [(f"{env}_40", scalability.get((f"{env}_40", env))),
                  *(must_cross.open_learned.get(env, []) if must_cross else [])]
        found += [compare(env, model, learned, controller, s) for model, learned in models]
    return [c for c in found if c is not None]


def open_field_controllers(must_cross: MustCross | None) -> list[str]:
    """The controllers compared in the open field: the baseline study's `dwa`, then the
    must_cross study's others."""
    return [DWA, *(name for name in (must_cross.controllers if must_cross else ()) if name != DWA)]


_BEATS = "every learned model beats move_base in its own environment"


def _around_of(comparisons: list[Comparison]) -> int:
    """The classical controller's successes that went around the ditch, counted once per environment."""
    return sum({c.environment: c.baseline.around for c in comparisons}.values())


def _successes_of(comparisons: list[Comparison]) -> int:
    return sum({c.environment: c.baseline.successes for c in comparisons}.values())


def _findings(scalability: dict, generalization: dict, baseline: dict, amalgam: dict,
              must_cross: MustCross | None = None) -> list[str]:
    """The paper's findings (docs/design.md, "The experiments") beside ours; each verdict computed from the numbers."""
    rows = ["| paper's finding | ours | agree? |", "| --- | --- | --- |"]
    envs = sorted({e for (_, e) in scalability} | {e for (_, e) in baseline})
    rising = []
    for env in envs:
        series = sorted((model_demos(m), s.rate) for (m, e), s in scalability.items() if e == env and model_demos(m))
        if len(series) >= 2:
            rising.append((env, series[-1][1] >= series[0][1], series))
    if rising:
        ours = "; ".join(f"{env} " + " -> ".join(f"{n}: {percent(r)}" for n, r in series) for env, _, series in rising)
        rows.append(f"| success generally rises with demonstrations | {ours} | "
                    f"{'yes' if sum(up for _, up, _ in rising) * 2 > len(rising) else 'no'} |")
    if must_cross:
        for controller in must_cross.controllers:
            comparisons = must_cross.comparisons(controller)
            if not comparisons:
                continue
            ours = _comparisons_cell(comparisons)
            around = _around_of(comparisons)
            if around:  # The walls should leave no way around: say so if some success still never entered.
                ours += (f" ({around} of {controller}'s {_successes_of(comparisons)} successes never tilted past "
                         f"{AROUND_TILT_DEG:g} deg)")
            compared = {c.environment for c in comparisons}
            unmatched = [env for env in must_cross.walled
                         if counted(must_cross.controllers[controller].get(env)) and env not in compared]
            if unmatched:
                ours += f"; no learned model evaluated in {', '.join(unmatched)}"
            rows.append(f"| {_BEATS}: walled (every route crosses the ditch), against "
                        f"{CONTROLLER_NAMES.get(controller, controller)} | {ours} | {beats_verdict(comparisons)} |")
        rows += _backslope_row(must_cross)
    for controller in open_field_controllers(must_cross):
        comparisons = open_field_comparisons(scalability, baseline, must_cross, controller)
        if not comparisons:
            continue
        ours = _comparisons_cell(comparisons)
        around = _around_of(comparisons)
        if around:
            ours += (f" (but {around} of {controller}'s {_successes_of(comparisons)} successes went around the ditch, "
                     "never entering it: the open field lets it bypass the obstacle)")
        rows.append(f"| {_BEATS}: open field, against {CONTROLLER_NAMES.get(controller, controller)} | {ours} | "
                    f"{beats_verdict(comparisons)} |")
    if generalization:
        mean_by_model = defaultdict(list)
        for (model, _), s in generalization.items():
            if s.trials:
                mean_by_model[model].append(s.rate)
        means = {m: sum(v) / len(v) for m, v in mean_by_model.items()}
        if means:
            best, worst = max(means, key=means.get), min(means, key=means.get)
            ours = ", ".join(f"{m} {percent(v)}" for m, v in sorted(means.items()))
            agree = best.startswith("crater") and worst.startswith("sine")
            rows.append(f"| the Crater model generalizes best, the Sine model worst | mean over other environments: "
                        f"{ours} | {'yes' if agree else 'no'} |")
    for (model, env), s in amalgam.items():
        singles = [g.rate for (m, e), g in generalization.items() if e == env and g.trials]
        if singles and s.trials:
            average = sum(singles) / len(singles)
            rows.append(f"| the amalgam beats the average of the single models in {env} | {model} {percent(s.rate)} vs "
                        f"average {percent(average)} | {'yes' if s.rate > average else 'no'} |")
    return rows


def findings_section(data: ReportData, must_cross: MustCross | None) -> list[str]:
    """The findings table, the rule of its verdicts, the pairs behind "beats move_base", and the
    must_cross study's halts by region."""
    summaries = data.summaries
    scalability, baseline = summaries.get("scalability", {}), summaries.get("baseline", {})
    findings = _findings(scalability, summaries.get("generalization", {}), baseline, summaries.get("amalgam", {}),
                         must_cross)
    lines = ["## The paper's findings and ours", ""]
    if must_cross and must_cross.walled:
        lines += [("The paper's move_base had to cross its ditches; ours can go around an open field's ditch. So "
                   "\"beats move_base\" is answered where every route crosses the ditch (the must_cross study's "
                   "walled environments: each environment's learned models, the shipped one and the paper-method "
                   "one, against the paper's move_base and our DWA there), and beside it in the open field (each "
                   "environment's learned models against the same controllers there)."), ""]
    lines += [*findings, ""]
    pairs = [(f"walled, against {controller}", must_cross.comparisons(controller))
             for controller in (must_cross.controllers if must_cross else ())]
    pairs += [(f"open field, against {controller}",
               open_field_comparisons(scalability, baseline, must_cross, controller))
              for controller in open_field_controllers(must_cross)]
    table = _comparisons_table([(setting, comparisons) for setting, comparisons in pairs if comparisons])
    if table:
        lines += ["### Learned models against move_base, pair by pair", "", verdict_rule(), "", *table, ""]
    if must_cross and must_cross.controllers.get(PAPER_MOVE_BASE):
        lines += [("Backslope rule: 'yes' when more than half of dwa_paper's failures in the walled environments "
                   "ended on the up wall (the backslope) and, where the records count halts, it halted there at "
                   "least once."), ""]
    halts = _halts_table(must_cross) if must_cross else []
    if halts:
        lines += ["### Halts of the classical controllers by region (must_cross)", "",
                  ("Halts (the |v| command below 0.05 m/s for 0.5 s or more) per region of the rollout, summed "
                   "over each group's rollouts, so the paper's failure (halt to replan on the backslope, slide, "
                   "roll) is measured, not guessed."), "", *halts, ""]
    return lines
