"""The paper's move_base (`dwa_paper`) beside today's `dwa`: the slope cost, the step
criterion for vertical obstacles, and what a global plan does with each on a walled ditch.

The costmaps here are made by `SlopeCostmap.mark` from synthetic point clouds (normals by its
own PCA), so they exercise the real cost functions end to end.
"""

import math

import numpy as np
import pytest
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed

from ditch_drake.common.config_yaml import config_digest, config_from_yaml, config_to_yaml
from ditch_drake.diagrams.controllers import controller_config, entry_for_config, get_controller
from ditch_drake.diagrams.rollout import DwaBaselineConfig, paper_dwa_config
from ditch_drake.planning import global_planner
from ditch_drake.planning.costmap import (
    LETHAL_OBSTACLE,
    MAX_NON_OBSTACLE,
    NO_INFORMATION,
    CostmapConfig,
    SlopeCostmap,
    slope_cost,
    step_heights,
)

DITCH_WALL_DEG = 55.0


def dwa_costmap(**changes) -> CostmapConfig:
    return CostmapConfig(**{**vars(controller_config("dwa").planner.costmap), **changes})


def paper_costmap(**changes) -> CostmapConfig:
    return CostmapConfig(**{**vars(controller_config("dwa_paper").planner.costmap), **changes})


def cost_at(slope_deg, config: CostmapConfig) -> np.ndarray:
    return slope_cost(np.cos(np.radians(slope_deg)), config.free_slope_deg, config.lethal_slope_deg)


# ----- the cost curve --------------------------------------------------------------------
def test_paper_cost_is_zero_when_flat_rises_with_slope_and_is_never_lethal():
    slopes = np.linspace(0.0, 90.0, 901)
    cost = cost_at(slopes, paper_costmap())
    assert np.all(cost[slopes <= 5.0] == 0.0)  # Flat ground (and the normals' noise) is free.
    assert np.all(np.diff(cost) >= 0.0)  # Monotone in the slope...
    rising = slopes > 5.0
    assert np.all(cost[rising] > 0.0) and cost[-1] > cost[np.searchsorted(slopes, 60.0)] > cost[rising][0]
    assert cost.max() == MAX_NON_OBSTACLE == cost[-1]  # ...up to the highest non-lethal cost at 90 deg,
    assert np.all(cost < LETHAL_OBSTACLE - 1)  # and no slope is lethal (nor inscribed).
    wall = float(cost_at(DITCH_WALL_DEG, paper_costmap()))
    assert 50.0 < wall < MAX_NON_OBSTACLE and math.isfinite(wall)  # 55 deg: a finite cost (107).


def test_dwa_cost_is_lethal_from_45_degrees_as_before():
    config = dwa_costmap()
    assert config.lethal_slope_deg == 45.0 and config.max_step_height == 0.0
    assert cost_at(44.0, config) < LETHAL_OBSTACLE and cost_at(45.0, config) == LETHAL_OBSTACLE
    assert cost_at(DITCH_WALL_DEG, config) == LETHAL_OBSTACLE
    # Exactly 90 keeps its meaning (only exactly vertical normals are lethal); inf means none.
    assert slope_cost(0.0, 5.0, 90.0) == LETHAL_OBSTACLE and slope_cost(0.0, 5.0, math.inf) == MAX_NON_OBSTACLE


def test_costmap_config_refuses_a_lethal_slope_below_the_free_one_but_takes_inf():
    with pytest.raises(ValueError, match="lethal_slope_deg"):
        CostmapConfig(free_slope_deg=50.0, lethal_slope_deg=45.0).validate()
    with pytest.raises(ValueError, match="lethal_slope_deg"):
        CostmapConfig(lethal_slope_deg=120.0).validate()
    with pytest.raises(ValueError, match="max_step_height"):
        CostmapConfig(max_step_height=-0.1).validate()
    CostmapConfig(lethal_slope_deg=math.inf).validate()


