"""The results page's figures, in the style of the paper's Figure 5 (PNG, matplotlib), each with
its caption: (a-d) per environment, success against the number of demonstrations (scalability)
beside the other environments' models in it (generalization); (e) the learned models against
move_base: per walled environment of the must_cross study (every route crosses the ditch) each
environment's learned models against `dwa_paper` (the paper's move_base) and `dwa`, and in the
open field the learned policy against the DWA baseline (and `dwa_paper` where measured); (f)
the amalgam model against the single-environment models in the amalgam's evaluation
environment; for any other results file, its success rate per model and environment; and
where the results hold gated policies (the `shared` controller), success against the
fallback's share of the control steps (`report_data.handover_curves`).

Every bar carries its 95 % Wilson interval and its number of trials; successes that went around
the ditch are hatched over the bar's bottom.
"""

import re
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from ditch_drake.common.files import save_figure
from ditch_drake.evaluation.model_labels import label_marks, model_demos, model_environments
from ditch_drake.evaluation.paper_findings import CONTROLLER_NAMES, DWA, PAPER_MOVE_BASE, MustCross
from ditch_drake.evaluation.report_data import ALONE, STUDIES, HandoverPoint, ReportData, handover_curves
from ditch_drake.evaluation.statistics import counted
from ditch_drake.evaluation.summary import AROUND_TILT_DEG, GroupSummary

# What each kind of bar is drawn as (colour, hatch), so the figures agree with each other.
_OWN_MODEL = {"color": "tab:blue"}
_PAPER_MODEL = {"color": "lightskyblue", "edgecolor": "tab:blue"}  # An own model, the paper's method alone.
_OTHER_MODELS = {"color": "tab:gray"}
_BASELINE = {"color": "tab:red"}
_PAPER_BASELINE = {"color": "lightsalmon", "edgecolor": "tab:red"}
_AMALGAM = {"color": "tab:orange", "hatch": "xx", "edgecolor": "black"}
_AROUND = {"fill": False, "hatch": "///", "edgecolor": "black", "linewidth": 0.0}
_AROUND_LABEL = f"successes that went around the ditch (peak tilt < {AROUND_TILT_DEG:g} deg)"
_CI_TEXT = "Error bars: 95 % Wilson score intervals"


@dataclass
class Figure:
    """A figure's PNG file and the caption the page writes under it."""

    path: Path
    caption: str


def _error_bars(summaries: list[GroupSummary | None]) -> list[list[float]]:
    """Matplotlib's yerr for the Wilson intervals (rounding can put a bound a hair past the rate)."""
    return [[max(0.0, s.rate - s.low) if s else 0.0 for s in summaries],
            [max(0.0, s.high - s.rate) if s else 0.0 for s in summaries]]


def _success_axis(ax, ylabel: str = "success rate") -> None:
    ax.set_ylim(0, 1.17)  # Room above a full bar's error bar for its n.
    ax.set_yticks([0, 0.25, 0.5, 0.75, 1.0])
    ax.set_ylabel(ylabel)


def _bars(ax, xs: list[float], summaries: list[GroupSummary | None], width: float = 0.8, label: str | None = None,
          **style) -> None:
    """Bars of the success rates with Wilson error bars, n written above each, and the
    successes that went around the ditch hatched over the bar's bottom."""
    summaries = [counted(s) for s in summaries]
    ax.bar(xs, [s.rate if s else 0.0 for s in summaries], width, yerr=_error_bars(summaries), capsize=3, label=label,
           **style)
    around = [s.around / s.trials if s else 0.0 for s in summaries]
    if any(around):
        labelled = _AROUND_LABEL in ax.get_legend_handles_labels()[1]
        ax.bar(xs, around, width, label=None if labelled else _AROUND_LABEL, **_AROUND)
    for x, s in zip(xs, summaries):
        ax.text(x, (s.high if s else 0.0) + 0.02, f"n={s.trials}" if s else "none", ha="center", va="bottom",
                fontsize=7)


