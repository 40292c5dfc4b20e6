"""Scenarios, the controller registry, and custom environment files on every command."""

import json
from dataclasses import dataclass
from pathlib import Path

import pytest
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from ditch_drake.cli import main
from ditch_drake.common.config_yaml import config_from_yaml, config_to_yaml
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.controllers import (
    controller_config,
    controller_names,
    get_controller,
    register_controller,
)
from ditch_drake.diagrams.ditch_scene import AddDitchScene, SceneConfig
from ditch_drake.diagrams.rollout import AddController
from ditch_drake.diagrams.scenario import Scenario, load_scenario, scenario_yaml
from ditch_drake.evaluation.batch import evaluate, make_specs
from ditch_drake.evaluation.results import read_records

CUSTOM = """\
environments:
  steep52:
    description: A straight ditch, 3.5 m bottom, 3.8 m deep, walls at 52 deg.
    terrain: {course: line, bottom_width_m: 3.5, depth_m: 3.8, slope_deg: 52.0}
    tasks:
      - {name: straight_across, start: [0.0, -10.0, 90.0], goal: [0.0, 10.0]}
      - {name: across_to_the_east, start: [-5.0, -10.0, 90.0], goal: [5.0, 10.0]}
      - {name: across_to_the_west, start: [5.0, -10.0, 90.0], goal: [-5.0, 10.0]}
"""


@pytest.fixture
def custom_file(tmp_path) -> Path:
    path = tmp_path / "my_ditches.yaml"
    path.write_text(CUSTOM)
    return path


def _comparable(scenario: Scenario) -> str:
    # Drake's own config structs have no ==; their YAML has every field.
    return scenario_yaml(scenario)


def test_the_default_scenario_round_trips_through_yaml(tmp_path):
    path = tmp_path / "scenario.yaml"
    path.write_text(scenario_yaml())
    loaded = load_scenario(path)
    assert _comparable(loaded) == _comparable(Scenario())
    assert (loaded.environment, loaded.task, loaded.seed, loaded.controller) == ("wide", 1, 1, Scenario().controller)


def test_named_scenarios_and_override_text(tmp_path):
    path = tmp_path / "scenarios.yaml"
    path.write_text("baseline:\n  environment: narrow\n  controller: !DwaBaselineConfig\n    planner:\n"
                    "      planner_patience: 2.0\nexpert:\n  controller: !ExpertConfig {}\n")
    baseline = load_scenario(path, "baseline")
    assert baseline.environment == "narrow" and baseline.controller.planner.planner_patience == 2.0
    assert type(load_scenario(path, "expert").controller).__name__ == "ExpertConfig"
    changed = load_scenario(path, "baseline", override="{task: 2, controller: !DwaBaselineConfig {planner: {controller_patience: 3.0}}}")
    assert changed.task == 2 and changed.environment == "narrow"  # Only what the override names changes.
    assert (changed.controller.planner.planner_patience, changed.controller.planner.controller_patience) == (2.0, 3.0)
    assert type(load_scenario(path, "baseline", override="{controller: !ExpertConfig {}}").controller).__name__ == \
        "ExpertConfig"
    with pytest.raises(ConfigError, match="line 5: unknown key 'controller.planner.patience'"):
        _bad_planner(tmp_path)  # A typo inside a tagged controller config is named with its line.
    with pytest.raises(ConfigError, match="no scenario 'nope'"):
        load_scenario(path, "nope")


def _bad_planner(tmp_path):
    path = tmp_path / "typo.yaml"
    path.write_text("environment: narrow\ncontroller: !DwaBaselineConfig\n  planner:\n    costmap: {}\n"
                    "    patience: 2.0\n")
    load_scenario(path)


