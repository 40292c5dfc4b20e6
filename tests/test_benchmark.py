"""The procedural ditch benchmark (issue 22): the seeded generator, its ranges and splits, the
`benchmark` command, its report, and the generalist's pipeline pieces."""

import json

import numpy as np
import pytest

from ditch_drake.benchmark.generator import CRATER_MAX_CROSSING_DEG, MAX_DRAWS, sample_ditch
from ditch_drake.benchmark.ranges import BenchmarkRanges, load_ranges, packaged_ranges_path
from ditch_drake.benchmark.run import BenchmarkConfig, benchmark_specs, replay_command
from ditch_drake.benchmark.splits import (
    SEED_SPLITS,
    ditches_file,
    split_of_environment,
    split_ranges,
    split_seeds,
    write_ditches,
)
from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.ditch_scene import MakeDitchDiagram, SceneConfig
from ditch_drake.evaluation.results import read_records
from ditch_drake.world.bypass import check_no_bypass, rasterize_field
from ditch_drake.world.crossing import crossing_turn_deg
from ditch_drake.world.environments import crosses_ditch, get_environment, load_environments, validate_environment
from ditch_drake.world.terrain import DitchTerrain, min_bend_radius_m


def test_the_same_seed_always_gives_the_same_ditch():
    for seed in (0, 7, 1003, 2042):
        first, second = sample_ditch(seed), sample_ditch(seed)
        assert first == second
        assert first.name == f"ditch_{seed:04d}"
    assert sample_ditch(1).environment != sample_ditch(2).environment


def test_the_splits_are_disjoint_and_a_seed_names_its_split():
    seeds = {name: set(values) for name, values in SEED_SPLITS.items()}
    assert seeds["train"] == set(range(200)) and seeds["val"] == set(range(1000, 1050))
    assert seeds["test"] == set(range(2000, 2100)) and seeds["stress"] == set(range(3000, 3100))
    for a, values_a in seeds.items():
        for b, values_b in seeds.items():
            assert a == b or not values_a & values_b
    assert split_of_environment("ditch_0012") == "train" and split_of_environment("ditch_2099") == "test"
    assert split_of_environment("sine") == "paper" and split_of_environment("ditch_0500") == ""
    assert split_of_environment("ditch_3042") == "stress" and split_seeds("stress", 2) == [3000, 3001]
    assert split_seeds("val", 3) == [1000, 1001, 1002]
    with pytest.raises(ConfigError, match="expected one of"):
        split_seeds("holdout")
    with pytest.raises(ConfigError, match="1..100"):
        split_seeds("test", 101)


def test_fifty_sampled_ditches_build_and_every_task_crosses_its_ditch():
    kinds = set()
    for seed in range(50):
        ditch = sample_ditch(seed)
        environment = ditch.environment
        validate_environment(environment)  # the family's limits, the clearances and the bypass proof
        terrain = DitchTerrain(environment.terrain)
        kinds.add(environment.terrain.course)
        grid = rasterize_field(terrain)
        assert len(environment.tasks) == 3
        ranges = BenchmarkRanges()
        for task in environment.tasks:
            assert crosses_ditch(terrain, task.start[:2], task.goal)
            check_no_bypass(terrain, task.start[:2], task.goal, grid)
            # Beyond the ditch's edge by at least the approach drawn, from every part of the
            # course: on curved courses, not just from the crossing point.
            for xy in (task.start[:2], task.goal[:2]):
                assert terrain.beyond_edge_m(np.array(xy)) >= ranges.approach_m[0] - 0.02, (ditch.name, task.name)
        params = environment.terrain
        assert ranges.slope_deg[0] <= params.slope_deg <= ranges.slope_deg[1]
        assert ranges.depth_m[0] <= params.depth_m <= ranges.depth_m[1]
        if seed % 10 == 0:  # the plant builds (each ditch's geometry in a MultibodyPlant)
            MakeDitchDiagram(SceneConfig(environment=ditch.name, environments={ditch.name: environment}))
    assert kinds == {"line", "sine", "arc", "point"}