def _legend_below(fig, ax) -> None:
    """The legend under the axes, outside them, so that it covers no bar."""
    handles, labels = ax.get_legend_handles_labels()
    rows = 0
    if handles:
        # As many columns as fit the figure's width (about 13 characters of 8 pt text an inch).
        room = 13 * fig.get_figwidth()
        columns = next(n for n in range(len(labels), 0, -1)
                       if n == 1 or n * (max(map(len, labels)) + 6) <= room)
        rows = -(-len(labels) // columns)
        fig.legend(handles, labels, loc="lower center", ncol=columns, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.02 + 0.065 * rows * 3.8 / fig.get_figheight(), 1, 1))


def _counts(named: list[tuple[str, GroupSummary | None]]) -> str:
    """'n = 10 rollouts each' or 'n = wide_10: 8, wide_20: 10': the trials behind each point."""
    counts = [(name, s.trials) for name, s in named if counted(s)]
    if not counts:
        return "no trials"
    if len({n for _, n in counts}) == 1:
        return f"n = {counts[0][1]} rollouts each"
    return "n = " + ", ".join(f"{name}: {n}" for name, n in counts)


def _around_sentence(named: list[tuple[str, GroupSummary | None]]) -> str:
    """Which successes went around the ditch (hatched in the figure), computed from the records."""
    around = [(name, s) for name, s in named if s is not None and s.around]
    if not around:
        return ""
    parts = "; ".join(f"{name}: {s.around} of its {s.successes} successes" for name, s in around)
    return (f" Hatched: successes that went around the ditch's end, never entering it (peak tilt below "
            f"{AROUND_TILT_DEG:g} deg): {parts}.")


def _own_model(scalability: dict, env: str) -> str | None:
    """The model of `env` trained on the most demonstrations in the scalability study."""
    models = [(model_demos(m), m) for (m, e) in scalability if e == env and model_demos(m)
              and model_environments(m) == [env]]
    return max(models)[1] if models else None


def _figure_environment(env: str, scalability: dict, generalization: dict, path: Path, number: int) -> Figure:
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.8))
    points = sorted((model_demos(m), m, s) for (m, e), s in scalability.items()
                    if e == env and model_demos(m) and counted(s))
    if points:
        demos = [n for n, _, _ in points]
        left.errorbar(demos, [s.rate for _, _, s in points], yerr=_error_bars([s for _, _, s in points]),
                      marker="o", capsize=3, color=_OWN_MODEL["color"])
        for n, _, s in points:
            left.annotate(f"n={s.trials}", (n, s.high), textcoords="offset points", xytext=(0, 4), ha="center",
                          fontsize=7)
        left.set_xticks(demos)
    left.set(title=f"{env}: scalability", xlabel="demonstrations")
    _success_axis(left)
    own = _own_model(scalability, env)
    bars = [(own, scalability[(own, env)], _OWN_MODEL)] if own else []
    bars += [(m, s, _AMALGAM if "+" in m else _OTHER_MODELS) for (m, e), s in sorted(generalization.items())
             if e == env and m != own]
    for i, (model, summary, style) in enumerate(bars):
        label = ("own environment's model" if style is _OWN_MODEL else
                 "amalgam model" if style is _AMALGAM else "other environments' models")
        labelled = label in right.get_legend_handles_labels()[1]
        _bars(right, [i], [summary], label=None if labelled else label, **style)
    right.set_xticks(range(len(bars)), [m for m, _, _ in bars], rotation=25, ha="right", fontsize=8)
    right.set(title=f"{env}: models from each environment")
    _success_axis(right)
    _legend_below(fig, right)
    save_figure(fig, path, dpi=110)
    named = [(m, s) for _, m, s in points]
    caption = (f"Figure {number}: {env}. Left: success rate of the {env} models against the number of "
               f"demonstrations ({_counts(named)}). Right: models evaluated in {env}: "
               + (f"its own {own} (blue) and " if own else "")
               + f"the other environments' models (grey) ({_counts([(m, s) for m, s, _ in bars])}; n above "
               f"each bar). {_CI_TEXT}." + _around_sentence(named + [(m, s) for m, s, _ in bars]))
    return Figure(path, caption)


