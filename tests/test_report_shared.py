"""The results page for the `shared` controller, from synthetic records of known values: its "Shared
control" table (the fallback's share of steps, switches, where handovers began, the failures and
who drove at their end), no such table where no
record is of shared control, the Models row of an ensemble file, and success against the fallback's share of
the steps (the points of each gated run beside the policy alone, and the figure)."""

import re
from pathlib import Path

import torch

from ditch_drake.evaluation.model_labels import gate_words
from ditch_drake.evaluation.report import write_report
from ditch_drake.evaluation.report_data import handover_curves, load_report_data, shared_control_table, study_table
from ditch_drake.evaluation.results import RolloutRecord
from ditch_drake.learning.checkpoint import checkpoint_digest, make_checkpoint, save_checkpoint
from ditch_drake.learning.ensemble import EnsembleCheckpoint, save_ensemble
from ditch_drake.learning.model import FourInputClassifier

SHARED_HEADER = ("| model | environment | success | fallback's share of steps (mean) | (max) | switches (median) | "
                 "handovers (region:count) | failures (of them, the fallback driving at the end) |")


def record(i: int, controller: str = "shared", env: str = "wide", success: bool = True, fraction: float = 0.0,
           switches: int = 0, regions: tuple[str, ...] = (), checkpoint: str = "", digest: str = "",
           status: str = "") -> RolloutRecord:
    return RolloutRecord(
        key=f"{controller}|{checkpoint}|{env}|{i}", controller=controller, checkpoint=checkpoint, environment=env,
        task=i, seed=0, time_limit_s=120.0, goal_radius_m=1.5, checkpoint_sha256=digest,
        status=status or ("reached_goal" if success else "rolled_over"), success=success, time_s=60.0,
        path_length_m=30.0, peak_abs_roll_deg=5.0, peak_abs_pitch_deg=30.0, peak_tilt_deg=31.0,
        min_stability_margin_deg=10.0, final_x_m=0.0, final_y_m=0.0, failure_region="" if success else "up_wall",
        wall_s=1.0, handover_fraction=fraction, switches=switches, handover_regions=list(regions))


def write(path: Path, records: list[RolloutRecord]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(r.to_json() + "\n" for r in records))
    return path


def shared_records() -> list[RolloutRecord]:
    """Wide: 2 of 3 reached the goal, the fallback drove 10 %, 20 % and 45 % of the steps, after 2, 4 and 5
    switches; crater: 1 of 1, never handed over; plus an error record, counted nowhere."""
    return [
        record(0, fraction=0.10, switches=2, regions=("up_wall",)),
        record(1, fraction=0.20, switches=4, regions=("approach", "up_wall")),
        record(2, success=False, fraction=0.45, switches=5, regions=("floor", "approach", "up_wall")),
        record(3, success=False, status="error", fraction=0.9, switches=99, regions=("beyond",)),
        record(4, env="crater"),
    ]


def test_the_shared_control_table_gives_each_groups_share_switches_and_handover_regions():
    lines = shared_control_table(shared_records())
    assert lines[0] == SHARED_HEADER
    # A model in two environments: first its rollouts pooled (switches 0, 2, 4, 5: median 3).
    assert lines[2:] == ["| shared | all | 3/4 | 18.8% | 45.0% | 3 | approach:2, floor:1, up_wall:3 | 1 (1) |",
                         "| shared | crater | 1/1 | 0.0% | 0.0% | 0 | - | 0 |",
                         "| shared | wide | 2/3 | 25.0% | 45.0% | 4 | approach:2, floor:1, up_wall:3 | 1 (1) |"]
    # An even count of rollouts: the median of 4 and 5 switches is 4.5.
    assert shared_control_table(shared_records()[1:3])[2:] == [
        "| shared | wide | 1/2 | 32.5% | 45.0% | 4.5 | approach:2, floor:1, up_wall:2 | 1 (1) |"]
    # A failure after an even number of switches ended with the policy driving.
    handed_back = record(5, success=False, fraction=0.3, switches=2, regions=("floor",))
    assert shared_control_table([*shared_records()[1:3], handed_back])[2:] == [
        "| shared | wide | 1/3 | 31.7% | 45.0% | 4 | approach:2, floor:2, up_wall:2 | 2 (1) |"]