# ----- registration and configs ----------------------------------------------------------
def test_dwa_paper_is_registered_beside_dwa_with_the_papers_costmap():
    config = controller_config("dwa_paper")
    assert isinstance(config, DwaBaselineConfig) and config == paper_dwa_config()
    assert get_controller("dwa_paper").config_type is get_controller("dwa").config_type
    costmap = config.planner.costmap
    assert costmap.lethal_slope_deg == math.inf and costmap.max_step_height > 0.0
    assert costmap.negative_obstacle_depth == 0.0  # The paper's layer had only the normal-based cost.
    # Unknown (the hidden wall below an edge) stays passable, so it will drive into a ditch.
    assert config.planner.global_planner.allow_unknown and not config.planner.local_planner.unknown_is_lethal
    # An experiment's `!DwaBaselineConfig {...}` maps back to the first entry of its type.
    assert entry_for_config(config).name == "dwa"


def test_the_configs_round_trip_and_dwa_keeps_its_recorded_text():
    paper = paper_dwa_config()
    # The results' YAML (`config_to_yaml`) and Drake's (`scenario --print`) both read back.
    assert config_from_yaml(DwaBaselineConfig, config_to_yaml(paper)) == paper
    assert yaml_load_typed(schema=DwaBaselineConfig, data=yaml_dump_typed(paper)) == paper
    assert "lethal_slope_deg: .inf" in config_to_yaml(paper) and "max_step_height: 0.3" in config_to_yaml(paper)
    # `dwa` leaves the step criterion off, and its recorded text (so its digest, in every
    # recorded rollout's key) does not name it.
    dwa = DwaBaselineConfig()
    assert "max_step_height" not in config_to_yaml(dwa)
    assert config_digest(dwa) != config_digest(paper)


# ----- the step criterion ----------------------------------------------------------------
def ground_grid(x_range, y_range, spacing=0.05, height=lambda x, y: np.zeros_like(x)):
    x, y = np.meshgrid(np.arange(*x_range, spacing), np.arange(*y_range, spacing))
    x, y = x.ravel(), y.ravel()
    return np.c_[x, y, height(x, y)]


def vertical_wall(x_face, y_range, height=1.0, spacing=0.05):
    """The lidar's side of a vertical wall: points on the face x = x_face, from the ground up."""
    y, z = np.meshgrid(np.arange(*y_range, spacing), np.arange(0.0, height + 1e-9, spacing))
    return np.c_[np.full(y.size, x_face), y.ravel(), z.ravel()]


def ditch_height(y, depth=1.0, slope_deg=DITCH_WALL_DEG, half_width=2.5):
    """A ditch across x: flat at 0 for |y| > half_width, walls at slope_deg, a floor at -depth."""
    return -np.clip((half_width - np.abs(y)) * math.tan(math.radians(slope_deg)), 0.0, depth)


def mark(config: CostmapConfig, points: np.ndarray, sensor=(0.0, 0.0, 0.8)):
    costmap = SlopeCostmap(config)
    origin = costmap.window_origin([0.0, 0.0])
    return costmap, origin, costmap.mark(costmap.empty_layer(), origin, points, np.asarray(sensor, dtype=float))


def test_step_heights_leave_out_each_cells_highest_and_lowest_point():
    cell = np.array([0, 0, 0, 0, 1, 1, 1, 2, 2, 2, 2, 2])
    z = np.array([0.0, 0.4, 0.9, 1.0, 0.0, 1.0, 2.0, 5.0, 0.1, 0.2, 0.3, -5.0])
    np.testing.assert_allclose(step_heights(cell, z, 4), [0.5, 0.0, 0.2, 0.0])