def _figure_baseline(scalability: dict, baseline: dict, path: Path, number: int,
                     paper: dict[str, GroupSummary] | None = None,
                     shipped: dict[str, tuple[str, GroupSummary]] | None = None) -> Figure:
    """The open field: each environment's own model against the DWA baseline, and against the
    paper's move_base (`paper`: its summary per open environment, from must_cross) where measured;
    `shipped`: per open environment, the shipped model's (label, summary) that must_cross ran there."""
    paper, shipped = paper or {}, shipped or {}
    envs = sorted({e for (_, e) in baseline} | set(paper))
    fig, ax = plt.subplots(figsize=(7, 3.8))
    owns = {env: _own_model(scalability, env) for env in envs}
    learned = [scalability.get((owns[env], env)) if owns[env] else None for env in envs]
    dwa = [baseline.get((DWA, env)) for env in envs]
    series = []
    if any(env in shipped for env in envs):
        series.append(([shipped[env][1] if env in shipped else None for env in envs],
                       "learned: the environment's shipped model", _OWN_MODEL))
    if any(learned) or not series:
        label = "learned: the paper's method, own environment's model" if series else "learned (own environment's model)"
        series.append((learned, label, _PAPER_MODEL if series else _OWN_MODEL))
    series += [(dwa, "DWA baseline (dwa)", _BASELINE)] if baseline else []
    series += [([paper.get(env) for env in envs], "the paper's move_base (dwa_paper)", _PAPER_BASELINE)] if paper else []
    width = 0.8 / len(series)
    for j, (summaries, label, style) in enumerate(series):
        _bars(ax, [i + (j - (len(series) - 1) / 2) * width for i in range(len(envs))], summaries, width, label=label,
              **style)
    ax.set_xticks(range(len(envs)), envs)
    ax.set_title("open field (the ditch can be bypassed): learned policy vs move_base")
    _success_axis(ax)
    _legend_below(fig, ax)
    save_figure(fig, path, dpi=110)
    models = ", ".join(f"{owns[env]}" for env in envs if owns[env]) or "none evaluated"
    named = [(f"{shipped[env][0]} in {env}", shipped[env][1]) for env in envs if env in shipped]
    named += [(f"{m} in {env}", s) for env, m, s in zip(envs, [owns[e] for e in envs], learned) if m]
    named += [(f"DWA in {env}", s) for env, s in zip(envs, dwa)] if baseline else []
    named += [(f"dwa_paper in {env}", paper.get(env)) for env in envs] if paper else []
    against = " and ".join([*(["the DWA baseline (red)"] if baseline else []),
                            *(["the paper's move_base, dwa_paper (light red)"] if paper else [])])
    learners = (["the environment's shipped model (blue; the must_cross study's runs)"] if shipped else [])
    own = f"the environment's own model with the most demonstrations ({'light blue' if shipped else 'blue'}: {models})"
    learners += [own] if any(learned) or not shipped else []
    caption = (f"Figure {number}: in the open field, per environment, {' and '.join(learners)} against {against} "
               f"({_counts(named)}; n above each "
               f"bar; 'none': not evaluated). {_CI_TEXT}." + _around_sentence(named))
    return Figure(path, caption)