def test_only_shared_control_records_get_rows_and_a_file_without_them_gets_no_table(tmp_path):
    others = [record(i, controller="dwa", env="wide") for i in range(2)]
    # A record of another name whose fallback drove some steps counts as shared control.
    gated = record(9, controller="gated", fraction=0.5, switches=1, regions=("floor",))
    data = load_report_data([write(tmp_path / "mixed.jsonl", [*others, *shared_records(), gated]),
                             write(tmp_path / "plain.jsonl", others)])
    assert data.shared_tables["mixed"][2:] == [
        "| gated | wide | 1/1 | 50.0% | 50.0% | 1 | floor:1 | 0 |",
        "| shared | all | 3/4 | 18.8% | 45.0% | 3 | approach:2, floor:1, up_wall:3 | 1 (1) |",
        "| shared | crater | 1/1 | 0.0% | 0.0% | 0 | - | 0 |",
        "| shared | wide | 2/3 | 25.0% | 45.0% | 4 | approach:2, floor:1, up_wall:3 | 1 (1) |"]
    assert "plain" not in data.shared_tables and data.study_lines("plain") == data.tables["plain"]
    page = write_report([tmp_path / "mixed.jsonl", tmp_path / "plain.jsonl"], tmp_path / "page" / "results.md",
                        tmp_path / "page" / "img", data=data).read_text()
    mixed, plain = page.split("## mixed")[1].split("## plain")
    assert "### Shared control\n\n" + SHARED_HEADER in mixed and "Shared control" not in plain
    assert "### Shared control" in data.markdown_tables()


def _checkpoint(seed: int, epochs: int, best: int, seconds: float, train_demos: int):
    torch.manual_seed(seed)
    return make_checkpoint(
        FourInputClassifier().eval(),
        training={"train_demo_ids": list(range(train_demos)), "val_demo_ids": [0, 1],
                  "train_config": {"device": "cpu"}},
        metrics={"epochs_run": epochs, "best_epoch": best, "training_seconds": seconds, "best": {}})


def test_the_models_table_summarises_an_ensemble_and_checks_its_hash(tmp_path):
    members = [_checkpoint(0, 3, 2, 10.4, 5), _checkpoint(1, 3, 1, 20.3, 5)]
    ensemble = str(save_ensemble(EnsembleCheckpoint(members), tmp_path / "models" / "gated_k2.pt"))
    single = str(save_checkpoint(_checkpoint(2, 4, 4, 7.0, 5), tmp_path / "models" / "alone.pt"))
    records = [record(0, fraction=0.2, switches=2, checkpoint=ensemble, digest=checkpoint_digest(ensemble)),
               record(1, controller="learned", checkpoint=single, digest=checkpoint_digest(single))]
    results = write(tmp_path / "results" / "gated.jsonl", records)
    page = write_report([results], tmp_path / "page.md", tmp_path / "img").read_text()
    models = page.split("## Models")[1].splitlines()
    assert (f"| gated_k2 | {ensemble} | {checkpoint_digest(ensemble)} | ensemble of 2: 5/2 each | 3 (2), 3 (1) | cpu "
            "| 31 (sum) |") in models
    assert f"| alone | {single} | {checkpoint_digest(single)} | 5/2 | 4 (4) | cpu | 7 |" in models
    # Another file at the ensemble's path since the rollouts: not read as theirs.
    data = load_report_data([results])
    save_ensemble(EnsembleCheckpoint(members[::-1]), ensemble)
    page = write_report([results], tmp_path / "page.md", tmp_path / "img", data=data).read_text()
    assert f"| gated_k2 | {ensemble} | {records[0].checkpoint_sha256} | (file gone or changed since) |" in page


