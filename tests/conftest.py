"""Shared fixtures: scenes are built once per test session where tests only read them."""

from pathlib import Path

import pytest

from ditch_drake.diagrams.ditch_scene import MakeDitchDiagram, SceneConfig
from ditch_drake.evaluation import batch, rollout_worker


@pytest.fixture(scope="session")
def wide_diagram():
    return MakeDitchDiagram(SceneConfig(environment="wide"))


@pytest.fixture
def recorded_pools(monkeypatch) -> list[tuple[int, int]]:
    """Replaces the batch evaluation's worker pools by a stub that records (rollouts, workers)
    of each pool started and keeps a "not run" error record for every rollout."""
    pools = []

    def fake_pool(specs, workers, keep):
        pools.append((len(specs), workers))
        for spec in specs:
            keep(rollout_worker.error_record(spec, "not run", 0.0))
        return []

    monkeypatch.setattr(batch, "_run_pool", fake_pool)
    return pools


@pytest.fixture
def session_processes():
    """A function: the processes of a session (its leader's pid) still alive, "pid command" each
    (Linux /proc); a signal test asserts that none outlived the command."""
    return _session_processes


def _session_processes(session: int) -> list[str]:
    """The processes of `session` still alive (Linux /proc): "pid command" each."""
    alive = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rpartition(")")[2].split()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            continue
        if int(fields[3]) == session and fields[0] != "Z":
            alive.append(f"{entry.name} {command[:80]}")
    return alive