def _figure_must_cross(must_cross: MustCross, path: Path, number: int) -> Figure:
    """The paper's Figure 5e like for like: per walled environment, its learned models against
    the classical controllers."""
    envs = list(must_cross.walled)

    def model(env: str, shipped: bool) -> tuple[str, GroupSummary] | tuple[None, None]:
        models = [(m, s) for m, s in must_cross.learned.get(env, []) if (model_demos(m) is None) == shipped]
        return max(models, key=lambda item: model_demos(item[0]) or 0) if models else (None, None)

    shipped, paper = [model(env, True) for env in envs], [model(env, False) for env in envs]
    demos = sorted({model_demos(m) for m, _ in paper if m})
    colours = plt.get_cmap("tab10")
    series = [(shipped, "learned: shipped model of the base environment", _OWN_MODEL),
              (paper, "learned: the paper's method" + (f", {', '.join(map(str, demos))} demonstrations" if demos else ""),
               _PAPER_MODEL)]
    styles = {PAPER_MOVE_BASE: _PAPER_BASELINE, DWA: _BASELINE}
    series += [([(name, by_env.get(env)) for env in envs], CONTROLLER_NAMES.get(name, name),
                styles.get(name, {"color": colours((4 + j) % 10)}))
               for j, (name, by_env) in enumerate(must_cross.controllers.items())]
    series = [item for item in series if any(counted(s) for _, s in item[0])]
    width = 0.8 / max(1, len(series))
    fig, ax = plt.subplots(figsize=(max(7.0, 1.2 + 0.45 * len(envs) * len(series)), 3.8))
    for j, (bars, label, style) in enumerate(series):
        _bars(ax, [i + (j - (len(series) - 1) / 2) * width for i in range(len(envs))], [s for _, s in bars], width,
              label=label, **style)
    ax.set_xticks(range(len(envs)), envs)
    ax.set_title("walled (every route crosses the ditch): learned models vs move_base")
    _success_axis(ax)
    _legend_below(fig, ax)
    save_figure(fig, path, dpi=110)
    named = [(f"{m} in {env}", s) for bars, _, _ in series for (m, s), env in zip(bars, envs) if m]
    caption = (f"Figure {number}: the paper's Figure 5e like for like: per walled environment (the ditch and tasks "
               "of its base environment, fenced so that every route crosses the ditch), the learned models "
               "(blue: the base environment's shipped model; light blue: the paper's method alone, the experiment's "
               "own model) against the paper's move_base (dwa_paper, light red) and our DWA (dwa, red: slopes from "
               f"45 deg lethal) ({_counts(named)}; n above each bar; 'none': not evaluated). {_CI_TEXT}."
               + _around_sentence(named))
    return Figure(path, caption)


def _figure_amalgam(env: str, amalgam: dict, singles: dict, path: Path, number: int) -> Figure:
    mixes = [(m, s) for (m, e), s in sorted(amalgam.items()) if e == env]
    demos = {model_demos(m) for m, _ in mixes}
    others = [(m, s) for (m, e), s in sorted(singles.items())
              if e == env and len(model_environments(m)) == 1 and model_demos(m) in demos]
    fig, ax = plt.subplots(figsize=(7, 3.8))
    _bars(ax, list(range(len(mixes))), [s for _, s in mixes], label="amalgam model (trained on several environments)",
          **_AMALGAM)
    _bars(ax, list(range(len(mixes), len(mixes) + len(others))), [s for _, s in others],
          label="single-environment models", **_OTHER_MODELS)
    ax.set_xticks(range(len(mixes) + len(others)), [m for m, _ in mixes + others], rotation=25, ha="right",
                  fontsize=8)
    ax.set_title(f"amalgam vs single-environment models in {env}")
    _success_axis(ax)
    _legend_below(fig, ax)
    save_figure(fig, path, dpi=110)
    named = mixes + others
    caption = (f"Figure {number}: in {env}, the amalgam model (orange, cross-hatched) against the single-environment "
               f"models with as many demonstrations (grey) ({_counts(named)}; n above each bar). {_CI_TEXT}."
               + _around_sentence(named))
    return Figure(path, caption)


# The series of bars of the rows without marks where each environment has a model of its own.
UNMARKED_SERIES = "each environment's model alone"


def bar_series(summaries: dict) -> tuple[list[str], dict]:
    """The series of a study's bars and the summaries by (series, environment): a series per
    model; but where every model ran in one environment only (an experiment's ensemble per
    ditch, each gated several ways), a series per row marks (`label_marks`, the ungated first), so
    that no group holds the other environments' models as empty bars."""
    envs = {e for (_, e) in summaries}
    models = sorted({m for (m, _) in summaries})
    by_marks = {(label_marks(m) or UNMARKED_SERIES, e): summary for (m, e), summary in summaries.items()}
    if len(envs) > 1 and len(models) == len(summaries) == len(by_marks):
        return sorted({m for (m, _) in by_marks}, key=lambda m: (m != UNMARKED_SERIES, m)), by_marks
    return models, summaries


