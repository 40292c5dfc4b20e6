"""The command line: subcommands exist, bad input exits 2 with a clear message."""

import json

import pytest

from ditch_drake.cli import build_parser, main


def test_subcommands_exist():
    parser = build_parser()
    for command in ("demo", "view", "calibrate", "bench"):
        assert parser.parse_args([command]).command == command


def test_unknown_environment_is_a_clear_error(capsys):
    assert main(["demo", "--env", "moat"]) == 2
    assert "unknown environment 'moat'" in capsys.readouterr().err


def test_bench_json_has_unit_suffixed_keys(capsys, monkeypatch):
    from ditch_drake.perf import bench

    monkeypatch.setattr(bench.measure_plant_rtf, "__defaults__", (0, 0.5, "", 1))
    monkeypatch.setattr(bench.measure_closed_loops, "__defaults__", (0, 0.5, 2, ""))
    monkeypatch.setattr(bench, "measure_blocks", lambda: {"lidar_render_and_cloud_ms": 1.0})
    monkeypatch.setattr(bench, "measure_rollouts_per_minute", lambda: {"evaluate_rollouts_per_min": 1.0})
    from ditch_drake.perf import bench_training

    monkeypatch.setattr(bench_training, "measure_training_throughput", lambda: {"train_samples_per_s": 1.0})
    monkeypatch.setattr(bench_training, "measure_streaming_memory", lambda: {"train_peak_rss_mib": 1.0})
    from ditch_drake.perf import bench_gym

    monkeypatch.setattr(bench_gym.measure_gym_env, "__defaults__", ("wide", 0, 0, 1))
    from ditch_drake.perf import bench_scene

    monkeypatch.setattr(bench_scene, "build_cases", lambda: [("narrow", None, "narrow")])
    monkeypatch.setattr(bench_scene, "RSS_ENVIRONMENTS", ("narrow",))
    monkeypatch.setattr(bench_scene.measure_diagram_rss, "__defaults__", (("narrow",),))
    monkeypatch.setattr(bench_scene.measure_benchmark_rollouts_per_min, "__defaults__", (1,))
    assert main(["bench", "--json", "--env", "narrow"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert set(figures) >= {"plant_narrow_rtf", "scene_build_narrow_s", "plant_min_rtf", "peak_rss_mib",
                            "plant_narrow_walled_rtf", "scene_build_narrow_walled_s",
                            "closed_loop_narrow_rtf", "observation_update_narrow_ms", "observation_first_step_narrow_ms",
                            "closed_loop_min_rtf", "host_reference_start_ms", "host_reference_end_ms"}
    assert all(key.rsplit("_", 1)[-1] in {"rtf", "s", "mib", "ms", "min", "ratio"} for key in figures)
    assert {"train_samples_per_s", "evaluate_rollouts_per_min", "train_wide_40_demos_s", "train_peak_rss_mib"} <= set(figures)
    assert figures["gym_env_steps_per_s"] > 0 and figures["gym_env_step_time_ratio"] > 0
    assert figures["plant_narrow_rtf"] > 0
    assert figures["scene_build_max_s"] > 0 and figures["diagram_rss_mib"] > 0
    assert figures["benchmark_rollouts_per_min"] > 0


def test_training_on_cuda_without_a_gpu_is_a_clear_error(capsys, tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    assert main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "m.pt"), "--device", "cuda"]) == 2
    assert "torch sees no CUDA device" in capsys.readouterr().err
    assert not (tmp_path / "m.pt").exists()


def test_every_shipped_model_loads_and_says_where_it_was_trained(capsys):
    from ditch_drake.learning.checkpoint import SHIPPED_MODELS

    assert main(["checkpoint-info", *SHIPPED_MODELS]) == 0
    header, *rows = capsys.readouterr().out.splitlines()
    # An ensemble's members have a row each: "generalist_k5[0]" ...
    assert header.split()[-1] == "device" and {row.split()[0].split("[")[0] for row in rows} == set(SHIPPED_MODELS)
    # The paper-method models were trained on this project's reference CPU (their time is a bench figure).
    assert all(row.split()[-1] == "cpu" for row in rows if row.split()[0].endswith("_bc40"))


@pytest.mark.slow
def test_calibration_passes_in_every_environment():
    """The full calibration benchmark (10 seeded trials each): the physics shows the paper's phenomenon."""
    from ditch_drake.validation.calibration import CalibrationConfig, run_calibration

    report = run_calibration(CalibrationConfig(), progress=False)
    assert report["all_ok"], json.dumps(report, indent=1)


def test_view_runs_an_episode_in_meshcat(capsys):
    assert main(["view", "--env", "narrow", "--realtime-rate", "0"]) == 0
    out = capsys.readouterr().out
    assert "meshcat: open http" in out and "outcome: reached_goal" in out


