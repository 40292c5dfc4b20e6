"""Shared fixtures: scenes are built once per test session where tests only read them."""

import pytest

from ditch_drake.diagrams.ditch_scene import MakeDitchDiagram, SceneConfig


@pytest.fixture(scope="session")
def wide_diagram():
    return MakeDitchDiagram(SceneConfig(environment="wide"))