def test_a_models_rollouts_in_generated_ditches_are_one_row_in_both_tables():
    ditches = "results/test.ditches.yaml"
    generated = [RolloutRecord(**{**record(i, env=f"ditch_200{i // 3}", success=i != 4, fraction=0.1 * (i % 3),
                                           switches=i % 3, regions=("beyond",) * (i % 3)).__dict__,
                                  "environments_file": ditches}) for i in range(6)]
    packaged = record(9, env="wide", fraction=0.5, switches=1, regions=("floor",))
    table, summaries = study_table([*generated, packaged])
    assert [line.split(" | ")[1:3] for line in table[2:]] == [["2 generated ditches", "5/6"], ["wide", "1/1"]]
    assert summaries[("shared", "2 generated ditches")].trials == 6
    assert shared_control_table([*generated, packaged])[2:] == [
        "| shared | all | 6/7 | 15.7% | 50.0% | 1 | beyond:6, floor:1 | 1 (1) |",
        "| shared | 2 generated ditches | 5/6 | 10.0% | 20.0% | 1 | beyond:6 | 1 (1) |",
        "| shared | wide | 1/1 | 50.0% | 50.0% | 1 | floor:1 | 0 |"]
    # One generated ditch reads as such too.
    assert study_table(generated[:3])[0][2].split(" | ")[1] == "1 generated ditch"


def gated(i: int, signal: str, budget: float | None, fallback: str = "expert", **fields) -> RolloutRecord:
    """A `shared` record of the policy models/k5.pt whose config names its gate."""
    budget_words = f", budget: {budget}" if budget is not None else ""
    config = (f"policy:\n  checkpoint: models/k5.pt\ngate: {{signal: {signal}, upper_threshold: 1.0{budget_words}, "
              f"fallback: {fallback}}}\nexpert:\n  style_seed: null\n")
    return RolloutRecord(**{**record(i, checkpoint="models/k5.pt", **fields).__dict__, "controller_config": config})


def curve_records() -> dict[str, list[RolloutRecord]]:
    """In wide: the policy alone 1 of 2; the risk gate at budgets 0.02 (2 of 2, the fallback on 10 % and 30 %
    of the steps) and 0.1 (1 of 2, 40 % and 60 %, in another file); random handover at 0.02 (1 of 2, 5 %
    each, and an error record, counted nowhere); a fixed-threshold gate with the mppi (1 of 1, 0 %). In
    crater: the policy alone only (no panel). In the test split's generated ditches: the risk gate."""
    alone = [record(i, controller="learned", checkpoint="models/k5.pt", success=i == 0) for i in range(2)]
    ditches = "results/test.ditches.yaml"
    return {
        "gates": [*alone, record(5, controller="learned", checkpoint="models/k5.pt", env="crater"),
                  gated(0, "tip_risk_ahead", 0.02, fraction=0.1), gated(1, "tip_risk_ahead", 0.02, fraction=0.3),
                  gated(2, "random", 0.02, fraction=0.05), gated(3, "random", 0.02, fraction=0.05, success=False),
                  gated(4, "random", 0.02, fraction=0.9, status="error", success=False),
                  gated(6, "tip_risk_now", None, fallback="mppi"),
                  RolloutRecord(**{**gated(7, "tip_risk_ahead", 0.02, env="ditch_2003", fraction=0.2).__dict__,
                                   "environments_file": ditches}),
                  record(8, controller="dwa")],
        "larger": [gated(0, "tip_risk_ahead", 0.1, fraction=0.6, success=False),
                   gated(1, "tip_risk_ahead", 0.1, fraction=0.4)],
    }


def test_the_handover_curves_give_each_runs_share_and_success_beside_the_policy_alone():
    curves = handover_curves(curve_records())
    assert list(curves) == ["k5 on the test split", "k5 on wide"]
    wide = curves["k5 on wide"]
    assert list(wide) == ["alone", "random, fallback expert", "tip_risk_ahead, fallback expert",
                          "tip_risk_now, fallback mppi"]
    seen = {series: [(round(p.share, 6), p.summary.successes, p.summary.trials, p.budget) for p in points]
            for series, points in wide.items()}
    assert seen == {"alone": [(0.0, 1, 2, None)],
                    "random, fallback expert": [(0.05, 1, 2, 0.02)],
                    "tip_risk_ahead, fallback expert": [(0.2, 2, 2, 0.02), (0.5, 1, 2, 0.1)],
                    "tip_risk_now, fallback mppi": [(0.0, 1, 1, None)]}
    assert [(p.share, p.summary.trials) for p in curves["k5 on the test split"]["tip_risk_ahead, fallback expert"]] \
        == [(0.2, 1)]
    assert "alone" not in curves["k5 on the test split"]
    # A privileged fallback's series says so, as its table row does.
    marked = RolloutRecord(**{**gated(9, "tip_risk_ahead", 0.02).__dict__, "privileged": ["terrain"]})
    assert list(handover_curves({"marked": [marked]})["k5 on wide"]) == [
        "tip_risk_ahead, fallback expert (privileged: analytic terrain)"]
    # Without a gated run there is nothing to draw.
    assert handover_curves({"alone": curve_records()["gates"][:3]}) == {}


