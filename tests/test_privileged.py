"""Privileged inputs are declared: what each controller reads beyond its sensors, pose and goal,
given only to a controller that declares it, carried by its records and marked in every table."""

import dataclasses
import json
from dataclasses import dataclass

import pytest
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource

from ditch_drake.benchmark.results_page import write_benchmark_report
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams import controllers
from ditch_drake.diagrams.controllers import controller_config, controller_view, get_controller, register_controller
from ditch_drake.diagrams.ditch_scene import AddDitchScene, SceneConfig
from ditch_drake.diagrams.lidar_rig import AddLidar
from ditch_drake.diagrams.rollout import AddController, ConstantCommandConfig, LearnedPolicyConfig
from ditch_drake.evaluation import rollout_worker
from ditch_drake.evaluation.batch import make_specs
from ditch_drake.evaluation.model_labels import controller_labels, model_demos
from ditch_drake.evaluation.report_data import study_table
from ditch_drake.evaluation.results import SCHEMA_VERSION, RolloutRecord, read_records, record_key
from ditch_drake.world.terrain import DitchTerrain


@pytest.mark.parametrize("name, privileged", [
    ("expert", ("terrain",)), ("edge_angle", ("terrain",)), ("head_on", ("terrain",)), ("learned", ()),
    ("dwa", ()), ("dwa_paper", ()), ("mppi", ()), ("constant", ())])
def test_each_built_in_controller_declares_what_it_reads_beyond_its_sensors(name, privileged):
    assert get_controller(name).privileged_inputs(controller_config(name)) == privileged


def test_the_learned_policy_is_privileged_only_when_told_its_side_by_the_oracle():
    learned = get_controller("learned")
    assert learned.privileged_inputs(LearnedPolicyConfig(crossing_side="perceived")) == ()
    assert learned.privileged_inputs(LearnedPolicyConfig(crossing_side="oracle")) == ("terrain",)


@pytest.mark.parametrize("privileged, message", [("terrain", "expected a tuple of names"),
                                                 (("map",), "privileged input 'map'")])
def test_a_declaration_of_no_known_input_is_refused(privileged, message):
    with pytest.raises(ConfigError, match=message):
        register_controller("badly_declared", PeekerConfig, TerrainPeeker, "a test's controller", privileged=privileged)


@dataclass
class PeekerConfig:
    speed_mps: float = 0.5


class TerrainPeeker(LeafSystem):
    """Reads the analytic ditch when built: a test's controller, declared or not."""

    def __init__(self, config: PeekerConfig, site):
        super().__init__()
        self.depth_m = site.terrain.params.depth_m
        self.terrain = site.terrain
        self.DeclareVectorOutputPort("command", 2, lambda context, output: output.SetFromVector(
            [config.speed_mps, 0.0]))


@dataclass
class DeclaredPeekerConfig:
    speed_mps: float = 0.5


@dataclass
class PeekingBuilderConfig:
    read: str = "terrain"  # "terrain" or "environment"


def add_peeking_builder(builder, scene, config: PeekingBuilderConfig):
    """A builder function that reads the scene's terrain, or its environment's terrain parameters."""
    terrain = scene.terrain if config.read == "terrain" else scene.environment.terrain
    return builder.AddNamedSystem("peeker", ConstantVectorSource([terrain.slope_deg * 0.0, 0.0])).get_output_port()


@pytest.fixture(scope="module", autouse=True)
def peekers():
    """The test's controllers, registered for this module's tests only (other modules list the registry)."""
    register_controller("undeclared_peeker", PeekerConfig, TerrainPeeker, "reads the terrain undeclared (a test's)")
    register_controller("declared_peeker", DeclaredPeekerConfig, TerrainPeeker,
                        "reads the terrain declared (a test's)", privileged=("terrain",))
    register_controller("peeking_builder", PeekingBuilderConfig, add_peeking_builder,
                        "a builder function reading the terrain undeclared (a test's)")
    yield
    for name in ("undeclared_peeker", "declared_peeker", "peeking_builder"):
        controllers._REGISTRY.pop(name)