def test_a_ditch_the_family_cannot_build_is_redrawn_and_the_draw_recorded():
    # Long arcs of the smallest radius crossed at steep angles: most first draws leave no
    # room for a task's start, and are replaced by the seed's next draws.
    tight = BenchmarkRanges(course_kinds=["arc"], arc_radius_m=[12.0, 12.0], course_length_m=[36.0, 36.0],
                            crossing_angle_deg=[35.0, 35.0])
    redrawn = sample_ditch(3, tight)
    assert 1 <= redrawn.draw < MAX_DRAWS
    assert sample_ditch(3, tight) == redrawn
    with pytest.raises(ConfigError, match="seed 0: none of 20 draws"):
        sample_ditch(0, tight)
    impossible = BenchmarkRanges(course_kinds=["sine"], sine_amplitude_m=[10.0, 10.0], sine_wavelength_m=[10.0, 10.0])
    with pytest.raises(ConfigError, match="seed 5: none of"):
        sample_ditch(5, impossible)


@pytest.mark.parametrize("field, value, message", [
    ("slope_deg", [60.0, 45.0], "slope_deg=.*inverted"),
    ("depth_m", [0.5, 4.0], "depth_m=.*out of bounds: expected .*1 <= low"),
    ("course_kinds", ["line", "spiral"], "course_kinds has 'spiral': expected some of"),
    ("bottom_width_m", [2.0], "bottom_width_m=.*not a range"),
])
def test_bad_ranges_name_the_key_and_the_allowed_values(field, value, message):
    ranges = BenchmarkRanges(**{field: value})
    with pytest.raises(ConfigError, match=message):
        ranges.validate()


def test_the_cli_refuses_a_bad_split_or_ranges_file_with_exit_2(tmp_path, capsys):
    out = str(tmp_path / "b.jsonl")
    assert main(["benchmark", "--split", "holdout", "--out", out]) == 2
    assert ("unknown split 'holdout': expected one of "
            "['train', 'val', 'test', 'stress', 'search', 'search_val', 'paper']") in capsys.readouterr().err
    ranges = tmp_path / "ranges.yaml"
    ranges.write_text("slope_deg: [50.0, 40.0]\n")
    assert main(["benchmark", "--split", "val", "--ranges", str(ranges), "--out", out]) == 2
    assert "slope_deg=[50.0, 40.0] is inverted" in capsys.readouterr().err
    ranges.write_text("course_kinds: [line, zigzag]\n")
    assert main(["benchmark", "--split", "val", "--ranges", str(ranges), "--out", out]) == 2
    assert "'zigzag': expected some of ['line', 'sine', 'arc', 'point']" in capsys.readouterr().err
    ranges.write_text("slopes: [50.0, 55.0]\n")
    assert main(["benchmark", "--split", "val", "--ranges", str(ranges), "--out", out]) == 2
    assert "unknown key 'slopes'" in capsys.readouterr().err
    assert main(["benchmark", "--split", "val", "--geometries", "0", "--out", out]) == 2
    assert not (tmp_path / "b.jsonl").exists()


def test_the_ditches_file_reads_back_and_refuses_a_different_ditch_of_the_same_name(tmp_path):
    path = ditches_file(tmp_path / "run.jsonl")
    assert path.name == "run.ditches.yaml"
    ditches = [sample_ditch(seed) for seed in (1000, 1001)]
    write_ditches(path, ditches[:1])
    write_ditches(path, ditches)  # adds the second, keeps the first
    environments = load_environments(path)
    assert list(environments) == ["ditch_1000", "ditch_1001"]
    assert environments["ditch_1001"].terrain.course == ditches[1].environment.terrain.course
    other = sample_ditch(1000, BenchmarkRanges(course_kinds=["line"]))
    with pytest.raises(ConfigError, match="holds a different ditch_1000"):
        write_ditches(path, [other])
    assert list(load_environments(path)) == ["ditch_1000", "ditch_1001"]


