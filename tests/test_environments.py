"""Environments data: loading, validation, clear errors for bad files and names."""

import pytest

from ditch_drake.world.environments import (
    ConfigError,
    environment_names,
    get_environment,
    get_task,
    load_environments,
)


def test_four_environments_with_three_tasks_each():
    assert environment_names() == ["crater", "wide", "narrow", "sine"]
    for name in environment_names():
        assert len(get_environment(name).tasks) == 3


def test_unknown_environment_lists_the_known_ones():
    with pytest.raises(ConfigError, match=r"unknown environment 'moat'.*crater"):
        get_environment("moat")


def test_unknown_task():
    with pytest.raises(ConfigError, match="task index 7 is out of range"):
        get_task(get_environment("wide"), 7)
    with pytest.raises(ConfigError, match="unknown task 'x'"):
        get_task(get_environment("wide"), "x")


def test_malformed_yaml_names_the_file(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("environments: {wide: {terrain: {slope_deg: [3}}}\n")
    with pytest.raises(ConfigError, match=r"(?s)malformed YAML in .*broken.yaml.*line 1"):
        load_environments(path)


def test_unknown_field_names_the_file(tmp_path):
    path = tmp_path / "typo.yaml"
    path.write_text("environments: {wide: {terrain: {slope_degg: 50}}}\n")
    with pytest.raises(ConfigError, match=r"typo.yaml.*slope_degg"):
        load_environments(path)


def test_out_of_range_terrain_names_environment_and_value(tmp_path):
    path = tmp_path / "steep.yaml"
    path.write_text(
        "environments:\n  cliff:\n    terrain: {slope_deg: 95}\n"
        "    tasks: [{name: a, start: [0, -10, 90], goal: [0, 10]}]\n")
    with pytest.raises(ConfigError, match=r"'cliff'.*slope_deg=95.*0 < slope_deg < 90"):
        load_environments(path)


def test_task_must_cross_the_ditch(tmp_path):
    path = tmp_path / "same_side.yaml"
    path.write_text(
        "environments:\n  wide:\n    terrain: {bottom_width_m: 6}\n"
        "    tasks: [{name: a, start: [0, -10, 90], goal: [5, -10]}]\n")
    with pytest.raises(ConfigError, match="not on opposite sides"):
        load_environments(path)


def test_missing_file():
    with pytest.raises(ConfigError, match="cannot read environments file"):
        load_environments("/nonexistent/environments.yaml")


def test_new_shape_is_data(tmp_path):
    path = tmp_path / "gentle.yaml"
    path.write_text(
        "environments:\n  gentle:\n    terrain: {course: line, bottom_width_m: 3, slope_deg: 30, depth_m: 2}\n"
        "    tasks: [{name: a, start: [0, -9, 90], goal: [0, 9]}]\n")
    environments = load_environments(path)
    assert environments["gentle"].terrain.slope_deg == 30