def test_a_vertical_1m_wall_is_lethal_and_a_55_degree_slope_is_not_under_dwa_papers_costmap():
    wall_cloud = np.r_[ground_grid((0.5, 3.0), (-1.0, 1.0)), vertical_wall(2.55, (-1.0, 1.0))]
    costmap, origin, layer = mark(paper_costmap(), wall_cloud)
    iy, ix, _ = costmap.world_to_cell(origin, np.c_[np.full(19, 2.55), np.linspace(-0.9, 0.9, 19)])
    assert np.all(layer[iy, ix] == LETHAL_OBSTACLE)
    iy, ix, _ = costmap.world_to_cell(origin, np.array([[1.5, 0.0]]))
    assert layer[iy[0], ix[0]] == 0.0  # The ground before it is free.

    x_slope = 2.0
    slope_cloud = ground_grid((0.5, 4.0), (-1.5, 1.5), height=lambda x, y: np.where(
        x > x_slope, (x - x_slope) * math.tan(math.radians(DITCH_WALL_DEG)), 0.0))
    on_slope = np.c_[np.linspace(2.3, 3.5, 13), np.zeros(13)]  # Within the 4 m range.
    costmap, origin, layer = mark(paper_costmap(), slope_cloud)
    iy, ix, _ = costmap.world_to_cell(origin, on_slope)
    assert not np.any(layer == LETHAL_OBSTACLE)
    assert np.all((layer[iy, ix] > 50.0) & (layer[iy, ix] < MAX_NON_OBSTACLE))  # Costly, not lethal.
    # Under `dwa`'s costmap the same slope is lethal.
    costmap, origin, layer = mark(dwa_costmap(), slope_cloud)
    assert np.all(layer[iy, ix] == LETHAL_OBSTACLE)


def test_one_stray_low_return_on_a_55_degree_slope_is_not_a_wall():
    slope = ground_grid((0.5, 4.0), (-1.5, 1.5), height=lambda x, y: np.where(
        x > 2.0, (x - 2.0) * math.tan(math.radians(DITCH_WALL_DEG)), 0.0))
    stray = np.array([[3.05, 0.05, (3.05 - 2.0) * math.tan(math.radians(DITCH_WALL_DEG)) - 1.0]])
    _, _, layer = mark(paper_costmap(), np.r_[slope, stray])
    assert not np.any(layer == LETHAL_OBSTACLE)


def test_a_wall_seen_in_part_later_stays_lethal_under_dwa_paper_but_dwa_still_overwrites():
    full = np.r_[ground_grid((0.5, 3.0), (-1.0, 1.0)), vertical_wall(2.55, (-1.0, 1.0))]
    costmap, origin, layer = mark(paper_costmap(), full)
    iy, ix, _ = costmap.world_to_cell(origin, np.array([[2.55, 0.05]]))
    assert layer[iy[0], ix[0]] == LETHAL_OBSTACLE
    # A later view of the wall's top alone (0.8-1 m: no step within a cell) does not lower it.
    top = vertical_wall(2.55, (-1.0, 1.0))
    top = top[top[:, 2] >= 0.8]
    again = costmap.mark(layer, origin, top, np.array([0.0, 0.0, 0.8]))
    assert again[iy[0], ix[0]] == LETHAL_OBSTACLE
    assert np.all(again[layer == LETHAL_OBSTACLE] == LETHAL_OBSTACLE)  # Every mark kept.
    # `dwa` (steps off) keeps overwriting: a lethal slope seen flat later is free again.
    dwa = SlopeCostmap(dwa_costmap())
    steep = ground_grid((2.0, 2.5), (-0.5, 0.5), height=lambda x, y: x * math.tan(math.radians(60.0)))
    layer = dwa.mark(dwa.empty_layer(), origin, steep, np.array([0.0, 0.0, 3.0]))
    iy, ix, _ = dwa.world_to_cell(origin, np.array([[2.25, 0.05]]))
    assert layer[iy[0], ix[0]] == LETHAL_OBSTACLE
    flat = ground_grid((2.0, 2.5), (-0.5, 0.5), height=lambda x, y: np.full_like(x, 3.0))
    assert dwa.mark(layer, origin, flat, np.array([0.0, 0.0, 3.5]))[iy[0], ix[0]] == 0.0


# ----- a walled ditch: cross it, or no plan ------------------------------------------------
CORRIDOR_X = 3.0  # Walls at x = +-3 m close the way round the ditch, which spans |x| <= 4.5 m.