def _figure_study(study: str, summaries: dict, path: Path, number: int) -> Figure:
    """Any other results file: success rate per series of `bar_series` (bars) and environment
    (groups)."""
    envs = sorted({e for (_, e) in summaries})
    models, bars = bar_series(summaries)
    width = 0.8 / len(models)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 + 0.5 * len(envs) * len(models)), 3.8))
    colours, count = (plt.get_cmap("tab10"), 10) if len(models) <= 10 else (plt.get_cmap("tab20"), 20)
    for j, model in enumerate(models):
        style = _AMALGAM if "+" in model else {"color": colours(j % count)}
        _bars(ax, [i + (j - (len(models) - 1) / 2) * width for i in range(len(envs))],
              [bars.get((model, env)) for env in envs], width, label=model, **style)
    ax.set_xticks(range(len(envs)), envs)
    ax.set_title(f"{study}: success per model and environment")
    _success_axis(ax)
    _legend_below(fig, ax)
    save_figure(fig, path, dpi=110)
    named = [(f"{m} in {e}", s) for (m, e), s in sorted(summaries.items())]
    caption = (f"Figure {number}: {study}: success rate of each model (bars) in each environment (groups) "
               f"({_counts(named)}; n above each bar, 'none': not evaluated there). {_CI_TEXT}."
               + _around_sentence(named))
    return Figure(path, caption)


# How a shared-control series is drawn: its fallback's marker; random handover (the chance
# control) hollow and dashed, so that each gate can be read against it.
_FALLBACK_MARKERS = {"expert": "o", "expert, replanning": "P", "expert, keeping the facing side": "D", "mppi": "s",
                     "teleop": "^"}
_RANDOM_SIGNAL = "random"


