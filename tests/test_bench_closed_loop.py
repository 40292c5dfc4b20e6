"""The closed-loop repeat benchmark (`ditch_drake.perf.bench_closed_loop`)."""

import json

import pytest

from ditch_drake.perf import bench_closed_loop


def _sample(observation_ms: float, rtf: float) -> dict:
    return {"observation_update_wide_ms": observation_ms, "closed_loop_wide_rtf": rtf}


def test_summary_counts_the_repeats_meeting_each_target():
    samples = [_sample(2.0, 40.0), _sample(3.2, 30.0), _sample(2.5, 24.0)]
    summary = bench_closed_loop.summarize(samples, ["wide"])
    assert summary["repeats"] == 3
    assert summary["observation_update_wide_ms_median"] == 2.5
    assert summary["observation_update_wide_ms_max"] == 3.2
    assert summary["observation_update_wide_ms_meets_target_count"] == 2
    assert summary["closed_loop_wide_rtf_min"] == 24.0
    assert summary["closed_loop_wide_rtf_meets_target_count"] == 2
    assert summary["repeats_meeting_every_target"] == 1


def test_prints_one_line_per_repeat_and_a_summary(capsys, monkeypatch):
    figures = iter([2.0, 3.5])
    monkeypatch.setattr(bench_closed_loop, "measure_host_reference_ms", lambda: 25.0)
    monkeypatch.setattr(bench_closed_loop, "measure_closed_loops", lambda names: _sample(next(figures), 30.0))
    bench_closed_loop.main(["2", "wide"])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["observation_update_wide_ms"] for line in lines[:2]] == [2.0, 3.5]
    assert lines[0]["host_reference_start_ms"] == 25.0
    assert lines[2]["summary"]["repeats_meeting_every_target"] == 1


def test_bad_arguments_are_named():
    with pytest.raises(SystemExit, match="'moat'"):
        bench_closed_loop.main(["1", "moat"])
    with pytest.raises(ValueError, match="repeats=0"):
        bench_closed_loop.sample_closed_loop(0, ["wide"])


def test_environments_take_turns_episode_by_episode(monkeypatch):
    from ditch_drake.perf import bench

    runs = []

    def fake_timed_run(diagram, seed, duration_s, warmup_s):
        runs.append((diagram, seed))
        # Loop and plant-only runs alternate; the loop takes 0.05 s longer over 1 simulated s.
        is_loop = len(runs) % 2 == 1
        return (0.05 if is_loop else 0.0) + 0.01 * seed, 1.0, 0.02 if is_loop else 0.0

    monkeypatch.setattr(bench, "timed_run", fake_timed_run)
    figures = bench.measure_closed_loops(["narrow", "wide"], seed=1, episodes=3)
    loops = [runs[i] for i in range(0, len(runs), 2)]
    assert [seed for _, seed in loops] == [1, 1, 2, 2, 3, 3]
    assert loops[0][0] is loops[2][0] and loops[0][0] is not loops[1][0]  # narrow, wide, narrow, ...
    assert list(figures)[:3] == ["closed_loop_narrow_rtf", "observation_update_narrow_ms",
                                 "observation_first_step_narrow_ms"]
    # The median episode (seed 2): 0.07 s of wall time for 1 s (10 control steps), 5 ms a step
    # more than the plant alone.
    assert figures["closed_loop_wide_rtf"] == pytest.approx(1.0 / 0.07)
    assert figures["observation_update_wide_ms"] == pytest.approx(5.0)
    assert figures["observation_first_step_wide_ms"] == pytest.approx(20.0)
    with pytest.raises(ValueError, match="episodes=0"):
        bench.measure_closed_loops(["wide"], episodes=0)
