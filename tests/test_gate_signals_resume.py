"""`ditch-drake gate-signals` keeps each episode as it finishes: a stopped recording continues
where it stopped and ends with the file an unstopped one writes, a rerun with other settings is
refused, and a finished recording is not overwritten."""

import numpy as np
import pytest

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.evaluation import gate_signals
from ditch_drake.evaluation.gate_signals import PARTS_VERSION, EpisodeParts, EpisodeSignals, parts_folder, parts_header
from ditch_drake.learning import gate_calibration

ARGV = ["gate-signals", "--checkpoint", "wide_bc40", "--env", "wide", "--task", "1", "--rollouts", "2", "--seed", "4",
        "--time-limit", "3", "--workers", "0"]
RUN_EPISODE = gate_signals.RunEpisode


def _stop_after(monkeypatch, episodes: int) -> list[int]:
    """Runs `episodes` episodes, then raises KeyboardInterrupt as Ctrl-C would; returns the seeds run."""
    seeds = []

    def run(simulator, diagram, scene, seed, **options):
        if len(seeds) == episodes:
            raise KeyboardInterrupt
        seeds.append(seed)
        return RUN_EPISODE(simulator, diagram, scene, seed, **options)

    monkeypatch.setattr(gate_signals, "RunEpisode", run)
    return seeds


def _arrays(path) -> dict:
    with np.load(path, allow_pickle=False) as data:
        return {name: data[name] for name in data.files}


def test_a_stopped_recording_continues_to_the_file_of_an_unstopped_one(tmp_path, monkeypatch, capsys):
    whole, resumed = tmp_path / "whole.npz", tmp_path / "resumed.npz"
    assert main([*ARGV, "--out", str(whole)]) == 0
    assert not parts_folder(whole).exists()
    capsys.readouterr()

    _stop_after(monkeypatch, 1)
    assert main([*ARGV, "--out", str(resumed)]) == 130
    err = capsys.readouterr().err
    assert "episode 1/2: wide task 1 seed 4: timeout" in err and "run the same command again" in err, err
    assert not resumed.exists() and not (tmp_path / "resumed.auc.json").exists()
    assert sorted(path.name for path in parts_folder(resumed).iterdir()) == ["header.json", "wide.task1.seed4.npz"]

    seeds = _stop_after(monkeypatch, 99)
    assert main([*ARGV, "--out", str(resumed)]) == 0
    err = capsys.readouterr().err
    assert seeds == [5], "the kept episode is not run again"
    assert "1/2 episodes finished before" in err and "episode 2/2: wide task 1 seed 5" in err, err
    assert not parts_folder(resumed).exists()
    expected, found = _arrays(whole), _arrays(resumed)
    assert sorted(found) == sorted(expected)
    for name, array in expected.items():
        np.testing.assert_array_equal(found[name], array, err_msg=name)
    assert found["episode_seed"].tolist() == [4, 5] and found["episode"].tolist() == [0] * 30 + [1] * 30
    assert (tmp_path / "resumed.auc.json").read_text() == (tmp_path / "whole.auc.json").read_text()

    # A finished recording is refused, not recorded again.
    assert main([*ARGV, "--out", str(resumed)]) == 2
    assert "exists (a finished recording)" in capsys.readouterr().err
    assert seeds == [5]


def test_worker_processes_record_the_file_one_process_records(tmp_path, capsys, monkeypatch):
    one, two = tmp_path / "one.npz", tmp_path / "two.npz"
    argv = [*ARGV[:ARGV.index("--env")], "--env", "wide", "--env", "narrow", "--env", "sine",
            *ARGV[ARGV.index("--task"):-2]]
    assert main([*argv, "--workers", "0", "--out", str(one)]) == 0
    # One pair per worker and pool: two pools for three pairs, the second with one worker.
    pools = []

    class CountedPool(gate_signals.WorkerPool):
        def __init__(self, max_workers, **options):
            pools.append(max_workers)
            super().__init__(max_workers, **options)

    monkeypatch.setattr(gate_signals, "PAIRS_PER_WORKER", 1)
    monkeypatch.setattr(gate_signals, "WorkerPool", CountedPool)
    assert main([*argv, "--workers", "2", "--out", str(two)]) == 0
    assert pools == [2, 1]
    err = capsys.readouterr().err
    assert "episode 6/6:" in err, err
    expected, found = _arrays(one), _arrays(two)
    assert sorted(found) == sorted(expected)
    for name, array in expected.items():
        np.testing.assert_array_equal(found[name], array, err_msg=name)
    assert found["episode_environment"].tolist() == ["wide", "wide", "narrow", "narrow", "sine", "sine"]
    assert not parts_folder(two).exists()