def test_a_page_with_gated_runs_draws_success_against_the_fallbacks_share(tmp_path):
    results = [write(tmp_path / "results" / f"{name}.jsonl", records) for name, records in curve_records().items()]
    page = write_report(results, tmp_path / "page.md", tmp_path / "img").read_text()
    assert "![fig_shared_control](img/fig_shared_control.png)" in page
    assert (tmp_path / "img" / "fig_shared_control.png").stat().st_size > 0
    plain = write(tmp_path / "plain" / "plain.jsonl", [record(i, controller="dwa") for i in range(2)])
    assert "fig_shared_control" not in write_report([plain], tmp_path / "plain.md", tmp_path / "plain_img").read_text()


def test_an_experiments_shared_control_file_keeps_its_success_bars_beside_the_handover_figure(tmp_path):
    # The experiment writes its shared_control study to shared_control.jsonl, whose bars take the
    # name the handover figure has on other pages.
    records = [r for rs in curve_records().values() for r in rs]
    results = write(tmp_path / "results" / "shared_control.jsonl", records)
    page = write_report([results], tmp_path / "page.md", tmp_path / "img").read_text()
    drawn = re.findall(r"!\[[^]]*\]\((img/[^)]+)\)", page)
    assert drawn == ["img/fig_shared_control.png", "img/fig_shared_control_handover.png"]
    assert all((tmp_path / path).stat().st_size > 0 for path in drawn)


def test_an_expert_fallback_that_replans_is_its_own_series_and_row():
    latched = gated(0, "tip_risk_ahead", 0.2)
    config = latched.controller_config.replace("expert:\n  style_seed: null\n",
                                               "expert:\n  style_seed: null\n  variation: {replan_each_step: true}\n")
    replanning = RolloutRecord(**{**gated(1, "tip_risk_ahead", 0.2, success=False).__dict__, "controller_config": config})
    # The mppi's own settings below the expert's do not count as the expert's.
    other = RolloutRecord(**{**gated(2, "tip_risk_ahead", 0.2, fallback="mppi").__dict__,
                             "controller_config": latched.controller_config.replace("fallback: expert", "fallback: mppi")
                             + "mppi: {replan_each_step: true}\n"})
    assert [gate_words(r) for r in (latched, replanning, other)] == [
        "gate tip_risk_ahead, budget 0.2, fallback expert", "gate tip_risk_ahead, budget 0.2, fallback expert, replanning",
        "gate tip_risk_ahead, budget 0.2, fallback mppi"]
    facing = RolloutRecord(**{**latched.__dict__, "controller_config": latched.controller_config.replace(
        "expert:\n  style_seed: null\n", "expert:\n  style_seed: null\n  variation: {keep_facing_side: true}\n")})
    assert gate_words(facing) == "gate tip_risk_ahead, budget 0.2, fallback expert, keeping the facing side"
    # A progress watchdog beside the signal is its own series and row.
    guarded = RolloutRecord(**{**latched.__dict__, "controller_config": latched.controller_config.replace(
        "fallback: expert", "fallback: expert, progress_limit_s: 20.0")})
    assert latched.controller_config != guarded.controller_config
    assert gate_words(guarded) == "gate tip_risk_ahead, budget 0.2, watchdog 20 s, fallback expert"
    both = handover_curves({"with": [guarded], "without": [latched]})
    assert sorted(both["k5 on wide"]) == ["tip_risk_ahead, fallback expert", "tip_risk_ahead, watchdog 20 s, fallback expert"]
    both_watchdogs = RolloutRecord(**{**latched.__dict__, "controller_config": latched.controller_config.replace(
        "fallback: expert", "fallback: expert, progress_limit_s: 20.0, regress_limit_m: 3.0")})
    assert gate_words(both_watchdogs) == "gate tip_risk_ahead, budget 0.2, watchdog 20 s, 3 m, fallback expert"
    # A longer hold before handing back is its own series and row; the default hold names none.
    def held(record, calm):
        return RolloutRecord(**{**record.__dict__, "controller_config": record.controller_config.replace(
            "fallback: expert", f"calm_steps: {calm}, fallback: expert, progress_limit_s: 20.0")})
    held_longer, held_default = held(latched, 20), held(latched, 5)
    assert [gate_words(r) for r in (held_longer, held_default)] == [
        "gate tip_risk_ahead, budget 0.2, 20 calm steps, watchdog 20 s, fallback expert", gate_words(guarded)]
    assert sorted(handover_curves({"20": [held_longer], "5": [held_default]})["k5 on wide"]) == [
        "tip_risk_ahead, 20 calm steps, watchdog 20 s, fallback expert", "tip_risk_ahead, watchdog 20 s, fallback expert"]
    # A tip risk on arcs of another length than the default is its own series and row.
    def on_arcs(record, text):
        config = record.controller_config
        assert config.count("\ngate:") == 1
        return RolloutRecord(**{**record.__dict__, "controller_config": config.replace("\ngate:", text + "\ngate:")})
    shorter = on_arcs(gated(3, "tip_risk_ahead", 0.2), "\n  tip_risk: {horizon_s: 1.0, presume_drops: true}")
    default = on_arcs(gated(4, "tip_risk_ahead", 0.2), "\n  tip_risk: {horizon_s: 2.0, presume_drops: true}")
    assert [gate_words(r) for r in (shorter, default)] == [
        "gate tip_risk_ahead on 1 s arcs, budget 0.2, fallback expert", "gate tip_risk_ahead, budget 0.2, fallback expert"]
    curves = handover_curves({"1 s": [shorter], "2 s": [default]})["k5 on wide"]
    assert sorted(curves) == ["tip_risk_ahead on 1 s arcs, fallback expert", "tip_risk_ahead, fallback expert"]
    curves = handover_curves({"latched": [latched, other], "replanning": [replanning]})["k5 on wide"]
    assert {series: [p.summary.successes for p in points] for series, points in curves.items()} == {
        "tip_risk_ahead, fallback expert": [1], "tip_risk_ahead, fallback expert, replanning": [0],
        "tip_risk_ahead, fallback mppi": [1]}