def _build(config):
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, SceneConfig(environment="narrow", task=1))
    AddController(builder, scene, config)
    return builder.Build(), scene


def test_a_block_that_reads_the_terrain_undeclared_fails_when_its_diagram_is_built_naming_it():
    with pytest.raises(ConfigError, match=r"controller 'undeclared_peeker' reads the analytic terrain \(terrain.params"
                                          r"\).*privileged=\('terrain',\)"):
        _build(PeekerConfig())


def test_a_block_that_declares_the_terrain_gets_the_scenes_own():
    diagram, scene = _build(DeclaredPeekerConfig())
    peeker = diagram.GetSubsystemByName("declared_peeker")
    assert isinstance(peeker.terrain, DitchTerrain) and peeker.terrain is scene.terrain
    assert peeker.depth_m == scene.terrain.params.depth_m


@pytest.mark.parametrize("read", ["terrain", "environment"])
def test_a_builder_function_that_reads_the_terrain_undeclared_fails_naming_it(read):
    with pytest.raises(ConfigError, match="controller 'peeking_builder' reads the analytic terrain"):
        _build(PeekingBuilderConfig(read=read))


def test_records_carry_what_the_controller_declared_and_the_side_blocks_source():
    (expert,) = make_specs("expert", "", "wide", [0], rollouts=1)
    (dwa,) = make_specs("dwa", "", "wide", [0], rollouts=1)
    assert rollout_worker.error_record(expert, "boom").privileged == ["terrain"]
    assert rollout_worker.error_record(dwa, "boom").privileged == []
    (still,) = make_specs(ConstantCommandConfig([0.0, 0.0]), "", "narrow", [1], rollouts=1, time_limit_s=0.5)
    record = rollout_worker.run_rollout(still)
    assert record.status == "timeout" and (record.privileged, record.crossing_side_source) == ([], "")
    line = json.loads(record.to_json())
    assert line["schema_version"] == SCHEMA_VERSION == 7 and line["privileged"] == []
    for source in ("perceived", "oracle"):
        builder = DiagramBuilder()
        builder.AddNamedSystem(f"{source}_crossing_side", ConstantVectorSource([0.0]))
        assert rollout_worker.crossing_side_source(builder.Build()) == source
    builder = DiagramBuilder()
    builder.AddNamedSystem("crossing_side", ConstantVectorSource([0.0]))
    assert rollout_worker.crossing_side_source(builder.Build()) == ""


def _record(**changes) -> RolloutRecord:
    record = RolloutRecord(**{
        "key": "k", "controller": "expert", "checkpoint": "", "environment": "wide", "task": 0, "seed": 0,
        "time_limit_s": 120.0, "goal_radius_m": 1.5, "checkpoint_sha256": "", "status": "reached_goal",
        "success": True, "time_s": 30.0, "path_length_m": 10.0, "peak_abs_roll_deg": 1.0,
        "peak_abs_pitch_deg": 30.0, "peak_tilt_deg": 30.0, "min_stability_margin_deg": 20.0, "final_x_m": 0.0,
        "final_y_m": 1.0, "failure_region": "", "wall_s": 1.0, **changes})
    record.key = record_key(record)
    return record


def test_records_of_schema_5_read_with_nothing_declared_and_the_same_key(tmp_path):
    record = _record(privileged=["terrain"])
    line = json.loads(record.to_json())
    old = {key: value for key, value in line.items() if key not in ("privileged", "crossing_side_source")}
    path = tmp_path / "old.jsonl"
    path.write_text(json.dumps(old | {"schema_version": 5}) + "\n")
    (read,), warnings = read_records(path)
    assert (read.privileged, read.crossing_side_source, read.key, warnings) == ([], "", record.key, [])