def test_the_packaged_ranges_file_is_the_default():
    assert load_ranges() == BenchmarkRanges()


STRESS_RANGES = packaged_ranges_path("stress_ranges.yaml")


def test_the_stress_split_draws_beyond_the_train_ranges_from_its_own_file(tmp_path):
    stress, train = split_ranges("stress"), BenchmarkRanges()
    assert stress == load_ranges(STRESS_RANGES)
    assert split_ranges("test") == split_ranges("val") == split_ranges("train") == train
    assert stress.slope_deg[0] >= train.slope_deg[1] and stress.depth_m[0] >= train.depth_m[1]
    assert stress.bottom_width_m[1] <= train.bottom_width_m[0] and stress.arc_radius_m[1] <= train.arc_radius_m[0]
    assert stress.crossing_angle_deg[0] >= train.crossing_angle_deg[1]
    assert stress.course_kinds == train.course_kinds
    # Arcs down to the family's bend limit of the widest stress ditch.
    assert 0.0 <= stress.arc_radius_m[0] - stress.widest_arc_bend_limit_m() < 0.1
    # A ranges file named for the run overrides the split's.
    other = tmp_path / "ranges.yaml"
    other.write_text("slope_deg: [40.0, 45.0]\n")
    assert split_ranges("stress", other) == BenchmarkRanges(slope_deg=[40.0, 45.0])


def _check_stress_ditches(seeds) -> list:
    """Samples the stress ditches of `seeds` (`sample_ditch` validates each draw as the packaged
    walled environments are: the family's limits, the clearances and the bypass proof), checks
    that they lie in the stress ranges and that every task's line crosses its ditch, turned by
    the drawn angle; returns their terrains."""
    ranges = split_ranges("stress")
    terrains = []
    for seed in seeds:
        ditch = sample_ditch(seed, ranges)
        environment, params = ditch.environment, ditch.environment.terrain
        terrain = DitchTerrain(params)
        terrains.append(params)
        assert ranges.slope_deg[0] <= params.slope_deg <= ranges.slope_deg[1]
        assert ranges.depth_m[0] <= params.depth_m <= ranges.depth_m[1]
        if params.course == "arc":
            assert params.arc_radius_m >= min_bend_radius_m(params)
            assert params.length_m / params.arc_radius_m <= np.radians(ranges.arc_max_sweep_deg)
        for index, task in enumerate(environment.tasks):
            assert crosses_ditch(terrain, task.start[:2], task.goal), (ditch.name, task.name)
            turn = abs(crossing_turn_deg(environment, index))
            if params.course == "point":
                assert turn <= CRATER_MAX_CROSSING_DEG + 0.01
            else:
                assert ranges.crossing_angle_deg[0] - 0.5 <= turn <= ranges.crossing_angle_deg[1] + 0.5, ditch.name
    return terrains


def test_stress_ditches_build_and_every_task_crosses_its_ditch():
    """The first 12 seeds and the tightest arc (all 100: the slow test below)."""
    terrains = _check_stress_ditches([*range(3000, 3012), 3040])
    assert {params.course for params in terrains} == {"line", "sine", "arc", "point"}
    assert terrains[-1].course == "arc" and terrains[-1].arc_radius_m < split_ranges("stress").arc_radius_m[0] + 0.2


@pytest.mark.slow
def test_every_stress_ditch_builds_and_every_task_crosses_its_ditch():
    terrains = _check_stress_ditches(split_seeds("stress"))  # about 15 s
    assert sum(params.course == "arc" for params in terrains) >= 10


def test_a_stress_ditch_builds_in_a_plant():
    ranges = split_ranges("stress")
    for seed in (3040, 3001):  # the tightest arc (6.82 m, its bend limit 5.75 m) and a sine
        ditch = sample_ditch(seed, ranges)
        MakeDitchDiagram(SceneConfig(environment=ditch.name, environments={ditch.name: ditch.environment}))