def _figure_shared_control(curves: dict[str, dict[str, list[HandoverPoint]]], path: Path, number: int) -> Figure:
    """Success against the fallback's share of the control steps, a panel per gated policy and
    where it drove, a line per gate signal and fallback through its runs, the policy alone at 0."""
    columns = min(2, len(curves))
    rows = -(-len(curves) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(5.2 * columns, 3.6 * rows + 0.6), squeeze=False)
    # A signal with watchdogs beside it ("tip_risk_ahead, watchdog 20 s, 6 m") is a colour of its own.
    signals = sorted({series.partition(", fallback ")[0] for panel in curves.values() for series in panel}
                     - {ALONE, _RANDOM_SIGNAL})
    colours = plt.get_cmap("tab10")
    handles: dict[str, object] = {}
    for ax, (panel, series_points) in zip(axes.flat, curves.items()):
        lows, highs, shares = [], [], [0.0]
        for series, points in series_points.items():
            summaries = [counted(point.summary) for point in points]
            drawn = [(point, s) for point, s in zip(points, summaries) if s]
            if not drawn:
                continue
            xs = [100 * point.share for point, _ in drawn]
            ys = [s.rate for _, s in drawn]
            yerr = _error_bars([s for _, s in drawn])
            shares += xs
            lows += [s.low for _, s in drawn]
            highs += [s.high for _, s in drawn]
            if series == ALONE:
                style = {"color": "black", "marker": "D", "linestyle": "none"}
                label = "the policy alone"
            else:
                signal, _, fallback = series.partition(", fallback ")
                random = signal == _RANDOM_SIGNAL
                style = {"color": "tab:gray" if random else colours(signals.index(signal) % 10),
                         "marker": _FALLBACK_MARKERS.get(fallback.split(" (")[0], "v"), "linestyle": "--" if random else "-",
                         "markerfacecolor": "white" if random else None}
                label = f"{'random handover' if random else signal}, fallback {fallback}"
            line = ax.errorbar(xs, ys, yerr=yerr, capsize=3, linewidth=1.2, markersize=5, label=label, **style)
            handles.setdefault(label, line)
            for (point, s), x in zip(drawn, xs):
                if point.budget is not None:
                    ax.annotate(f"{100 * point.budget:g}%", (x, s.rate), textcoords="offset points", xytext=(4, -9),
                                fontsize=6, color=style["color"])
        ax.set_title(panel, fontsize=9)
        ax.set_xlabel("fallback's share of the control steps (%, mean over the rollouts)", fontsize=8)
        ax.set_ylabel("success rate", fontsize=8)
        if lows:
            ax.set_ylim(max(0.0, min(lows) - 0.03), min(1.05, max(highs) + 0.03))
        span = max(1.0, max(shares))
        ax.set_xlim(-0.06 * span, 1.1 * span)
    for ax in list(axes.flat)[len(curves):]:
        ax.set_visible(False)
    labels = sorted(handles, key=lambda label: (label != "the policy alone", label.startswith("random"), label))
    # As many columns as fit the figure's width (about 13 characters of 8 pt text an inch, as `_legend_below`).
    columns = max(1, min(3, len(labels), int(13 * fig.get_figwidth()) // (max(map(len, labels)) + 6)))
    fig.legend([handles[label] for label in labels], labels, loc="lower center", ncol=columns, fontsize=8,
               frameon=False)
    legend_rows = -(-len(labels) // columns)
    fig.tight_layout(rect=(0, 0.2 * legend_rows / fig.get_figheight(), 1, 1))
    save_figure(fig, path, dpi=110)
    named = [(f"{series} in {panel}" + (f" at budget {point.budget:g}" if point.budget is not None else ""),
              point.summary) for panel, series_points in curves.items() for series, points in series_points.items()
             for point in points]
    caption = (f"Figure {number}: shared control: success rate against the fallback's share of the control steps "
               "(the mean over a run's rollouts), one point per run, labelled with the budget that set its gate's "
               "thresholds; a line joins the runs of one gate signal and fallback (marker: the fallback), random "
               "handover (the chance control) hollow and dashed; the diamond at 0 is the same policy ungated, where "
               f"the results hold it ({_counts(named)}). {_CI_TEXT}.")
    return Figure(path, caption)


def draw_figures(data: ReportData, figures_dir: Path,
                 must_cross: MustCross | None = None) -> tuple[list[Figure], list[str]]:
    """Every figure the data allows, and a sentence for each results file that gets none.

    Learned models against move_base: in the walled environments (`fig5_must_cross.png`) where
    the must_cross study has results there, then in the open field (`fig5_baseline.png`) where
    the baseline study or must_cross's open environments have results.
    """
    summaries = data.summaries
    scalability, generalization = summaries.get("scalability", {}), summaries.get("generalization", {})
    baseline, amalgam = summaries.get("baseline", {}), summaries.get("amalgam", {})
    figures, missing = [], []
    for env in sorted({e for (_, e) in scalability} | {e for (_, e) in generalization}):
        figures.append(_figure_environment(env, scalability, generalization, figures_dir / f"fig5_{env}.png",
                                           len(figures) + 1))
    if must_cross and must_cross.walled:
        figures.append(_figure_must_cross(must_cross, figures_dir / "fig5_must_cross.png", len(figures) + 1))
    paper = must_cross.open_field(PAPER_MOVE_BASE) if must_cross else {}
    shipped = {env: models[0] for env, models in (must_cross.open_learned if must_cross else {}).items()
               if models and model_demos(models[0][0]) is None}
    if baseline or paper:
        figures.append(_figure_baseline(scalability, baseline, figures_dir / "fig5_baseline.png", len(figures) + 1,
                                        paper, shipped))
    amalgam_envs = sorted({e for (_, e) in amalgam})
    for env in amalgam_envs:
        name = "fig5_amalgam.png" if len(amalgam_envs) == 1 else f"fig5_amalgam_{env}.png"
        figures.append(_figure_amalgam(env, amalgam, {**generalization, **scalability}, figures_dir / name,
                                       len(figures) + 1))
    for study in data.studies:
        if study in STUDIES:
            continue
        if not any(s.trials for s in summaries[study].values()):
            missing.append(f"No figure for {study}: it holds no trials "
                           f"({len(data.records[study])} current records, all errors or none).")
            continue
        name = re.sub(r"[^A-Za-z0-9_.+-]", "_", study)
        figures.append(_figure_study(study, summaries[study], figures_dir / f"fig_{name}.png", len(figures) + 1))
    if curves := handover_curves(data.records):
        # An experiment's study named shared_control has drawn its success bars at this name already.
        path = figures_dir / "fig_shared_control.png"
        if any(figure.path == path for figure in figures):
            path = figures_dir / "fig_shared_control_handover.png"
        figures.append(_figure_shared_control(curves, path, len(figures) + 1))
    return figures, missing