def _side_records(seeds=range(2)) -> list[RolloutRecord]:
    """The expert, and one clone told its side both ways, on the same seeds."""
    learned = {"controller": "learned", "checkpoint": "generalist", "checkpoint_sha256": "abc"}
    return [record for seed in seeds for record in (
        _record(seed=seed, privileged=["terrain"]),
        _record(seed=seed, **learned, controller_sha256="p", crossing_side_source="perceived"),
        _record(seed=seed, **learned, controller_sha256="o", crossing_side_source="oracle", privileged=["terrain"],
                success=False, status="rolled_over"))]


def test_tables_mark_privileged_rows_and_keep_the_two_side_sources_apart():
    records = _side_records()
    label = controller_labels(records)
    assert [label(r) for r in records[:3]] == [
        "expert (privileged: analytic terrain)", "generalist (perceived side)",
        "generalist (oracle side; privileged: analytic terrain)"]
    assert controller_labels(records, marks=False)(records[2]) == "generalist"
    assert model_demos("wide_40 (oracle side)") == 40
    lines, summaries = study_table(records)
    assert "| expert (privileged: analytic terrain) | wide | 2/2 |" in "\n".join(lines)
    assert summaries[("generalist (perceived side)", "wide")].successes == 2
    assert summaries[("generalist (oracle side; privileged: analytic terrain)", "wide")].successes == 0


def test_the_benchmark_page_marks_privileged_rows(tmp_path):
    results = tmp_path / "paper.jsonl"
    results.write_text("".join(record.to_json() + "\n" for record in _side_records()))
    page = write_benchmark_report([results], tmp_path / "page.md")
    text = page.read_text()
    assert "reads what the robot cannot sense" in text
    assert "| expert (privileged: analytic terrain) | 2/2 " in text
    assert "| generalist (perceived side) | 2/2 " in text
    assert "| generalist (oracle side; privileged: analytic terrain) | 0/2 " in text


def test_a_user_builder_of_sensors_still_renders_the_terrain_undeclared():
    # `AddLidar` gives the scene graph the terrain's boxes through the controller's view of the scene.
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, SceneConfig(environment="narrow", task=1))
    view = controller_view(scene, "a_user_controller", ())
    assert dataclasses.is_dataclass(view) and view.plant is scene.plant and view.task is scene.task
    AddLidar(builder, view)
    with pytest.raises(ConfigError, match="'a_user_controller' reads the analytic terrain"):
        view.terrain.nearest_on_course((0.0, 0.0))
    assert controller_view(scene, "a_user_controller", ("terrain",)) is scene


def test_a_batch_stops_at_the_first_rollout_of_an_undeclared_reader_naming_it(tmp_path):
    from ditch_drake.evaluation.batch import evaluate, load_results

    specs = make_specs(PeekerConfig(), "", "narrow", [1], rollouts=3, time_limit_s=0.5)
    out = tmp_path / "peeker.jsonl"
    with pytest.raises(ConfigError, match="controller 'undeclared_peeker' reads the analytic terrain"):
        evaluate(specs, out, workers=0, progress=False)
    [record] = load_results([out])  # The first rollout's error is kept; the other two never ran.
    assert record.status == "error" and "undeclared_peeker" in record.error


def test_the_benchmark_page_measures_the_perceived_side_against_the_oracles(tmp_path):
    learned = {"controller": "learned", "checkpoint": "generalist", "checkpoint_sha256": "abc",
               "crossing_side_source": "perceived", "environment": "narrow"}
    records = [_record(**learned, seed=0, side_zone_steps=300, side_agreeing_steps=300),
               _record(**learned, seed=1, side_zone_steps=200, side_agreeing_steps=150, side_unseen_steps=10,
                       side_disagreement_edge_m=[0.5, 2.4], success=False, status="rolled_over")]
    results = tmp_path / "paper.jsonl"
    results.write_text("".join(record.to_json() + "\n" for record in records))
    text = write_benchmark_report([results], tmp_path / "page.md").read_text()
    assert "| generalist (perceived side) | paper | 450/500 (90.00 %); 1/2 | 450/500 (90.00 %); 1/2 |" in text
    assert "| generalist (perceived side) | narrow | 0 | 1 | line |" in text
    assert "| 150/200 | 10 | +0.5 to +2.4 | rolled_over |" in text


