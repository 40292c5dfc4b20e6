"""The control step's profile split (`ditch_drake.perf.profile_step`) and the policy-step timings."""

import types

import pytest

from ditch_drake.perf import profile_step

ADVANCE = ("~", 0, profile_step.ADVANCE[1])
LIDAR = ("/x/ditch_drake/systems/lidar.py", 196, "_update")
STACKER = ("/x/ditch_drake/systems/frame_stacker.py", 109, "_push")
IMAGE = ("/x/ditch_drake/systems/normal_image_converter.py", 123, "_calc_image")
POLICY = ("/x/ditch_drake/systems/policy.py", 139, "_update")
MONITOR = ("/x/ditch_drake/systems/episode_monitor.py", 123, "_update")
PULL = ("~", 0, "<built-in method pydrake.systems.framework.EvalBasicVector>")


def _entry(cumulative_s: float, callers: dict) -> tuple:
    # pstats' (primitive calls, calls, own time, cumulative time, {caller: edge}) per function.
    return (1, 1, 0.0, cumulative_s, callers)


def _edge(cumulative_s: float) -> tuple:
    return (1, 1, 0.0, cumulative_s)


def _stats(advance_s: float) -> types.SimpleNamespace:
    """A profile of 10 control steps: the stacker pulls the image; the rest is called by AdvanceTo."""
    return types.SimpleNamespace(stats={
        ADVANCE: _entry(advance_s, {}),
        LIDAR: _entry(0.02, {ADVANCE: _edge(0.02)}),
        STACKER: _entry(0.03, {ADVANCE: _edge(0.03)}),
        PULL: _entry(0.025, {STACKER: _edge(0.025)}),
        IMAGE: _entry(0.025, {PULL: _edge(0.025)}),
        POLICY: _entry(0.04, {ADVANCE: _edge(0.04)}),
        MONITOR: _entry(0.005, {ADVANCE: _edge(0.005)}),
    })


def test_the_split_counts_the_pulled_image_apart_from_the_stacker_and_the_rest_as_cpp():
    split = profile_step.split_control_step(_stats(advance_s=0.12), control_steps=10)
    assert split["advance_ms_per_step"] == pytest.approx(12.0)
    assert split["lidar_render_and_cloud_ms"] == pytest.approx(2.0)
    assert split["normal_image_ms"] == pytest.approx(2.5)
    assert split["frame_stacker_ms"] == pytest.approx(0.5)
    assert split["policy_ms"] == pytest.approx(4.0)
    assert split["other_python_blocks_ms"] == pytest.approx(0.5)
    # 120 ms in AdvanceTo, 95 ms of it in Python callbacks.
    assert split["plant_and_framework_cpp_ms"] == pytest.approx(2.5)
    shares = [value for key, value in split.items() if key.endswith("_share")]
    assert sum(shares) == pytest.approx(1.0)


def test_the_network_is_counted_layer_by_layer():
    # Two 3 x 3 convolutions (4 -> 64 on 128 x 128, 64 -> 32 on 32 x 32) are almost all of it.
    convolutions = 128 * 128 * 64 * 4 * 9 + 32 * 32 * 32 * 64 * 9
    multiply_adds = profile_step.network_multiply_adds("wide")
    assert convolutions < multiply_adds < convolutions * 1.01


def test_the_bench_times_one_clone_an_ensemble_and_the_onnx_runtime_in_float_and_int8():
    from ditch_drake.perf import bench_training

    pytest.importorskip("onnxruntime")
    one = bench_training.measure_policy_step_ms(repeats=2)
    five = bench_training.measure_ensemble_policy_step_ms(repeats=2)
    onnx = bench_training.measure_onnxruntime_policy_step_ms(repeats=2)
    assert 0 < one["policy_step_ms"] <= one["policy_step_max_ms"]
    assert 0 < five["ensemble_policy_step_ms"] <= five["ensemble_policy_step_max_ms"]
    assert 0 < onnx["policy_step_onnxruntime_ms"] <= onnx["policy_step_onnxruntime_max_ms"]
    assert 0 < onnx["policy_step_onnxruntime_int8_ms"] <= onnx["policy_step_onnxruntime_int8_max_ms"]