def walled_ditch_costmap(config: CostmapConfig, walls: bool = True):
    """The master costmap (12 m window at the origin) of a ditch across x, |y| < 2.5 m, 1 m deep
    with 55 deg walls, ending at |x| = 4.5 m, with (or without) vertical 1 m walls along
    x = +-3 m from edge to edge of the window."""
    config = CostmapConfig(**{**vars(config), "width": 12.0, "height": 12.0, "obstacle_range": 30.0})

    def height(x, y):
        return np.where(np.abs(x) <= 4.5, ditch_height(y), 0.0)

    points = [ground_grid((-6.0, 6.0), (-6.0, 6.0), height=height)]
    if walls:
        for x_face in (-CORRIDOR_X - 0.05, CORRIDOR_X + 0.05):
            points.append(vertical_wall(x_face, (-6.0, 6.0)))
    costmap, origin, layer = mark(config, np.concatenate(points), sensor=(0.0, 0.0, 10.0))
    assert not np.any(layer == NO_INFORMATION)  # Every cell seen: unknown space plays no part.
    return costmap.inflate(layer), costmap.origin_m(origin), costmap.resolution


START, GOAL = np.array([0.0, -4.5]), np.array([0.0, 4.5])


def test_dijkstra_crosses_a_walled_ditch_under_dwa_paper_and_finds_no_plan_under_dwa():
    costs, origin_m, resolution = walled_ditch_costmap(paper_costmap())
    plan = global_planner.plan(costs, origin_m, resolution, START, GOAL)
    assert plan is not None and plan.reaches_goal
    assert np.linalg.norm(plan.path_xy[-1] - GOAL) <= 0.1
    assert np.all(np.abs(plan.path_xy[:, 0]) < CORRIDOR_X)  # Between the walls, so...
    floor = np.abs(plan.path_xy[:, 1]) < 1.7
    assert floor.any() and np.all(ditch_height(plan.path_xy[floor, 1]) <= -0.99)  # ...over the ditch's floor.
    iy, ix = np.floor((plan.path_xy - origin_m) / resolution).astype(int)[:, ::-1].T
    on_path = costs[iy, ix]
    assert 50.0 < on_path.max() < MAX_NON_OBSTACLE  # Down and up the 55 deg walls at a finite cost.

    costs, origin_m, resolution = walled_ditch_costmap(dwa_costmap())
    assert global_planner.plan(costs, origin_m, resolution, START, GOAL) is None


def test_without_the_walls_dwa_plans_around_the_ditchs_end():
    costs, origin_m, resolution = walled_ditch_costmap(dwa_costmap(), walls=False)
    plan = global_planner.plan(costs, origin_m, resolution, START, GOAL)
    assert plan is not None and plan.reaches_goal and np.abs(plan.path_xy[:, 0]).max() > 4.5


# ----- the docs --------------------------------------------------------------------------
def test_the_cost_curve_figure_and_the_baseline_pages_section(tmp_path):
    from ditch_drake.docs_tools.baseline_page import _cost_curves_section
    from ditch_drake.docs_tools.figures import cost_curve_figure, cost_curves

    curves = cost_curves()
    assert set(curves) == {"dwa", "dwa_paper"}
    slope_deg, paper = curves["dwa_paper"]
    assert paper[0] == 0.0 and paper[-1] == MAX_NON_OBSTACLE and slope_deg[-1] == 90.0
    assert curves["dwa"][1][-1] == LETHAL_OBSTACLE
    path = cost_curve_figure(tmp_path)
    assert path.name == "costmap_cost_curves.png" and path.stat().st_size > 10_000
    section = "\n".join(_cost_curves_section("img/costmap_cost_curves.png", DITCH_WALL_DEG))
    assert "| `dwa` | 0 to 5 deg |" in section and "| 45 deg | LETHAL (254) |" in section
    assert "| `dwa_paper` | 0 to 5 deg |" in section and "| none | 107 |" in section
    assert "![Slope cost of dwa and dwa_paper](img/costmap_cost_curves.png)" in section