def test_a_controller_with_the_window_search_is_its_own_marked_row(tmp_path):
    plain = _record(controller="mppi", controller_config="planner: {}\n")
    searching = _record(controller="mppi", controller_config="planner: {}\nsearch: {}\n", controller_sha256="s")
    label = controller_labels([plain, searching])
    assert (label(plain), label(searching)) == ("mppi", "mppi (window search)")
    results = tmp_path / "search.jsonl"
    results.write_text(plain.to_json() + "\n" + searching.to_json() + "\n")
    text = write_benchmark_report([results], tmp_path / "page.md").read_text()
    assert "| mppi (window search) | 1/1 " in text and "\"window search\": a controller driven" in text


def test_an_mppi_with_a_climb_threshold_is_its_own_marked_row():
    searching = _record(controller="mppi", controller_config="planner: {samples: 256}\nsearch: {}\n")
    climbing = _record(controller="mppi", controller_sha256="c", controller_config=(
        "planner: {fore_aft_margin_threshold_deg: 16.0, climb_fore_aft_margin_threshold_deg: 11.0}\nsearch: {}\n"))
    label = controller_labels([searching, climbing])
    assert (label(searching), label(climbing)) == ("mppi (window search)", "mppi (window search; climb margin 11 deg)")


@pytest.mark.parametrize("configs, labels", [
    (("planner: {climb_fore_aft_margin_threshold_deg: 11.0}\nsearch: {edge_standoff_m: 0.8, hold_way_m: 0.5}\n",
      "search: {hold_way_m: 0.5, keep_off_seen_drops: true}\n"),
     ("mppi (window search, way held 0.5 m; climb margin 11 deg)",
      "mppi (window search, way held 0.5 m, off seen drops)")),
    (("search: {first_leg_m: 8.0, max_search_m: 60.0, hold_way_m: 0.5}\n",
      "search: {first_leg_m: 40.0, max_search_m: 60.0, hold_way_m: 0.5}\n"),
     ("mppi (window search, way held 0.5 m)", "mppi (window search, first leg 40 m, way held 0.5 m)")),
], ids=["way held, off seen drops", "first leg"])
def test_a_search_setting_off_its_default_is_its_own_marked_row(configs, labels):
    records = [_record(controller="mppi", controller_sha256=str(i), controller_config=config)
               for i, config in enumerate(configs)]
    label = controller_labels(records)
    assert [label(record) for record in records] == list(labels)


def test_the_benchmark_page_gives_time_and_path_length_paired_with_the_most_successful_controller(tmp_path):
    expert = [_record(environment="wide", task=task, time_s=30.0 + task, path_length_m=10.0) for task in range(3)]
    mppi = [_record(controller="mppi", controller_config="planner: {}\n", controller_sha256="m", environment="wide",
                    task=task, time_s=60.0 + 2 * task, path_length_m=15.0, success=task < 2,
                    status="reached_goal" if task < 2 else "rolled_over") for task in range(3)]
    results = tmp_path / "paper.jsonl"
    results.write_text("".join(record.to_json() + "\n" for record in expert + mppi))
    text = write_benchmark_report([results], tmp_path / "page.md").read_text()
    assert "| expert | paper | 3 | 31 (30-32) | 10 (10-10) | - | - | - | - |" in text
    # mppi crossed tasks 0 and 1: 60/30 and 62/31 s, 15/10 m.
    assert "| mppi | paper | 2 | 61 (60-62) | 15 (15-15) | expert | 2 | 2.00 | 1.50 |" in text
