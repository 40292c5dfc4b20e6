"""`collect --backend ray`: the same demonstrations as the local pool, written by the calling
process, resumable; a bad backend or address refused at once."""

import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from ditch_drake.cli.main import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.demos.collect import CollectConfig, collect
from ditch_drake.demos.store import DatasetStore


@pytest.fixture(scope="module")
def local_ray():
    """One Ray of 2 CPUs for the module: `collect` uses the Ray it finds initialized."""
    pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[ray]')")
    from ditch_drake.common.ray_tasks import ray_session

    with ray_session("local", num_cpus=2):
        yield


def _episodes(path) -> list[tuple[dict, dict]]:
    store = DatasetStore.open(path)
    return [(episode.metadata, store.read(episode, mmap=False)) for episode in store.episodes()]


def test_collect_on_ray_records_the_local_pools_demonstrations_and_resumes(tmp_path, local_ray):
    config = CollectConfig(environment="wide", demos=2, seed=0, out=str(tmp_path / "local"), workers=0)
    assert collect(config, progress=False)["recorded"] == 2
    on_ray = CollectConfig(environment="wide", demos=1, seed=0, out=str(tmp_path / "ray"), workers=2, backend="ray",
                           address="local")
    first = collect(on_ray, progress=False)
    assert (first["recorded"], first["unfilled_slots"], first["task_errors"]) == (1, [], {})
    # Run again for two: slot 0 is kept, only slot 1 runs.
    second = collect(CollectConfig(**{**vars(on_ray), "demos": 2}), progress=False)
    assert (second["kept_before"], second["recorded"], second["interrupted"]) == (1, 1, False)
    local, ray = _episodes(tmp_path / "local"), _episodes(tmp_path / "ray")
    assert len(local) == len(ray) == 2
    for (local_metadata, local_arrays), (ray_metadata, ray_arrays) in zip(local, ray):
        assert ray_metadata == local_metadata
        assert set(ray_arrays) == set(local_arrays)
        for name, values in local_arrays.items():
            np.testing.assert_array_equal(ray_arrays[name], values, err_msg=name)
    assert collect(CollectConfig(**{**vars(on_ray), "demos": 2}), progress=False)["recorded"] == 0


def test_ray_tasks_keep_each_result_and_report_a_dead_worker_or_a_raised_error(local_ray):
    from ditch_drake.common.ray_tasks import failure_message, raised_by_task, run_ray_tasks

    def work(n: int) -> int:  # Nested: Ray's pickler sends it by value, not by a module the workers lack.
        if n == 1:
            os._exit(1)  # A worker that dies, as a crash in compiled code or the OOM killer would.
        if n == 2:
            raise ValueError("two")
        return n * 10

    kept, failed = {}, {}
    run_ray_tasks(work, [(0,), (1,), (2,), (3,)], "local", 2, keep=lambda call, result: kept.update({call[0]: result}),
                  failed=lambda call, error: failed.update({call[0]: error}))
    assert kept == {0: 0, 3: 30}
    assert raised_by_task(failed[1]) is None and "WorkerCrashedError" in failure_message(failed[1])
    assert isinstance(raised_by_task(failed[2]), ValueError)


def test_a_slot_whose_ray_task_died_is_unfilled_not_a_traceback(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[ray]')")
    import ditch_drake.demos.collect as collect_module

    def died(function, calls, address, max_in_flight, keep, failed, calls_per_worker=0):
        for call in calls:
            failed(call, ray.exceptions.WorkerCrashedError())

    monkeypatch.setattr(collect_module, "run_ray_tasks", died)
    report = collect(CollectConfig(demos=2, out=str(tmp_path / "d"), backend="ray"), progress=False)
    assert (report["recorded"], report["unfilled_slots"], report["interrupted"]) == (0, [0, 1], False)
    assert "WorkerCrashedError" in report["task_errors"][0]
    assert DatasetStore.open(tmp_path / "d").episodes() == []


def test_an_unknown_backend_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["collect", "--env", "wide", "--demos", "1", "--backend", "spark", "--out", str(tmp_path / "d")])
    assert stop.value.code == 2
    assert "--backend" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="backend='spark'"):
        collect(CollectConfig(demos=1, out=str(tmp_path / "d"), backend="spark"))
    assert not (tmp_path / "d").exists()


def _free_local_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.parametrize("address", ["nohost:1", "unreachable", "not an address"])
def test_a_bad_ray_address_exits_2_within_seconds(tmp_path, capsys, address):
    pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[ray]')")
    address = f"127.0.0.1:{_free_local_port()}" if address == "unreachable" else address
    start = time.monotonic()
    code = main(["collect", "--env", "wide", "--demos", "1", "--workers", "1", "--backend", "ray",
                 "--address", address, "--out", str(tmp_path / "d")])
    assert code == 2
    assert time.monotonic() - start < 15
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(f"ditch-drake: error: Ray address {address!r}")
    assert not (tmp_path / "d").exists()


def test_collect_and_train_generalist_list_the_backend(capsys):
    for command in ("collect", "train-generalist"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = capsys.readouterr().out
        assert "--backend {local,ray}" in text and "--address" in text, command


_CLI_WITH_CTRL_C = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
                    "from ditch_drake.cli.main import main; sys.exit(main())")


@pytest.mark.slow  # Two Ray starts in fresh processes, each importing Drake: about a minute.
@pytest.mark.parametrize("signum, to_group, code", [(signal.SIGINT, True, 130), (signal.SIGTERM, False, 143)])
def test_a_signal_stops_collect_on_ray_keeping_whole_episodes_and_no_ray_process(tmp_path, signum, to_group, code, session_processes):
    pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[ray]')")
    out = tmp_path / "d"
    # In a process group of its own with Ctrl-C's handler (a background job's children ignore
    # SIGINT), as a terminal's foreground job.
    process = subprocess.Popen([sys.executable, "-c", _CLI_WITH_CTRL_C, "collect", "--env", "wide", "--demos", "30",
                                "--workers", "1", "--backend", "ray", "--out", str(out)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 240
    while not (out / "episodes" / "episode_000000" / "episode.json").exists():
        assert process.poll() is None, process.communicate()[1]
        assert time.monotonic() < deadline, "no episode was written"
        time.sleep(0.1)
    start = time.monotonic()
    os.killpg(process.pid, signum) if to_group else process.send_signal(signum)
    _, err = process.communicate(timeout=60)
    assert process.returncode == code, err
    assert time.monotonic() - start < 15
    store = DatasetStore.open(out)
    episodes = store.episodes()
    assert 1 <= len(episodes) < 30 and not store.temporary_episodes()
    for episode in episodes:
        assert all(len(values) == episode.steps for values in store.read(episode).values())
    deadline = time.monotonic() + 10
    while session_processes(process.pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not session_processes(process.pid), "a Ray process outlived the command"
