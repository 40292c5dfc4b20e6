"""move_base-style planning in plain numpy/scipy: slope costmap, Dijkstra global planner, DWA.

The Drake block that runs them at the control rate is `ditch_drake.systems.dwa_controller.DwaController`.
"""

from ditch_drake.planning.costmap import CostmapConfig, SlopeCostmap, slope_cost
from ditch_drake.planning.dwa import DwaPlannerConfig, DwaResult, find_best_trajectory
from ditch_drake.planning.global_planner import GlobalPlannerConfig, Plan, plan

__all__ = [
    "CostmapConfig",
    "DwaPlannerConfig",
    "DwaResult",
    "GlobalPlannerConfig",
    "Plan",
    "SlopeCostmap",
    "find_best_trajectory",
    "plan",
    "slope_cost",
]
