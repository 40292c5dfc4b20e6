"""The results page where the ditch must be crossed (issue 20), from synthetic records of known counts:
the findings' Wilson intervals, Boschloo p-values and verdicts, the halts by region, and the figures.

The records are made by hand, so nothing here runs a rollout; the walled environments' names resolve
through the registry where they are defined and by the `<env>_walled` convention where not.
"""

from pathlib import Path

import pytest
from scipy.stats import boschloo_exact

from ditch_drake.evaluation.paper_findings import must_cross_groups, walled_base
from ditch_drake.evaluation.report import write_report
from ditch_drake.evaluation.report_data import load_report_data
from ditch_drake.evaluation.results import RolloutRecord
from ditch_drake.evaluation.statistics import ALPHA, beats_verdict, compare, two_proportion_test
from ditch_drake.evaluation.summary import summarize, wilson_interval

HALTS_UP_WALL = {"approach": 1, "down_wall": 0, "floor": 2, "up_wall": 5, "beyond": 0}


def group(controller: str, checkpoint: str, env: str, successes: int, trials: int = 30, around: int = 0,
          failure_region: str = "up_wall", halts: dict[str, int] | None = None) -> list[RolloutRecord]:
    """`trials` records of one controller in one environment: the first `successes` reached the goal (the
    first `around` of those never tilted into the ditch), the others rolled over in `failure_region`."""
    records = []
    for i in range(trials):
        success = i < successes
        records.append(RolloutRecord(
            key=f"{controller}|{checkpoint}|{env}|{i}", controller=controller, checkpoint=checkpoint, environment=env,
            task=i % 3, seed=i // 3, time_limit_s=120.0, goal_radius_m=1.5, checkpoint_sha256="",
            status="reached_goal" if success else "rolled_over", success=success, time_s=60.0, path_length_m=30.0,
            peak_abs_roll_deg=5.0, peak_abs_pitch_deg=30.0, peak_tilt_deg=5.0 if i < around else 31.0,
            min_stability_margin_deg=10.0, final_x_m=0.0, final_y_m=0.0,
            failure_region="" if success else failure_region, wall_s=1.0,
            halts_by_region=dict(halts or {})))
    return records


