"""Every example of the tutorials docs/tutorials/your_{ditch,controller,study}.md runs: the custom
ditches, the custom controller, the scenario file and the study, each as the page tells a user to run
it (from the repository root)."""

import dataclasses
import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from ditch_drake.cli import main
from ditch_drake.diagrams import controllers
from ditch_drake.diagrams.scenario import load_scenario
from ditch_drake.pipelines.experiment import load_experiment, run_experiment
from ditch_drake.world.environments import load_environments

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples"


@pytest.fixture
def at_repo_root(monkeypatch):
    """The examples name their files relative to the repository root, as the docs run them."""
    monkeypatch.chdir(REPO)


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def test_my_ditches_load_and_the_expert_crosses_steep52(at_repo_root, tmp_path):
    environments = load_environments("examples/my_ditches.yaml")
    assert {"steep52", "gentle_sine"} <= set(environments)
    steep = environments["steep52"].terrain
    assert (steep.course, steep.slope_deg, steep.bottom_width_m, steep.depth_m) == ("line", 52.0, 3.5, 3.8)
    assert len(environments["steep52"].tasks) == 3

    out = tmp_path / "steep52.jsonl"
    code = main(["evaluate", "--environments", "examples/my_ditches.yaml", "--env", "steep52", "--controller",
                 "expert", "--rollouts", "1", "--task", "0", "--workers", "0", "--out", str(out)])
    assert code == 0
    (record,) = read_jsonl(out)
    assert (record["controller"], record["environment"], record["task"]) == ("expert", "steep52", 0)
    assert record["status"] == "reached_goal", record


def test_goal_seeker_runs_through_batch_evaluation(monkeypatch, tmp_path):
    # The example registers "goal_seeker" on import; the registry is restored after the test so
    # that the other tests see the built-in controllers only.
    monkeypatch.setattr(controllers, "_REGISTRY", dict(controllers._REGISTRY))
    monkeypatch.syspath_prepend(str(EXAMPLES))
    monkeypatch.delitem(sys.modules, "goal_seeker_controller", raising=False)
    example = importlib.import_module("goal_seeker_controller")
    from ditch_drake.evaluation.batch import evaluate, make_specs

    assert "goal_seeker" in controllers.controller_names()
    out = tmp_path / "seeker.jsonl"
    report = evaluate(make_specs(example.GoalSeekerConfig(), "", "wide", tasks=[0], rollouts=1), out, workers=0,
                      progress=False)
    assert report.recorded == 1
    (record,) = read_jsonl(out)
    assert (record["controller"], record["environment"]) == ("goal_seeker", "wide")
    assert record["status"] == "rolled_over", record  # Head-on into 55 deg walls: the example's point.


def test_goal_seeker_script_runs():
    done = subprocess.run([sys.executable, str(EXAMPLES / "goal_seeker_controller.py")], cwd=REPO, check=False,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "goal_seeker in wide, task 0: rolled_over" in done.stdout


def test_my_scenarios_load_and_one_replays(at_repo_root, tmp_path, capsys):
    dwa = load_scenario("examples/my_scenario.yaml", "dwa_in_steep52")
    assert (dwa.environment, dwa.environments_file, dwa.task) == ("steep52", "examples/my_ditches.yaml", 0)
    assert type(dwa.controller).__name__ == "DwaBaselineConfig"
    assert dwa.episode.time_limit_s == 90.0
    expert = load_scenario("examples/my_scenario.yaml", "expert_in_wide")
    assert (expert.environment, expert.environments_file, expert.task) == ("wide", "", 1)
    assert type(expert.controller).__name__ == "ExpertConfig"
    assert load_scenario("examples/my_scenario.yaml", "expert_in_wide", "{seed: 3}").seed == 3

    page = tmp_path / "r.html"
    code = main(["replay", "--scenario", "examples/my_scenario.yaml", "--scenario-name", "expert_in_wide",
                 "--out", str(page)])
    assert code == 0
    assert page.stat().st_size > 0
    assert "expert in wide task 1 seed 0: reached_goal" in capsys.readouterr().out


def test_my_study_evaluates_and_reports(at_repo_root, tmp_path):
    config = load_experiment("examples/my_study.yaml")
    assert config.environments_file == "examples/my_ditches.yaml"
    assert config.results_dir.startswith("results/") and not config.report
    assert type(config.studies.baseline.controller).__name__ == "DwaBaselineConfig"
    assert config.studies.baseline.controller.planner.costmap.lethal_slope_deg == 60.0

    results = tmp_path / "my_study"
    fast = dataclasses.replace(config, results_dir=str(results), tasks=[0], rollouts=1, time_limit_s=30.0,
                               workers=0)
    run_experiment(fast, stages=("evaluate", "report"), progress=False)
    records = read_jsonl(results / "baseline.jsonl")
    assert sorted(r["environment"] for r in records) == sorted(config.studies.baseline.environments)
    assert {r["controller"] for r in records} == {"dwa"}
    page = (results / "report.md").read_text()
    assert config.name in page
    assert "| dwa | steep52 |" in page