def test_a_benchmark_run_writes_the_ditches_of_its_splits_ranges_or_of_the_ranges_it_names(tmp_path):
    out = tmp_path / "stress.jsonl"
    specs = benchmark_specs(BenchmarkConfig(split="stress", controller="head_on", geometries=2, out=str(out)),
                            progress=False)
    assert sorted({spec.environment for spec in specs}) == ["ditch_3000", "ditch_3001"] and len(specs) == 6
    stress = split_ranges("stress")
    write_ditches(ditches_file(out), [sample_ditch(3000, stress)])  # the same ditch: accepted
    with pytest.raises(ConfigError, match="holds a different ditch_3000"):
        write_ditches(ditches_file(out), [sample_ditch(3000, BenchmarkRanges())])
    named = tmp_path / "named.jsonl"
    benchmark_specs(BenchmarkConfig(split="stress", controller="head_on", geometries=1, out=str(named),
                                    ranges=str(packaged_ranges_path())), progress=False)
    write_ditches(ditches_file(named), [sample_ditch(3000, BenchmarkRanges())])
    assert load_environments(ditches_file(named))["ditch_3000"].terrain.slope_deg <= BenchmarkRanges().slope_deg[1]


@pytest.mark.parametrize("changes, message", [
    ({"arc_radius_m": [10.0, 30.0]}, r"arc_radius_m=\[10.0, 30.0\] bends tighter .* at least 10.31 m"),
    ({"arc_max_sweep_deg": 200.0}, r"arc_max_sweep_deg=200.0 is out of bounds"),
])
def test_ranges_beyond_the_familys_bend_limit_are_refused(changes, message):
    with pytest.raises(ConfigError, match=message):
        BenchmarkRanges(**changes).validate()
    # Arcs that are not drawn need no radius the family builds.
    BenchmarkRanges(course_kinds=["line", "point"], arc_radius_m=[10.0, 30.0]).validate()


