"""The closed-loop repeat benchmark (`ditch_drake.benchmarks.bench_closed_loop`)."""

import json

import pytest

from ditch_drake.benchmarks import bench_closed_loop


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
    monkeypatch.setattr(bench_closed_loop, "measure_closed_loop", lambda name: _sample(next(figures), 30.0))
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