@pytest.mark.parametrize("text, message", [
    ("", "is empty"),
    ("tsk: 1\n", "line 1: unknown key 'tsk'"),
    ("task: one\n", "line 1: task is 'one' (str); expected int"),
    ("controller: !Teleporter {}\n", "expected a controller tag among"),
    ("task: 7\n", "task index 7 is out of range"),
    ("environment: moat\n", "unknown environment 'moat'"),
    ("seed: -3\n", "seed=-3"),
])
def test_bad_scenario_files_name_the_file_key_and_value(tmp_path, capsys, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_scenario(path)
    assert main(["replay", "--scenario", str(path), "--out", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err
    assert message in err and (str(path) in err or "task index" in err or "unknown environment" in err or
                               "seed=" in err)


def test_scenario_print_is_a_template_that_loads_back(tmp_path, capsys):
    assert main(["scenario", "--print"]) == 0
    path = tmp_path / "template.yaml"
    path.write_text(capsys.readouterr().out)
    assert _comparable(load_scenario(path)) == _comparable(Scenario(controller=controller_config("learned", "wide")))
    assert main(["scenario", "--print", "--override", "{controller: !ExpertConfig {}, task: 0}"]) == 0
    assert "!ExpertConfig" in capsys.readouterr().out


@pytest.mark.parametrize("name", controller_names())
def test_every_registered_controller_builds_from_its_yaml(name):
    config = controller_config(name, seed=4)
    loaded = config_from_yaml(type(config), config_to_yaml(config))
    assert loaded == config
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, SceneConfig(environment="narrow", task=1))
    AddController(builder, scene, loaded)
    builder.Build()


def test_a_controller_of_another_registered_config_is_refused():
    with pytest.raises(ConfigError, match="config of no registered controller"):
        AddController(DiagramBuilder(), None, object())
    with pytest.raises(ConfigError, match="unknown controller 'teleporter'"):
        get_controller("teleporter")


@dataclass
class ToyConfig:
    speed_mps: float = 0.5


class ToyDriver(LeafSystem):
    """Drives straight at a fixed speed: a controller registered by a test."""

    def __init__(self, config: ToyConfig, site):
        super().__init__()
        self.DeclareVectorOutputPort("command", 2, lambda context, output: output.SetFromVector(
            [config.speed_mps, 0.0]))


def test_a_toy_controller_registered_here_runs_through_the_batch_path(tmp_path):
    register_controller("toy", ToyConfig, ToyDriver, "drives straight (a test's controller)")
    assert "toy" in controller_names()
    out = tmp_path / "toy.jsonl"
    specs = make_specs(ToyConfig(speed_mps=0.5), "", "wide", [0], rollouts=1, time_limit_s=3.0)
    faster = make_specs(ToyConfig(speed_mps=0.7), "", "wide", [0], rollouts=1, time_limit_s=3.0)
    assert specs[0].key != faster[0].key  # Its parameters are in the key.
    report = evaluate(specs + faster, out, workers=0, progress=False)
    assert report.recorded == 2 and report.errors == 0
    records = {record.controller_sha256: record for record in read_records(out)[0]}
    slow, fast = records[specs[0].controller_sha256], records[faster[0].controller_sha256]
    assert slow.controller == "toy" and slow.status == "timeout"
    assert fast.path_length_m > slow.path_length_m > 1.0
    assert "speed_mps: 0.5" in slow.controller_config


def test_evaluate_takes_a_controller_config_from_a_scenario(tmp_path, capsys):
    scenario = tmp_path / "dwa.yaml"
    scenario.write_text("controller: !DwaBaselineConfig\n  planner: {planner_patience: 2.0}\nenvironment: narrow\n"
                        "episode: {time_limit_s: 2.0}\n")
    out = tmp_path / "r.jsonl"
    assert main(["evaluate", "--scenario", str(scenario), "--task", "0", "--rollouts", "1", "--workers", "0",
                 "--out", str(out)]) == 0
    (record,), _ = read_records(out)
    assert (record.controller, record.environment, record.time_limit_s) == ("dwa", "narrow", 2.0)
    assert "planner_patience: 2.0" in record.controller_config


def test_the_custom_ditch_bar_the_expert_crosses_it(custom_file, tmp_path, capsys):
    out = tmp_path / "x.jsonl"
    assert main(["evaluate", "--environments", str(custom_file), "--env", "steep52", "--controller", "expert",
                 "--rollouts", "1", "--task", "1", "--workers", "0", "--out", str(out)]) == 0
    (record,), _ = read_records(out)
    assert record.environment == "steep52" and record.environments_file == str(custom_file)
    assert record.status == "reached_goal" and record.peak_tilt_deg > 20.0  # Through the ditch, not around it.
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["recorded"] == 1


def test_replay_and_view_take_a_custom_environment(custom_file, tmp_path, capsys, monkeypatch):
    assert main(["replay", "--environments", str(custom_file), "--env", "steep52", "--task", "0", "--controller",
                 "head_on", "--out", str(tmp_path / "r.html")]) == 0
    assert "head_on in steep52 task 0" in capsys.readouterr().out
    assert main(["view", "--environments", str(custom_file), "--env", "steep52", "--controller", "head_on",
                 "--task", "0", "--realtime-rate", "0"]) == 0
    assert "outcome: rolled_over" in capsys.readouterr().out


def test_demo_collect_calibrate_and_bench_pass_the_environments_file_on(custom_file, tmp_path, monkeypatch):
    from ditch_drake.demos import collect as collect_module
    from ditch_drake.perf import bench
    from ditch_drake.validation import calibration

    seen = {}

    def remember(name, value, result):
        seen[name] = value
        return result

    monkeypatch.setattr(collect_module, "collect", lambda config: remember(
        "collect", config, {"unfilled_slots": [], "interrupted": False}))
    monkeypatch.setattr(calibration, "run_calibration", lambda config, environments, progress: remember(
        "calibrate", (config, environments), {"all_ok": True}))
    monkeypatch.setattr(bench, "run_bench", lambda environments, training, environments_file="": remember(
        "bench", (environments, environments_file), {"x_ms": 1.0}))
    assert main(["collect", "--environments", str(custom_file), "--env", "steep52", "--out", str(tmp_path)]) == 0
    assert seen["collect"].environments_file == str(custom_file)
    assert main(["calibrate", "--environments", str(custom_file), "--env", "steep52", "--json"]) == 0
    assert seen["calibrate"][0].environments_file == str(custom_file) and seen["calibrate"][1] == ["steep52"]
    assert main(["bench", "--environments", str(custom_file), "--env", "steep52", "--json"]) == 0
    assert seen["bench"] == (["steep52"], str(custom_file))
    assert main(["demo", "--environments", str(custom_file), "--env", "steep52", "--task", "7"]) == 2


def test_an_unknown_environment_in_a_custom_file_lists_the_files_names(custom_file, capsys):
    assert main(["evaluate", "--environments", str(custom_file), "--env", "moat", "--out", "unused.jsonl"]) == 2
    err = capsys.readouterr().err
    assert "unknown environment 'moat'" in err and "steep52" in err


def test_a_bad_environments_file_names_the_file_and_key(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text(CUSTOM.replace("slope_deg: 52.0", "slope_deg: steep"))
    assert main(["evaluate", "--environments", str(bad), "--env", "steep52", "--out", str(tmp_path / "x.jsonl")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "environments.steep52.terrain.slope_deg is 'steep'" in err
