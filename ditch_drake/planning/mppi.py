"""Rollover-aware MPPI (model predictive path integral control) on an elevation map, in numpy.

Model. Skid-steer unicycle kinematics at a fixed speed: x' = v cos(yaw), y' = v sin(yaw),
yaw' = w, integrated at `step_s` (the control period) over `horizon_s`. The speed is fixed at
the SPEC's label speed (`ditch_drake.spec.actions.SPEED_MPS`, 1 m/s) and only w is sampled,
continuous in [-max_w, max_w]: every one of the 17 labels drives at that speed, so a plan with
another speed could not be executed. The first command is quantized to the label table at the
output (`ditch_drake.spec.actions.quantize`), so the planner executes the same command set as
the learned policy and the demonstrators, and the comparison is fair; the continuous sequence
is kept as the next update's warm start.

Sampling. `samples` sequences of w: the 17 labels each held over the whole horizon (arcs that
random noise around a nominal seldom finds, such as turning to a shallow angle along a ditch's
edge), the nominal itself, and the rest the nominal plus white Gaussian noise of
`noise_sigma_w`, clipped to the limits. The nominal is the previous optimum shifted by one step
(the last step repeated). Randomness comes only from the `numpy.random.Generator` passed in.

Costs of a sampled trajectory (predicted attitudes from `ditch_drake.planning.attitude` at
every step, angles in rad):
- goal: `goal_weight` times the mean planar distance to the goal over the steps, plus
  `terminal_weight` times the last one;
- tip margin: infinite (inadmissible) if any step's sideways margin falls below
  `margin_threshold_deg`, its fore-aft margin below `fore_aft_margin_threshold_deg`, or the
  chassis underside would touch the map (`clearance_m`); otherwise `margin_weight` times the
  sum over steps of (max(0, comfort margin - margin))^2 step_s;
- cross-slope and pitch: `roll_weight` sum roll^2 step_s and `pitch_weight` sum pitch^2 step_s;
- smoothness: `smoothness_weight` times the sum of squared changes of w, the first one from
  the last executed w;
- unknown: `unknown_cost` per second with a wheel on an unknown cell (finite, so a goal in
  unseen ground is still approached; attitude there is not judged).
Thresholds. On a plane of the ditches' 55 deg, the static model (`ditch_drake.planning.attitude`)
gives sideways/fore-aft margins of 6.6/59.6 deg driving along the edge, 7.8/36.9 at 10 deg to
it, 9.3/28.5 at 15, 11.3/22.2 at 20, 13.7/17.6 at 25, 16.4/14.3 at 30, 26.2/8.5 at 45 and 61.6/4.6
head-on. The simulator rolled the robot over head-on and at 30-45 deg and got it across at
15-25 deg (SPEC, measured facts), so the smaller of the two (largest near 30 deg) cannot be the
rule alone: the fore-aft direction needs a larger allowance, as the speed acts along the
heading (the chassis pitches over the rounded hinge and into the toe under its momentum). The
defaults, 8 deg sideways and 16 deg fore-aft, admit about 12-26 deg to the edge on a 55 deg
wall: the band that crossed in the simulator.

Weights exp(-(cost - least cost) / temperature) average the admissible sequences into the new
optimum. Averaging may blend two admissible ways around something into an inadmissible one, so
the average is itself evaluated and the best sample replaces it when it costs more. With no
admissible sample the planner says so and the caller stops.
"""

import math
from dataclasses import dataclass, fields

import numpy as np

from ditch_drake.common.errors import ConfigError
from ditch_drake.planning.attitude import predict_attitude
from ditch_drake.planning.elevation_map import ElevationGrid
from ditch_drake.spec import actions, robot