@pytest.mark.parametrize("change, message", [
    ("arc_radius_m: [6.0, 12.0]", ("arc_radius_m=[6.0, 12.0] bends tighter than the terrain family builds: "
                                   "expected a low end of at least 6.66 m")),
    ("depth_m: [5.0, 7.0]", "depth_m=[5.0, 7.0] is out of bounds: expected [low, high] with 1 <= low <= high <= 6"),
])
def test_a_stress_ranges_file_out_of_the_familys_limits_exits_2_naming_the_key(tmp_path, capsys, change, message):
    key = change.partition(":")[0]
    lines = [change if line.startswith(key + ":") else line for line in STRESS_RANGES.read_text().splitlines()]
    bad = tmp_path / "stress_ranges.yaml"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match=key):
        load_ranges(bad)
    out = tmp_path / "stress.jsonl"
    assert main(["benchmark", "--split", "stress", "--ranges", str(bad), "--geometries", "1", "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists() and not ditches_file(out).exists()


@pytest.mark.slow
def test_the_expert_on_the_first_stress_ditch_records_its_three_tasks(tmp_path, capsys):
    """The issue's bar: `benchmark --split stress --controller expert --geometries 1 --rollouts 1`."""
    out = tmp_path / "stress_expert.jsonl"
    assert main(["benchmark", "--split", "stress", "--controller", "expert", "--geometries", "1", "--rollouts", "1",
                 "--workers", "0", "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["recorded"] == 3
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert sorted((r["environment"], r["task"]) for r in records) == [("ditch_3000", task) for task in range(3)]
    assert load_environments(ditches_file(out))["ditch_3000"] == sample_ditch(3000, split_ranges("stress")).environment


def test_a_benchmark_run_records_every_task_of_every_ditch_and_its_report_names_the_failures(tmp_path, capsys):
    """The bar's command on the val split, in-process (the test split is for reports only)."""
    out = tmp_path / "val_expert.jsonl"
    assert main(["benchmark", "--split", "val", "--controller", "expert", "--geometries", "2", "--rollouts", "1",
                 "--workers", "0", "--time-limit", "60", "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["recorded"] == 6 and summary["geometries"] == 2
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert sorted((r["environment"], r["task"]) for r in records) == [
        (f"ditch_{seed}", task) for seed in (1000, 1001) for task in range(3)]
    assert all(r["environments_file"] == str(ditches_file(out)) for r in records)
    page = tmp_path / "report.md"
    assert main(["benchmark-report", str(out), "--out", str(page)]) == 0
    text = page.read_text()
    assert "| expert (privileged: analytic terrain) | " in text and "## Failed generated ditches" in text
    assert (tmp_path / "report_img" / "benchmark_success_by_parameter.png").exists()
    assert "| wall slope (deg) | 45-50 | 50-55 | 55-57 | 57-60 |" in text  # the figure's numbers
    assert ("| crossing's turn from square (deg; + left) | -45 to -35 | -35 to -15 | -15 to -5 | -5 to 5 | 5 to 15 | "
            "15 to 35 | 35 to 45 |") in text
    # Results of ditches drawn from other ranges under the same names are not pooled.
    other = tmp_path / "other.jsonl"
    other.write_text(out.read_text())
    write_ditches(ditches_file(other), [sample_ditch(1000, BenchmarkRanges(course_kinds=["line"]))])
    assert main(["benchmark-report", str(out), str(other), "--out", str(tmp_path / "mixed.md")]) == 2
    assert "its ditch_1000 differs from" in capsys.readouterr().err
    for record in records:
        if not record["success"]:
            assert f"--env {record['environment']} --task {record['task']} --seed {record['seed']}" in text
    # The replay command names the benchmark's expert whole (it makes room along the ditch first).
    recorded, _ = read_records(out)
    command = replay_command(recorded[0])
    assert "--override '{controller: !ExpertConfig {" in command and "lead_in: true" in command
    assert f"--environments {ditches_file(out)} --env {recorded[0].environment}" in command
    # Run again: nothing is recorded twice.
    assert main(["benchmark", "--split", "val", "--controller", "expert", "--geometries", "2", "--workers", "0",
                 "--time-limit", "60", "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["recorded"] == 0


def test_curvature_of_each_course_kind():
    sine = sample_ditch(next(s for s in range(200) if sample_ditch(s).environment.terrain.course == "sine"))
    params = sine.environment.terrain
    k = 2 * np.pi / params.sine_wavelength_m
    assert DitchTerrain(params).max_curvature_per_m == pytest.approx(params.sine_amplitude_m * k**2)


def test_crossing_turn_of_the_paper_tasks_and_of_generated_ones():
    # The packaged diagonal tasks start at x = -5 (east-bound, turned right) and x = 5.
    assert [crossing_turn_deg(get_environment("wide"), task) for task in range(3)] == pytest.approx(
        [0.0, -np.degrees(np.arctan2(10, 22)), np.degrees(np.arctan2(10, 22))])
    assert [crossing_turn_deg(get_environment("crater"), task) for task in range(3)] == pytest.approx([0, 0, 0], abs=1e-9)
    # The sine's middle task runs north where the course climbs at atan(A k); its bend tasks cross square on.
    sine = get_environment("sine")
    slope = np.degrees(np.arctan(sine.terrain.sine_amplitude_m * 2 * np.pi / sine.terrain.sine_wavelength_m))
    assert crossing_turn_deg(sine, 0) == pytest.approx(-slope, abs=0.5)
    assert abs(crossing_turn_deg(sine, 1)) < 2 and abs(crossing_turn_deg(sine, 2)) < 2
    # Generated tasks turn by their drawn crossing angle, either way, within the ranges.
    turns = [crossing_turn_deg(sample_ditch(seed).environment, task) for seed in range(8) for task in range(3)]
    limit = BenchmarkRanges().crossing_angle_deg[1]
    assert all(abs(turn) <= limit + 0.01 for turn in turns)
    assert min(turns) < -5 and max(turns) > 5


def test_report_names_checkpoints_of_one_stem_by_their_folders():
    from dataclasses import fields

    from ditch_drake.evaluation.model_labels import controller_labels
    from ditch_drake.evaluation.results import RolloutRecord

    def record(controller, checkpoint):
        return RolloutRecord(**{**{item.name: None for item in fields(RolloutRecord)},
                                "controller": controller, "checkpoint": checkpoint})

    records = [record("learned", "data/a/round2.pt"), record("learned", "data/b/round2.pt"),
               record("learned", "generalist"), record("learned", "data/a/generalist.pt"),
               record("learned", "data/a/round3.pt"), record("expert", "")]
    assert [controller_labels(records)(r) for r in records] == [
        "a/round2", "b/round2", "generalist", "a/generalist", "round3", "expert"]


def test_a_collection_over_several_environments_visits_each_task_in_order(tmp_path):
    """The generalist's demonstrations: demo i drives the i-th (environment, task) pair."""
    from ditch_drake.demos.collect import CollectConfig, slot_pairs

    ditches = [sample_ditch(seed) for seed in (3, 4)]
    path = write_ditches(tmp_path / "train.ditches.yaml", ditches)
    config = CollectConfig(environments=[d.name for d in ditches], environments_file=str(path))
    assert slot_pairs(config) == [(name, task) for name in ("ditch_0003", "ditch_0004") for task in range(3)]
    assert slot_pairs(CollectConfig(environment="wide")) == [("wide", 0), ("wide", 1), ("wide", 2)]
    with pytest.raises(ConfigError, match="unknown environment 'ditch_0009'"):
        slot_pairs(CollectConfig(environments=["ditch_0009"], environments_file=str(path)))


def test_the_paper_split_runs_the_four_packaged_ditches_and_its_report_has_a_column_each(tmp_path, capsys):
    out = tmp_path / "paper_head_on.jsonl"
    assert main(["benchmark", "--split", "paper", "--controller", "head_on", "--time-limit", "2", "--workers", "0",
                 "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["recorded"] == 12
    page = tmp_path / "paper.md"
    assert main(["benchmark-report", str(out), "--out", str(page)]) == 0
    text = page.read_text()
    assert "| controller | crater | narrow | sine | wide |" in text
    assert ("| head_on (privileged: analytic terrain) | 0/3 (0%-56%) | 0/3 (0%-56%) | 0/3 (0%-56%) | 0/3 (0%-56%) |"
            in text)


@pytest.mark.parametrize("option, value", [("--dagger-stride", "0"), ("--dagger-rounds", "-1"),
                                           ("--demos-per-task", "0"), ("--ensemble", "1")])
def test_train_generalist_refuses_a_bad_count_before_any_work(tmp_path, capsys, option, value):
    work = tmp_path / "generalist"
    assert main(["train-generalist", option, value, "--work-dir", str(work), "--out", str(tmp_path / "g.pt")]) == 2
    assert f"{option.lstrip('-').replace('-', '_')}={value}: expected an integer >=" in capsys.readouterr().err
    assert not work.exists()


def test_train_generalist_refuses_mirror_with_canonical_side_before_any_work(tmp_path, capsys):
    work = tmp_path / "generalist"
    assert main(["train-generalist", "--mirror", "--canonical-side", "--work-dir", str(work),
                 "--out", str(tmp_path / "g.pt")]) == 2
    assert "mirror and canonical_side: expected at most one (--mirror, --canonical-side)" in capsys.readouterr().err
    assert not work.exists()


def test_train_generalist_refuses_to_resume_a_work_dir_made_with_other_settings(tmp_path, capsys):
    from ditch_drake.benchmark.ranges import packaged_ranges_path
    from ditch_drake.pipelines.generalist import GENERALIST_TRAIN_RANGES, RECIPE_FILE, GeneralistConfig, _check_recipe

    work = tmp_path / "generalist"
    work.mkdir()
    _check_recipe(work, GeneralistConfig(), load_ranges(packaged_ranges_path(GENERALIST_TRAIN_RANGES)))
    made_with = (work / RECIPE_FILE).read_text()
    assert main(["train-generalist", "--canonical-side", "--work-dir", str(work), "--out", str(tmp_path / "g.pt")]) == 2
    assert "canonical_side=True: expected False, the setting" in capsys.readouterr().err
    assert (work / RECIPE_FILE).read_text() == made_with and sorted(p.name for p in work.iterdir()) == [RECIPE_FILE]
    other_ranges = tmp_path / "ranges.yaml"
    other_ranges.write_text("crater_diameter_m: [9.0, 12.0]\n")
    assert main(["train-generalist", "--train-ranges", str(other_ranges), "--work-dir", str(work),
                 "--out", str(tmp_path / "g.pt")]) == 2
    assert "train_ranges.crater_diameter_m=[9.0, 12.0]: expected [8.0, 12.0]" in capsys.readouterr().err


def test_a_generalist_work_dir_keeps_its_class_balancing_and_one_made_before_it_was_recorded_is_smotes(tmp_path, capsys):
    from ditch_drake.benchmark.ranges import packaged_ranges_path
    from ditch_drake.pipelines.generalist import GENERALIST_TRAIN_RANGES, RECIPE_FILE, GeneralistConfig, _check_recipe

    ranges = load_ranges(packaged_ranges_path(GENERALIST_TRAIN_RANGES))
    work = tmp_path / "generalist"
    work.mkdir()
    _check_recipe(work, GeneralistConfig(), ranges)
    assert json.loads((work / RECIPE_FILE).read_text())["balancing"] == "oversample"  # The default.
    assert main(["train-generalist", "--balancing", "smote", "--work-dir", str(work),
                 "--out", str(tmp_path / "g.pt")]) == 2
    assert "balancing=smote: expected oversample, the setting" in capsys.readouterr().err
    made_before = json.loads((work / RECIPE_FILE).read_text())
    del made_before["balancing"]
    (work / RECIPE_FILE).write_text(json.dumps(made_before))
    _check_recipe(work, GeneralistConfig(balancing="smote"), ranges)  # SMOTE, as every run then trained.
    with pytest.raises(ConfigError, match="balancing=oversample: expected smote"):
        _check_recipe(work, GeneralistConfig(), ranges)


def test_the_generalist_trains_on_the_benchmark_ranges_with_craters_from_8_m():
    from dataclasses import asdict

    from ditch_drake.benchmark.ranges import packaged_ranges_path
    from ditch_drake.pipelines.generalist import GENERALIST_TRAIN_RANGES

    train, benchmark = asdict(load_ranges(packaged_ranges_path(GENERALIST_TRAIN_RANGES))), asdict(load_ranges())
    assert train.pop("crater_diameter_m") == [8.0, 12.0] and benchmark.pop("crater_diameter_m") == [10.0, 12.0]
    assert train == benchmark


def test_train_generalist_refuses_a_bad_train_ranges_file_before_any_work(tmp_path, capsys):
    bad = tmp_path / "train_ranges.yaml"
    bad.write_text("crater_diameter_m: [12.0, 8.0]\n")
    work = tmp_path / "generalist"
    assert main(["train-generalist", "--train-ranges", str(bad), "--work-dir", str(work),
                 "--out", str(tmp_path / "g.pt")]) == 2
    assert "crater_diameter_m=[12.0, 8.0] is inverted" in capsys.readouterr().err
    assert not work.exists()


def test_the_benchmark_command_replaces_its_workers_every_30_rollouts(tmp_path, recorded_pools):
    """Every generated ditch builds diagrams of its own: the pools are refreshed more often."""
    assert main(["benchmark", "--split", "val", "--controller", "head_on", "--geometries", "11", "--workers", "1",
                 "--out", str(tmp_path / "val.jsonl")]) == 0
    assert recorded_pools == [(30, 1), (3, 1)]
