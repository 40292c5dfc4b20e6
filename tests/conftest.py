"""Shared fixtures: scenes are built once per test session where tests only read them."""

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