@dataclass
class MppiPlannerConfig:
    """MPPI's parameters (SI units; margins in degrees). See the module doc for the costs."""

    samples: int = 256
    horizon_s: float = 3.5
    step_s: float = robot.CONTROL_PERIOD_S
    speed_mps: float = actions.SPEED_MPS
    max_w: float = robot.MAX_ANGULAR_RATE_RADPS
    noise_sigma_w: float = 0.35
    temperature: float = 0.5
    goal_weight: float = 1.0
    terminal_weight: float = 2.0
    margin_threshold_deg: float = 8.0
    fore_aft_margin_threshold_deg: float = 16.0
    comfort_margin_deg: float = 20.0
    margin_weight: float = 5.0
    roll_weight: float = 0.1
    pitch_weight: float = 1.5
    smoothness_weight: float = 0.2
    unknown_cost: float = 3.0
    clearance_m: float = robot.GROUND_CLEARANCE_M + 0.1
    seed: int = 0

    def validate(self) -> None:
        """Raises ConfigError naming the first key out of range."""
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name not in ("seed", "samples") and not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ConfigError(f"mppi {f.name}={value!r}: expected a finite number")
        if not (isinstance(self.samples, int) and actions.NUM_LABELS + 2 <= self.samples <= 100_000):
            raise ConfigError(f"mppi samples={self.samples!r}: expected an integer in [{actions.NUM_LABELS + 2}, "
                              "100000]")
        if not (isinstance(self.seed, int) and self.seed >= 0):
            raise ConfigError(f"mppi seed={self.seed!r}: expected an integer >= 0")
        for name in ("horizon_s", "step_s", "speed_mps", "max_w", "temperature", "clearance_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"mppi {name}={getattr(self, name)!r}: expected > 0")
        if self.horizon_s < self.step_s:
            raise ConfigError(f"mppi horizon_s={self.horizon_s!r}: expected at least one step_s ({self.step_s})")
        for name in ("noise_sigma_w", "goal_weight", "terminal_weight", "margin_weight", "roll_weight",
                     "pitch_weight", "smoothness_weight", "unknown_cost"):
            if getattr(self, name) < 0:
                raise ConfigError(f"mppi {name}={getattr(self, name)!r}: expected >= 0")
        if not 0.0 <= self.margin_threshold_deg <= self.comfort_margin_deg < 90.0:
            raise ConfigError(f"mppi margin_threshold_deg={self.margin_threshold_deg!r}, comfort_margin_deg="
                              f"{self.comfort_margin_deg!r}: expected 0 <= threshold <= comfort < 90")
        if not 0.0 <= self.fore_aft_margin_threshold_deg < 90.0:
            raise ConfigError(f"mppi fore_aft_margin_threshold_deg={self.fore_aft_margin_threshold_deg!r}: "
                              "expected 0 <= threshold < 90")

    @property
    def steps(self) -> int:
        return int(round(self.horizon_s / self.step_s))


@dataclass
class MppiResult:
    """One planning update. K samples, H steps; poses are (x, y, yaw) from the start pose on.

    Attributes:
        admissible: some sample kept every margin; False: stop.
        command: [v, w] of the quantized first step ([0, 0] when not admissible).
        label: its action label (-1 when not admissible).
        optimal: (H,) the chosen continuous w sequence.
        next_nominal: (H,) the warm start for the next update: `optimal` shifted by one step.
        sample_poses: (K, H + 1, 3) every sampled trajectory; sample_costs: (K,) their costs.
        poses: (H + 1, 3) the chosen trajectory; margins, roll, pitch: (H,) its predicted
            attitude at steps 1..H (rad); unknown: (H,) where it stands on unknown cells.
    """

    admissible: bool
    command: np.ndarray
    label: int
    optimal: np.ndarray
    next_nominal: np.ndarray
    sample_poses: np.ndarray
    sample_costs: np.ndarray
    poses: np.ndarray
    margins: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    unknown: np.ndarray


def rollout(pose: np.ndarray, w: np.ndarray, speed: float, step_s: float) -> np.ndarray:
    """Poses (K, H + 1, 3) of w sequences (K, H) from `pose` (x, y, yaw), midpoint heading per step."""
    w = np.atleast_2d(w)
    yaw = pose[2] + np.concatenate([np.zeros((len(w), 1)), np.cumsum(w * step_s, axis=1)], axis=1)
    mid = 0.5 * (yaw[:, 1:] + yaw[:, :-1])
    zero = np.zeros((len(w), 1))
    x = pose[0] + np.concatenate([zero, np.cumsum(speed * step_s * np.cos(mid), axis=1)], axis=1)
    y = pose[1] + np.concatenate([zero, np.cumsum(speed * step_s * np.sin(mid), axis=1)], axis=1)
    return np.stack([x, y, yaw], axis=-1)


class MppiPlanner:
    """The planner of a config (module doc); it holds no state between updates."""

    def __init__(self, config: MppiPlannerConfig | None = None):
        self.config = config or MppiPlannerConfig()
        self.config.validate()
        self.steps = self.config.steps
        self._labels = np.repeat(actions.ANGULAR_RATES_RADPS[:, None], self.steps, axis=1)

    def initial_nominal(self) -> np.ndarray:
        """The warm start before the first update: straight ahead."""
        return np.zeros(self.steps)

    def costs(self, grid: ElevationGrid, heights: np.ndarray, origin: np.ndarray, poses: np.ndarray,
              w: np.ndarray, last_w: float, goal_xy: np.ndarray):
        """Costs (K,) of trajectories poses (K, H + 1, 3) of w (K, H), and their attitudes (K, H)."""
        c, dt = self.config, self.config.step_s
        attitude = predict_attitude(grid, heights, origin, poses[:, 1:], clearance_m=c.clearance_m)
        distance = np.hypot(poses[:, 1:, 0] - goal_xy[0], poses[:, 1:, 1] - goal_xy[1])
        cost = c.goal_weight * distance.mean(axis=1) + c.terminal_weight * distance[:, -1]
        known = ~np.isnan(attitude.margin)
        margin = np.where(known, attitude.margin, np.inf)
        shortfall = np.maximum(math.radians(c.comfort_margin_deg) - margin, 0.0)
        roll, pitch = np.where(known, attitude.roll, 0.0), np.where(known, attitude.pitch, 0.0)
        cost += dt * (c.margin_weight * (shortfall**2).sum(axis=1) + c.roll_weight * (roll**2).sum(axis=1)
                      + c.pitch_weight * (pitch**2).sum(axis=1) + c.unknown_cost * attitude.unknown.sum(axis=1))
        dw = np.diff(w, axis=1, prepend=last_w)
        cost += c.smoothness_weight * (dw**2).sum(axis=1)
        side = np.where(known, attitude.side_margin, np.inf)
        axle = np.where(known, attitude.axle_margin, np.inf)
        tips = ((side < math.radians(c.margin_threshold_deg)) | (axle < math.radians(c.fore_aft_margin_threshold_deg))
                | attitude.obstructed)
        return np.where(tips.any(axis=1), np.inf, cost), attitude

    def plan(self, grid: ElevationGrid, heights: np.ndarray, origin: np.ndarray, pose: np.ndarray,
             goal_xy: np.ndarray, nominal: np.ndarray, last_w: float, rng: np.random.Generator) -> MppiResult:
        """One MPPI update from `pose` (x, y, yaw) toward `goal_xy` on the map `heights` at `origin`.

        Args:
            nominal: (H,) the warm start (the previous `next_nominal`; `initial_nominal()` first).
            last_w: the w executed last (rad/s), for the smoothness cost.
            rng: the update's random generator (the caller seeds it).
        """
        c = self.config
        pose, goal_xy = np.asarray(pose, dtype=float), np.asarray(goal_xy, dtype=float)[:2]
        nominal = np.clip(np.nan_to_num(np.asarray(nominal, dtype=float)), -c.max_w, c.max_w)
        noisy = c.samples - len(self._labels) - 1
        eps = rng.normal(0.0, c.noise_sigma_w, size=(noisy, self.steps))
        w = np.concatenate([self._labels, nominal[None], np.clip(nominal + eps, -c.max_w, c.max_w)])
        poses = rollout(pose, w, c.speed_mps, c.step_s)
        costs, _ = self.costs(grid, heights, origin, poses, w, last_w, goal_xy)
        finite = np.isfinite(costs)
        if not finite.any():
            return self._result(False, nominal, poses, costs, grid, heights, origin, pose, last_w, goal_xy)
        weights = np.where(finite, np.exp(-(np.where(finite, costs, 0.0) - costs[finite].min()) / c.temperature), 0.0)
        optimal = weights @ w / weights.sum()
        mean_cost, _ = self.costs(grid, heights, origin, rollout(pose, optimal, c.speed_mps, c.step_s),
                                  optimal[None], last_w, goal_xy)
        best = int(np.argmin(costs))
        if not mean_cost[0] <= costs[best]:
            optimal = w[best]
        return self._result(True, optimal, poses, costs, grid, heights, origin, pose, last_w, goal_xy)

    def _result(self, admissible, optimal, poses, costs, grid, heights, origin, pose, last_w, goal_xy) -> MppiResult:
        c = self.config
        chosen = rollout(pose, optimal, c.speed_mps, c.step_s)
        _, attitude = self.costs(grid, heights, origin, chosen, optimal[None], last_w, goal_xy)
        label = actions.quantize([c.speed_mps, optimal[0]]) if admissible else -1
        command = actions.label_to_command(label) if admissible else np.zeros(2)
        return MppiResult(admissible, command, label, optimal.copy(), np.append(optimal[1:], optimal[-1]),
                          poses, costs, chosen[0], attitude.margin[0], attitude.roll[0], attitude.pitch[0],
                          attitude.unknown[0])