def test_workers_without_a_parts_folder_are_refused():
    with pytest.raises(ConfigError, match="workers=2: recording in worker processes needs a parts folder"):
        gate_signals.record_gate_signals("wide_bc40", [("wide", 1)], rollouts=1, workers=2)


@pytest.mark.parametrize("options, mismatch", [
    (["--time-limit", "2"], "time_limit_s 3.0 there, 2.0 now"),
    (["--checkpoint", "narrow_bc40"], "checkpoint_sha256"),
    (["--risk"], "risk False there, True now"),
])
def test_a_rerun_with_other_settings_is_refused(tmp_path, monkeypatch, capsys, options, mismatch):
    out = tmp_path / "signals.npz"
    _stop_after(monkeypatch, 0)
    assert main([*ARGV, "--out", str(out)]) == 130
    assert EpisodeParts.begun(parts_folder(out))
    capsys.readouterr()
    seeds = _stop_after(monkeypatch, 99)
    assert main([*ARGV, *options, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{parts_folder(out)} holds the episodes of a recording with other settings ({mismatch}" in err, err
    assert seeds == [] and not out.exists()


def test_a_folder_of_another_parts_version_is_refused_naming_the_version(tmp_path, monkeypatch, capsys):
    out = tmp_path / "signals.npz"
    _stop_after(monkeypatch, 0)
    assert main([*ARGV, "--out", str(out)]) == 130
    header = parts_folder(out) / "header.json"
    header.write_text(header.read_text().replace(f'"version": {PARTS_VERSION}', '"version": 1'))
    capsys.readouterr()
    seeds = _stop_after(monkeypatch, 99)
    assert main([*ARGV, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"(parts version 1 there, {PARTS_VERSION} now" in err and f"delete {parts_folder(out)}" in err, err
    assert seeds == [] and not out.exists()


def test_a_stop_while_the_files_are_written_is_finished_by_the_rerun(tmp_path, monkeypatch, capsys):
    out, report = tmp_path / "signals.npz", tmp_path / "signals.auc.json"
    argv = [*ARGV, "--rollouts", "1", "--out", str(out)]

    def stopped(path, report):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(gate_calibration, "write_auc_report", stopped)
        assert main(argv) == 130
    assert out.exists() and not report.exists() and EpisodeParts.begun(parts_folder(out))
    seeds = _stop_after(monkeypatch, 99)
    assert main(argv) == 0
    assert seeds == [] and report.is_file() and not parts_folder(out).exists()
    assert _arrays(out)["episode_seed"].tolist() == [4]


def test_episode_parts_keep_every_episode_under_its_own_name(tmp_path):
    parts = EpisodeParts.open(tmp_path / "parts", parts_header("abc", 3.0))
    episodes = [EpisodeSignals(name, 1, 7, "timeout", 3.0, [0.003, 0.103], {"mean_softmax_entropy": [0.25, 1.0 / 3]})
                for name in ("my ditch/2", "my_ditch_2")]
    for episode in episodes:
        parts.keep(episode)
    assert len({parts.path(episode.key) for episode in episodes}) == 2
    assert [parts.finished(episode.key) for episode in episodes] == episodes
    assert parts.finished(("my_ditch_2", 1, 8)) is None
    # The same settings continue it; a folder whose header was removed is begun afresh, without its leftovers.
    assert EpisodeParts.open(tmp_path / "parts", parts_header("abc", 3.0)).finished(episodes[0].key) == episodes[0]
    (tmp_path / "parts" / "header.json").unlink()
    assert EpisodeParts.open(tmp_path / "parts", parts_header("abc", 3.0)).finished(episodes[0].key) is None