def test_ci_runs_exactly_the_readme_test_command():
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    readme_commands = [line.strip() for line in (root / "README.md").read_text().splitlines()
                       if line.strip().startswith("pip install -e ")]
    assert readme_commands[:2] == ["pip install -e . && ditch-drake demo",
                                   "pip install -e '.[test]' && python -m pytest -q"]
    ci_lines = [line.strip() for line in (root / ".ci" / "run").read_text().splitlines()
                if line.strip() and not line.lstrip().startswith("#")]
    assert ci_lines[-1] == readme_commands[1]


def test_collect_labeller_choice_reaches_the_dagger_labeller(capsys, monkeypatch, tmp_path):
    from ditch_drake.demos import collect as collect_module

    seen = []
    monkeypatch.setattr(collect_module, "collect", lambda config: seen.append(config) or {"unfilled_slots": [], "interrupted": False})
    out = str(tmp_path / "dagger")
    assert main(["collect", "--env", "narrow", "--out", out, "--learner", "narrow", "--labeller", "replanning"]) == 0
    assert main(["collect", "--env", "narrow", "--out", out, "--learner", "narrow"]) == 0
    assert [config.variation.replan_each_step for config in seen] == [True, False]
    assert all(config.variation.steering_noise_radps == 0.0 for config in seen)
    assert main(["collect", "--env", "narrow", "--out", out, "--labeller", "replanning"]) == 2
    assert "--labeller replanning: a labeller needs --learner" in capsys.readouterr().err


def test_collect_lead_in_reaches_the_expert_and_the_labeller(monkeypatch, tmp_path):
    from ditch_drake.demos import collect as collect_module

    seen = []
    monkeypatch.setattr(collect_module, "collect", lambda config: seen.append(config) or {"unfilled_slots": [], "interrupted": False})
    out = str(tmp_path / "demos")
    assert main(["collect", "--env", "narrow", "--out", out, "--lead-in"]) == 0
    assert main(["collect", "--env", "narrow", "--out", out, "--lead-in", "--learner", "narrow"]) == 0
    assert main(["collect", "--env", "narrow", "--out", out]) == 0
    assert [config.variation.lead_in for config in seen] == [True, True, False]
    assert seen[0].variation.steering_noise_radps > 0.0  # The demonstrators' variation, not the labeller's.


def test_defaults_are_the_config_dataclasses():
    from ditch_drake.benchmark.run import BenchmarkConfig
    from ditch_drake.diagrams.scenario import Scenario
    from ditch_drake.pipelines.generalist import GeneralistConfig

    benchmark = build_parser().parse_args(["benchmark"])
    config = BenchmarkConfig()
    assert (benchmark.split, benchmark.controller, benchmark.geometries, benchmark.rollouts, benchmark.seed,
            benchmark.out, benchmark.ranges, benchmark.time_limit, benchmark.workers, benchmark.backend,
            benchmark.address) == (config.split, config.controller, config.geometries, config.rollouts, config.seed,
                                   config.out, config.ranges, config.time_limit_s, config.workers, config.backend,
                                   config.address)
    generalist = build_parser().parse_args(["train-generalist"])
    config = GeneralistConfig()
    assert all(getattr(generalist, name) == getattr(config, name)
               for name in ("out", "work_dir", "train_geometries", "demos_per_task", "dagger_rounds", "val_geometries",
                            "dagger_stride", "epochs", "balancing", "seed", "workers", "ranges", "train_ranges"))
    demo = build_parser().parse_args(["demo"])
    assert (demo.env, demo.task, demo.seed) == (Scenario().environment, Scenario().task, Scenario().seed)


@pytest.mark.parametrize("argv, named", [
    (["evaluate", "--controller", "constant", "--checkpoint", "wide", "--env", "wide", "--rollouts", "1"],
     "checkpoint 'wide' with controller 'constant'"),
    (["replay", "--controller", "dwa", "--checkpoint", "wide"], "--checkpoint wide"),
    (["view", "--realtime-rate", "nan"], "--realtime-rate nan"),
    (["teleop", "--realtime-rate", "-1", "--out", "unused"], "--realtime-rate -1.0"),
])
def test_an_option_the_command_cannot_use_exits_2_naming_it(argv, named, capsys, tmp_path):
    assert main([*argv, *(["--out", str(tmp_path / "x.jsonl")] if argv[0] == "evaluate" else [])]) == 2
    error = capsys.readouterr().err
    assert named in error and error.count("\n") == 1


def test_an_import_that_raises_exits_2_naming_the_module(capsys, tmp_path):
    module = tmp_path / "raises_at_import.py"
    module.write_text("raise RuntimeError('broken extension')\n")
    assert main(["--import", str(module), "scenario"]) == 2
    error = capsys.readouterr().err
    assert "raises_at_import.py" in error and "RuntimeError: broken extension" in error