def write(folder: Path, study: str, records: list[RolloutRecord]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{study}.jsonl").write_text("".join(record.to_json() + "\n" for record in records))


# Known counts (successes of 30) per walled environment: the shipped model, the paper-method model, the
# paper's move_base and our DWA.
COUNTS = {"wide": (27, 24, 6, 3), "crater": (30, 25, 0, 30)}


def must_cross_records(models: str, counts=None) -> list[RolloutRecord]:
    records = []
    for base, (shipped, paper, dwa_paper, dwa) in (counts or COUNTS).items():
        env = f"{base}_walled"
        records += group("learned", base, env, shipped)
        records += group("learned", f"{models}/{base}_40.pt", env, paper)
        records += group("dwa_paper", "", env, dwa_paper, halts=HALTS_UP_WALL)
        records += group("dwa", "", env, dwa, failure_region="approach")
    records += group("dwa_paper", "", "wide", 30, around=30, halts=dict.fromkeys(HALTS_UP_WALL, 0))
    return records


@pytest.fixture
def results(tmp_path) -> Path:
    """must_cross, scalability and baseline results files (the open field's learned model and DWA)."""
    folder = tmp_path / "results"
    write(folder, "must_cross", must_cross_records(str(tmp_path / "models")))
    write(folder, "scalability", group("learned", str(tmp_path / "models" / "wide_40.pt"), "wide", 20))
    write(folder, "baseline", group("dwa", "", "wide", 30, around=30))
    return folder


def page_lines(tmp_path: Path, results: Path) -> tuple[list[str], Path]:
    page = write_report([results], tmp_path / "results.md", tmp_path / "img")
    return page.read_text().splitlines(), page


def row(lines: list[str], *parts: str) -> str:
    (found,) = [line for line in lines if all(part in line for part in parts)]
    return found


def pct(value: float) -> str:
    return f"{100 * value:.0f}%"


def boschloo(a: int, b: int, trials: int = 30) -> float:
    return boschloo_exact([[a, b], [trials - a, trials - b]], alternative="two-sided").pvalue


def test_the_two_proportion_test_is_scipys_two_sided_boschloo_on_the_same_table():
    for a, b in [(27, 6), (24, 3), (25, 0), (8, 6), (30, 29)]:
        assert two_proportion_test(a, 30, b, 30) == pytest.approx(boschloo(a, b), rel=1e-12)
    assert two_proportion_test(9, 12, 2, 10) == pytest.approx(
        boschloo_exact([[9, 2], [3, 8]], alternative="two-sided").pvalue, rel=1e-12)
    # No evidence either way (scipy: nan): p = 1.
    assert two_proportion_test(30, 30, 30, 30) == 1.0 and two_proportion_test(0, 30, 0, 30) == 1.0
    with pytest.raises(ValueError, match="31/30"):
        two_proportion_test(31, 30, 0, 30)
    with pytest.raises(ValueError, match="trials >= 1"):
        two_proportion_test(0, 0, 0, 30)


def test_the_verdict_is_yes_only_when_every_learned_model_is_higher_and_significant():
    base = summarize(group("dwa_paper", "", "wide_walled", 6))

    def verdict(*learned: int) -> str:
        return beats_verdict([compare("wide_walled", f"m{i}", summarize(group("learned", f"m{i}", "wide_walled", n)),
                                      "dwa_paper", base) for i, n in enumerate(learned)])

    assert verdict(27, 24) == "yes"
    assert verdict(27, 8) == "not significant"  # 8 of 30 vs 6 of 30: higher, but p >= 0.05.
    assert boschloo(8, 6) >= ALPHA > boschloo(24, 6)
    assert verdict(27, 5) == verdict(27, 6) == "no"  # One model loses (or ties): the claim fails.
    assert compare("wide_walled", "m", summarize([]), "dwa_paper", base) is None  # No trials: no comparison.


def test_walled_base_is_the_registrys_based_on_or_the_naming_convention():
    assert walled_base("wide_walled") == "wide" and walled_base("wide") == ""
    assert walled_base("moon_walled") == "moon" and walled_base("moon") == ""  # Names no longer defined.


def test_the_groups_split_learned_models_from_classical_controllers_and_walled_from_open(tmp_path, results):
    groups = must_cross_groups(load_report_data([results]))
    assert groups.walled == {"crater_walled": "crater", "wide_walled": "wide"}
    assert [m for m, _ in groups.learned["wide_walled"]] == ["wide", "wide_40"]  # Shipped first.
    assert list(groups.controllers) == ["dwa_paper", "dwa"]  # The paper's move_base first.
    assert set(groups.open_field("dwa_paper")) == {"wide"} and groups.open_field("dwa") == {}
    assert [(c.environment, c.model) for c in groups.comparisons("dwa")] == [
        ("crater_walled", "crater"), ("crater_walled", "crater_40"), ("wide_walled", "wide"), ("wide_walled", "wide_40")]


def test_the_findings_answer_beats_move_base_on_the_walled_environments_with_wilson_and_boschloo(tmp_path, results):
    lines, _ = page_lines(tmp_path, results)
    # Against the paper's move_base every learned model is higher, significantly: yes.
    walled_paper = row(lines, "| every learned model beats move_base in its own environment: walled", "dwa_paper:")
    assert walled_paper.endswith("| yes |")
    assert (f"wide_walled: wide 90% (p={boschloo(27, 6):.2g}), wide_40 80% (p={boschloo(24, 6):.2g}) vs 20%"
            in walled_paper)
    assert "4 of 4 pairs higher with p < 0.05" in walled_paper
    # Against our DWA, which crosses crater_walled every time, the learned models are not all higher: no.
    assert row(lines, "| every learned model beats move_base in its own environment: walled",
               "our DWA baseline").endswith("| no |")
    # The open-field rows stay beside them, labelled: the learned model 20/30 against 30/30 for both.
    open_dwa = row(lines, "| every learned model beats move_base in its own environment: open field", "dwa:")
    assert open_dwa.endswith("| no |") and "30 of dwa's 30 successes went around the ditch" in open_dwa
    assert row(lines, "open field, against the paper's move_base").endswith("| no |")
    # The pairs table: counts, 95 % Wilson bounds (as the summaries compute them) and the p-value.
    low, high = wilson_interval(24, 30)
    base_low, base_high = wilson_interval(6, 30)
    assert row(lines, "| walled, against dwa_paper | wide_walled | wide_40 |") == (
        f"| walled, against dwa_paper | wide_walled | wide_40 | 24/30 | {pct(low)}-{pct(high)} | dwa_paper | 6/30 | "
        f"{pct(base_low)}-{pct(base_high)} | {boschloo(24, 6):.2g} | yes |")
    assert row(lines, "| walled, against dwa | crater_walled | crater |").endswith(
        f"| 30/30 | {pct(wilson_interval(30, 30)[0])}-100% | dwa | 30/30 | {pct(wilson_interval(30, 30)[0])}-100% | "
        "1 | no |")
    assert any("Boschloo exact test" in line and "intersection-union" in line for line in lines)


def test_the_verdict_flips_when_a_learned_model_loses(tmp_path, results):
    counts = {**COUNTS, "wide": (27, 5, 6, 3)}  # The paper-method wide model now succeeds less than dwa_paper.
    write(results, "must_cross", must_cross_records(str(tmp_path / "models"), counts))
    lines, _ = page_lines(tmp_path, results)
    walled_paper = row(lines, "| every learned model beats move_base in its own environment: walled", "dwa_paper:")
    assert walled_paper.endswith("| no |") and "3 of 4 pairs higher with p < 0.05" in walled_paper
    assert row(lines, "| walled, against dwa_paper | wide_walled | wide_40 |").endswith("| no |")


def test_a_walled_environment_without_learned_results_is_named_not_counted(tmp_path, results):
    records = [r for r in must_cross_records(str(tmp_path / "models"))
               if not (r.environment == "crater_walled" and r.controller == "learned")]
    write(results, "must_cross", records)
    lines, _ = page_lines(tmp_path, results)
    walled_paper = row(lines, "| every learned model beats move_base in its own environment: walled", "dwa_paper:")
    assert "2 of 2 pairs higher" in walled_paper and "no learned model evaluated in crater_walled" in walled_paper
    assert walled_paper.endswith("| yes |")


def test_the_classical_controllers_halts_are_shown_by_region_and_the_backslope_finding_computed(tmp_path, results):
    lines, _ = page_lines(tmp_path, results)
    header = row(lines, "| controller | environment | rollouts | approach |")
    assert header == "| controller | environment | rollouts | approach | down_wall | floor | up_wall | beyond | total |"
    # Summed over the group's 30 rollouts; walled environments first.
    assert row(lines, "| dwa_paper | wide_walled | 30 |") == "| dwa_paper | wide_walled | 30 | 30 | 0 | 60 | 150 | 0 | 240 |"
    assert row(lines, "| dwa_paper | wide | 30 |") == "| dwa_paper | wide | 30 | 0 | 0 | 0 | 0 | 0 | 0 |"
    assert row(lines, "| dwa | crater_walled | 30 |").endswith("| - | - | - | - | - | - |")  # Not counted.
    # dwa_paper's 24 + 30 failures in the walled environments all ended on the up wall, where it halted.
    backslope = row(lines, "| move_base mostly failed on the backslope")
    assert "54 of its 54 failures ended on the up wall" in backslope and "300 of its 480 halts" in backslope
    assert backslope.endswith("| yes |")


def test_the_figure_5e_plot_uses_the_walled_environments_and_keeps_the_open_field_one(tmp_path, results):
    lines, page = page_lines(tmp_path, results)
    walled, open_field = tmp_path / "img" / "fig5_must_cross.png", tmp_path / "img" / "fig5_baseline.png"
    assert walled.stat().st_size > 1000 and open_field.stat().st_size > 1000
    text = page.read_text()
    assert text.index("fig5_must_cross.png") < text.index("fig5_baseline.png")
    caption = next(line for line in lines if "Figure 5e like for like" in line)
    assert "per walled environment" in caption and "n = 30 rollouts each" in caption
    open_caption = next(line for line in lines if "in the open field, per environment" in line)
    assert "dwa_paper" in open_caption and "dwa_paper in wide: 30 of its 30 successes" in open_caption


def test_without_must_cross_results_the_page_keeps_the_open_field_comparison_alone(tmp_path, results):
    (results / "must_cross.jsonl").unlink()
    lines, _ = page_lines(tmp_path, results)
    assert not (tmp_path / "img" / "fig5_must_cross.png").exists()
    assert (tmp_path / "img" / "fig5_baseline.png").exists()
    assert not any(": walled" in line for line in lines)
    assert row(lines, "| every learned model beats move_base in its own environment: open field").endswith("| no |")


def test_the_open_field_row_pairs_the_studys_own_learned_runs_with_its_controllers(tmp_path):
    """Without the paper's other studies, the must_cross study's own open-field runs (the shipped
    model and dwa_paper in `wide`, same seeds) give the open-field row."""
    folder = tmp_path / "results"
    records = must_cross_records(str(tmp_path / "models"))  # dwa_paper in the open wide: 30/30, all around.
    records += group("learned", "wide", "wide", 12)
    write(folder, "must_cross", records)
    groups = must_cross_groups(load_report_data([folder]))
    assert [label for label, _ in groups.open_learned["wide"]] == ["wide"]
    lines, _ = page_lines(tmp_path, folder)
    (row,) = [line for line in lines if "open field, against the paper's move_base" in line]
    assert "wide 40%" in row and "vs 100%" in row and row.endswith("| no |")
    p_value = boschloo_exact([[12, 30], [18, 0]], alternative="two-sided").pvalue
    assert f"p={p_value:.2g}" in row


def test_the_open_field_figure_shows_the_studys_shipped_model_beside_dwa_paper(tmp_path):
    folder = tmp_path / "results"
    write(folder, "must_cross", [*must_cross_records(str(tmp_path / "models")), *group("learned", "wide", "wide", 12)])
    lines, _ = page_lines(tmp_path, folder)
    (caption,) = [line for line in lines if line.startswith("*Figure") and "open field" in line]
    assert "shipped model (blue" in caption and "n = 30 rollouts each" in caption and "dwa_paper (light red)" in caption
    assert (tmp_path / "img" / "fig5_baseline.png").exists()


def test_checkpoints_of_one_stem_in_two_folders_are_two_rows_not_one_pooled(tmp_path):
    folder = tmp_path / "results"
    write(folder, "scalability", group("learned", str(tmp_path / "a" / "wide_40.pt"), "wide", 20)
          + group("learned", str(tmp_path / "b" / "wide_40.pt"), "wide", 10))
    table = load_report_data([folder]).tables["scalability"]
    assert row(table, "| a/wide_40 |", "| wide |").split(" | ")[2] == "20/30"
    assert row(table, "| b/wide_40 |", "| wide |").split(" | ")[2] == "10/30"