def test_a_study_of_one_model_per_environment_draws_a_bar_per_gate_not_per_model():
    from ditch_drake.evaluation.report_figures import bar_series

    gated = "gate random, budget 0.05, fallback mppi"
    per_ditch = {(f"{env}_40_k5", env): env for env in ("crater", "wide")} | {
        (f"{env}_40_k5 ({gated})", env): f"{env} gated" for env in ("crater", "wide")}
    series, bars = bar_series(per_ditch)
    assert series == ["each environment's model alone", gated]
    assert bars[(gated, "wide")] == "wide gated" and bars[("each environment's model alone", "crater")] == "crater"
    # Models evaluated in several environments, or two of one environment without marks, keep a
    # bar each, as before.
    across = {("wide", "wide"): 1, ("wide", "narrow"): 2, ("narrow", "narrow"): 3}
    assert bar_series(across) == (["narrow", "wide"], across)
    clash = {("a", "wide"): 1, ("b", "wide"): 2, ("c", "narrow"): 3}
    assert bar_series(clash) == (["a", "b", "c"], clash)


def test_a_gate_with_a_progress_watchdog_is_drawn_beside_the_same_signal_without_one(tmp_path):
    without = gated(0, "tip_risk_ahead", 0.02)
    guarded = RolloutRecord(**{**gated(1, "tip_risk_ahead", 0.02).__dict__, "controller_config": without.controller_config
                               .replace("fallback: expert", "fallback: expert, progress_limit_s: 20.0")})
    results = write(tmp_path / "results" / "watchdog.jsonl", [without, guarded])
    page = write_report([results], tmp_path / "page.md", tmp_path / "img").read_text()
    assert "gate tip_risk_ahead, budget 0.02, watchdog 20 s, fallback expert" in page
    drawn = re.findall(r"!\[[^]]*\]\((img/[^)]+)\)", page)
    assert "img/fig_shared_control.png" in drawn and (tmp_path / "img/fig_shared_control.png").stat().st_size > 0
