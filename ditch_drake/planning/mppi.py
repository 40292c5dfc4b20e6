"""Rollover-aware MPPI (model predictive path integral control) on an elevation map, in numpy.

Model. Skid-steer unicycle kinematics at a fixed speed: x' = v cos(yaw), y' = v sin(yaw),
yaw' = w, integrated at `step_s` (the control period) over `horizon_s`. The speed is fixed at
the label speed (`ditch_drake.spec.actions.SPEED_MPS`, 1 m/s; docs/design.md, "The action table"); only w is sampled,
continuous in [-max_w, max_w]: every one of the 17 labels drives at that speed, so a plan with
another speed could not be executed. The first command is quantized to the label table at the
output (`ditch_drake.spec.actions.quantize`), so the planner executes the same command set as
the learned policy and the demonstrators, and the comparison is fair; the continuous sequence
is kept as the next update's warm start.

Sampling. `samples` sequences of w (the structured ones below as far as they fit): the 17 labels each held over the whole horizon (arcs that
random noise around a nominal seldom finds); with `hold_samples`, turn-then-hold sequences
(`HOLD_TURNS`: turn at a label rate until the heading has changed by 10, 20, ... 90 deg, then
straight: the "line up a shallow angle to the edge and hold it" manoeuvre, which white noise
never produces); with `contour_samples`, closed-loop edge-following sequences (at every step of
the rollout, steer to hold 12, 20 or 28 deg to the local contour of the map `_CONTOUR_LOOK_M`
ahead, down or up the slope, either way along it; toward the goal where the map ahead is flat:
on the sine ditch a fixed heading does not hold a fixed angle to the curving edge); the
nominal itself; and the rest the nominal plus white Gaussian noise of `noise_sigma_w`, clipped
to the limits. The nominal is the previous optimum shifted by one step (the last step
repeated). Randomness comes only from the `numpy.random.Generator` passed in.

The map the samples are judged on. Unknown cells within `presumed_drop_m` of known ones and
within `presumed_drop_radius_m` of the robot are presumed to fall away at
`presumed_drop_slope_deg` from their nearest known cell (`elevation_map.presume_drops`): the
wall below a ditch's hinge is in the lidar's shadow until the robot is at the edge, and read as
"unknown" it was driven into head-on; read as the steepest wall the robot may meet, the planner
lines up a shallow angle before the hinge.

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
  unseen ground is still approached; attitude there is not judged);
- commitment: `commitment_weight` times sum (w - nominal)^2 step_s, plus `side_switch_cost` for
  a sample turning the other way than the nominal (net turn beyond `_SIDE_MIN_TURN_RAD`): a
  left and a right way past a drop cost nearly the same, and choosing anew at every update
  between them is no choice;
- drop ahead: `drop_ahead_cost` per second headed into a drop (the map 1-1.5 m ahead along the
  heading falls steeper than `drop_ahead_slope_deg`; probed every `_DROP_PROBE_EVERY` steps):
  driving at an edge to turn away at the last moment costs more than lining up early;
- turning lean (`turn_lean`): the sideways threshold is raised by atan(v |w| / g), the lean of a
  turn at rate w.
Thresholds. On a plane of the ditches' 55 deg, the static model (`ditch_drake.planning.attitude`)
gives sideways/fore-aft margins of 6.6/59.6 deg driving along the edge, 7.8/36.9 at 10 deg to
it, 9.3/28.5 at 15, 11.3/22.2 at 20, 13.7/17.6 at 25, 16.4/14.3 at 30, 26.2/8.5 at 45 and 61.6/4.6
head-on. The simulator rolled the robot over head-on and at 30-45 deg and got it across at
15-25 deg (docs/design.md, "Measured facts"), so the smaller of the two (largest near 30 deg) cannot
be the rule alone: the fore-aft direction needs a larger allowance, as the speed acts along the
heading (the chassis pitches over the rounded hinge and into the toe under its momentum). The
defaults, 8 deg sideways and 16 deg fore-aft, admit about 12-26 deg to the edge on a 55 deg
wall: the band that crossed in the simulator. Climbing, the momentum pushes the chassis into the
wall rather than over an axle: `climb_fore_aft_margin_threshold_deg`, where set, is the fore-aft
threshold of the poses that pitch nose up (11 deg admits up to about 35 deg to the edge on a
55 deg wall, the scripted expert's climb; unset, every pose has `fore_aft_margin_threshold_deg`).

Weights exp(-(cost - least cost) / temperature) average the admissible sequences that turn the
same way as the best one (all of them when it turns less than `_SIDE_MIN_TURN_RAD`) into the new
optimum. Averaging may still blend admissible sequences into an inadmissible one, so the average
is itself evaluated and the best sample replaces it when it costs more. With no admissible
sample, with `fallback` (default) the least-bad one is driven: the smallest worst shortfall
below the tip-margin thresholds over the horizon (obstruction counted as
`_OBSTRUCTION_PENALTY_RAD` per fraction of the steps): stopping on a wall leaves the robot where
it slides or stays, which fails too. Without `fallback` the planner says so and the caller
stops. Where the robot's own pose already touches the map with its underside, obstruction in
the first `obstruction_grace_s` is not held against the samples.
"""

import math
from dataclasses import dataclass, field, fields

import numpy as np

from ditch_drake.common.config_yaml import WRITTEN_WHEN_SET
from ditch_drake.common.errors import ConfigError
from ditch_drake.planning.attitude import predict_attitude
from ditch_drake.planning.elevation_map import ElevationGrid, presume_drops
from ditch_drake.spec import actions, robot

# Turn-then-hold samples (`hold_samples`): (rate rad/s, angle deg) pairs: turn at the rate, either
# sign, until the heading has changed by the angle (to the nearest step), then w = 0 (held):
# every 5 deg to 90 at the largest label rate, and a wider arc to 10-40 deg.
HOLD_TURNS = tuple((0.85, float(a)) for a in range(5, 95, 5)) + tuple((0.45, float(a)) for a in (10, 20, 30, 40))
# Edge-following samples (`contour_samples`): closed-loop rollouts that steer, at every step, to
# hold each of these angles (deg) to the local contour of the map a short way ahead, down or up
# the slope, either way along it; where the map ahead is flat (or unknown), toward the goal.
CONTOUR_ANGLES_DEG = (12.0, 20.0, 28.0)
_CONTOUR_SAMPLES = len(CONTOUR_ANGLES_DEG) * 4
_CONTOUR_LOOK_M = 1.2  # The slope is read this far ahead of the robot...
_CONTOUR_SPAN_M = 0.3  # ...by central differences over +- this.
_CONTOUR_MIN_SLOPE = math.tan(math.radians(15.0))  # Below: flat, steer to the goal.
_CONTOUR_GAIN = 2.0  # w = gain x heading error (rad/s per rad), clipped to max_w.
# Fallback score: the worst tip-margin shortfall (rad) plus this per fraction of the horizon
# with the underside on the map.
_OBSTRUCTION_PENALTY_RAD = 0.2
_GRAVITY = 9.81
# Distances (m) ahead of a sample's pose where a drop is probed, every this many steps.
_DROP_PROBE_M = (1.0, 1.5)
_DROP_PROBE_EVERY = 5
# The samples averaged are those turning the same way as the best one when it turns more than this.
_SIDE_MIN_TURN_RAD = 0.1
# The most sample steps (samples x horizon steps) one plan may simulate and cost. Every plan holds
# a few float arrays of this many poses, at each control update: the default 256 x 35 is 8,960;
# 2 million keeps a plan's arrays within a few hundred MB and its time within seconds, where
# an unbounded horizon (a long horizon_s, a tiny step_s) ran out of memory mid-rollout.
MAX_SAMPLE_STEPS = 2_000_000


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
    climb_fore_aft_margin_threshold_deg: float | None = field(default=None, metadata=WRITTEN_WHEN_SET)
    comfort_margin_deg: float = 20.0
    margin_weight: float = 5.0
    roll_weight: float = 0.1
    pitch_weight: float = 1.5
    smoothness_weight: float = 0.2
    commitment_weight: float = 0.1
    side_switch_cost: float = 2.0
    unknown_cost: float = 3.0
    clearance_m: float = robot.GROUND_CLEARANCE_M + 0.1
    presumed_drop_slope_deg: float = 55.0
    presumed_drop_m: float = 1.5
    presumed_drop_radius_m: float = 4.0
    drop_ahead_cost: float = 0.0
    drop_ahead_slope_deg: float = 35.0
    hold_samples: bool = True
    contour_samples: bool = False
    fallback: bool = True
    turn_lean: bool = False
    obstruction_grace_s: float = 1.0
    seed: int = 0

    def validate(self) -> None:
        """Raises ConfigError naming the first key out of range."""
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None and f.default is None:  # An optional key left unset.
                continue
            if f.name not in ("seed", "samples", "hold_samples", "contour_samples", "fallback", "turn_lean") and not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ConfigError(f"mppi {f.name}={value!r}: expected a finite number")
        for name in ("hold_samples", "contour_samples", "fallback", "turn_lean"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"mppi {name}={getattr(self, name)!r}: expected true or false")
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
        if self.samples * self.steps > MAX_SAMPLE_STEPS:
            raise ConfigError(f"mppi samples={self.samples!r} over horizon_s={self.horizon_s!r} in step_s="
                              f"{self.step_s!r} is {self.samples * self.steps:,} sample steps a plan; expected at "
                              f"most {MAX_SAMPLE_STEPS:,} (fewer samples, a shorter horizon_s or a longer step_s)")
        if not 0.0 < self.presumed_drop_slope_deg < 90.0:
            raise ConfigError(f"mppi presumed_drop_slope_deg={self.presumed_drop_slope_deg!r}: expected in (0, 90)")
        if not 0.0 < self.drop_ahead_slope_deg < 90.0:
            raise ConfigError(f"mppi drop_ahead_slope_deg={self.drop_ahead_slope_deg!r}: expected in (0, 90)")
        for name in ("presumed_drop_m", "presumed_drop_radius_m", "drop_ahead_cost", "obstruction_grace_s", "noise_sigma_w", "goal_weight", "terminal_weight",
                     "margin_weight", "roll_weight",
                     "pitch_weight", "smoothness_weight", "commitment_weight", "side_switch_cost", "unknown_cost"):
            if getattr(self, name) < 0:
                raise ConfigError(f"mppi {name}={getattr(self, name)!r}: expected >= 0")
        if not 0.0 <= self.margin_threshold_deg <= self.comfort_margin_deg < 90.0:
            raise ConfigError(f"mppi margin_threshold_deg={self.margin_threshold_deg!r}, comfort_margin_deg="
                              f"{self.comfort_margin_deg!r}: expected 0 <= threshold <= comfort < 90")
        for name in ("fore_aft_margin_threshold_deg", "climb_fore_aft_margin_threshold_deg"):
            value = getattr(self, name)
            if value is not None and not 0.0 <= value < 90.0:
                raise ConfigError(f"mppi {name}={value!r}: expected 0 <= threshold < 90")

    @property
    def steps(self) -> int:
        return round(self.horizon_s / self.step_s)


@dataclass
class MppiResult:
    """One planning update. K samples, H steps; poses are (x, y, yaw) from the start pose on.

    Attributes:
        admissible: some sample kept every margin.
        command: [v, w] of the quantized first step ([0, 0] when neither admissible nor fallback).
        label: its action label (-1 when stopped).
        optimal: (H,) the chosen continuous w sequence.
        next_nominal: (H,) the warm start for the next update: `optimal` shifted by one step.
        sample_poses: (K, H + 1, 3) every sampled trajectory; sample_costs: (K,) their costs.
        poses: (H + 1, 3) the chosen trajectory; margins, roll, pitch: (H,) its predicted
            attitude at steps 1..H (rad); unknown: (H,) where it stands on unknown cells.
        fallback: no sample was admissible and the least-bad one is driven (`fallback` config).
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
    fallback: bool = False


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
        fixed = [np.repeat(actions.ANGULAR_RATES_RADPS[:, None], self.steps, axis=1)]
        if self.config.hold_samples:
            for rate, angle in HOLD_TURNS:
                rate = min(rate, self.config.max_w)
                count = max(1, round(math.radians(angle) / (rate * self.config.step_s)))
                turn = np.zeros(self.steps)
                turn[:min(count, self.steps)] = rate
                fixed += [turn[None], -turn[None]]
        # With fewer samples than the structured ones need, as many as fit (labels first), one
        # noisy sample kept.
        room = self.config.samples - actions.NUM_LABELS - 2
        self._contour_count = min(_CONTOUR_SAMPLES, room) if self.config.contour_samples else 0
        self._fixed = np.concatenate(fixed)[:actions.NUM_LABELS + room - self._contour_count]

    def initial_nominal(self) -> np.ndarray:
        """The warm start before the first update: straight ahead."""
        return np.zeros(self.steps)

    def contour_sequences(self, grid: ElevationGrid, heights: np.ndarray, origin: np.ndarray, pose: np.ndarray,
                          goal_xy: np.ndarray) -> np.ndarray:
        """The edge-following w sequences (`_CONTOUR_SAMPLES`, H) from `pose` on `heights` (module doc)."""
        c = self.config
        angle, sense, down = (a.ravel() for a in np.meshgrid(np.radians(CONTOUR_ANGLES_DEG), [1.0, -1.0], [1.0, -1.0]))
        x, y, yaw = (np.full(len(angle), float(v)) for v in pose)
        w = np.zeros((len(angle), self.steps))
        span = np.array([[_CONTOUR_SPAN_M, 0.0], [-_CONTOUR_SPAN_M, 0.0], [0.0, _CONTOUR_SPAN_M], [0.0, -_CONTOUR_SPAN_M]])
        for step in range(self.steps):
            ahead = np.stack([x + _CONTOUR_LOOK_M * np.cos(yaw), y + _CONTOUR_LOOK_M * np.sin(yaw)], axis=-1)
            h = grid.sample(heights, origin, ahead[:, None, :] + span)
            gx = np.nan_to_num((h[:, 0] - h[:, 1]) / (2 * _CONTOUR_SPAN_M))
            gy = np.nan_to_num((h[:, 2] - h[:, 3]) / (2 * _CONTOUR_SPAN_M))
            contour = np.arctan2(-gy, -gx) + sense * math.pi / 2  # Downhill, turned a quarter either way.
            desired = np.where(np.hypot(gx, gy) >= _CONTOUR_MIN_SLOPE, contour - sense * down * angle,
                               np.arctan2(goal_xy[1] - y, goal_xy[0] - x))
            error = np.angle(np.exp(1j * (desired - yaw)))
            w[:, step] = np.clip(_CONTOUR_GAIN * error, -c.max_w, c.max_w)
            mid = yaw + 0.5 * w[:, step] * c.step_s
            x, y = x + c.speed_mps * c.step_s * np.cos(mid), y + c.speed_mps * c.step_s * np.sin(mid)
            yaw = yaw + w[:, step] * c.step_s
        return w

    def planning_heights(self, grid: ElevationGrid, heights: np.ndarray, origin: np.ndarray | None = None,
                         pose: np.ndarray | None = None) -> np.ndarray:
        """The map the samples are judged on: `heights` with presumed drops (module doc), within
        `presumed_drop_radius_m` of the pose (everywhere without a pose)."""
        c = self.config
        within = None
        if pose is not None:
            xs, ys = grid.cell_centers(origin)
            within = np.hypot(xs[None, :] - pose[0], ys[:, None] - pose[1]) <= c.presumed_drop_radius_m
        return presume_drops(heights, grid.resolution, c.presumed_drop_slope_deg, c.presumed_drop_m, within)

    def costs(self, grid: ElevationGrid, heights: np.ndarray, origin: np.ndarray, poses: np.ndarray,
              w: np.ndarray, last_w: float, goal_xy: np.ndarray, grace_steps: int = 0,
              nominal: np.ndarray | None = None):
        """Costs (K,) of trajectories poses (K, H + 1, 3) of w (K, H), and their attitudes (K, H)."""
        cost, attitude, _ = self._costs(grid, heights, origin, poses, w, last_w, goal_xy, grace_steps, nominal)
        return cost, attitude

    def _costs(self, grid, heights, origin, poses, w, last_w, goal_xy, grace_steps, nominal=None):
        """`costs`, and each sample's fallback score: its worst tip-margin shortfall (rad) over the
        steps, plus `_OBSTRUCTION_PENALTY_RAD` per fraction of the steps obstructed, plus 1e-3 of
        its finite cost (ties)."""
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
        if nominal is not None:
            cost += c.commitment_weight * dt * ((w - nominal) ** 2).sum(axis=1)
            planned = nominal.sum() * dt
            if abs(planned) > _SIDE_MIN_TURN_RAD:
                cost += c.side_switch_cost * (w.sum(axis=1) * dt * planned < -_SIDE_MIN_TURN_RAD * abs(planned))
        if c.drop_ahead_cost > 0:
            # Headed into a drop: every `_DROP_PROBE_EVERY` steps (and at the end) the map 1-2 m
            # ahead along the heading is probed; a fall steeper than `drop_ahead_slope_deg` costs
            # `drop_ahead_cost` per second. Driving at an edge to turn away at the last moment
            # then costs more than turning to a shallow angle early.
            at = poses[:, _DROP_PROBE_EVERY::_DROP_PROBE_EVERY]
            ahead = np.asarray(_DROP_PROBE_M)
            heading = np.stack([np.cos(at[..., 2]), np.sin(at[..., 2])], axis=-1)
            probe = at[..., None, :2] + ahead[:, None] * heading[..., None, :]
            h = grid.sample(heights, origin, np.concatenate([at[..., None, :2], probe], axis=-2))
            with np.errstate(invalid="ignore"):
                steep = ((h[..., :1] - h[..., 1:]) / ahead > math.tan(math.radians(c.drop_ahead_slope_deg))).any(-1)
            cost += c.drop_ahead_cost * _DROP_PROBE_EVERY * dt * steep.sum(axis=1)
        # Turning at w and speed v leans the chassis outward like a slope of atan(v w / g): the
        # sideways margin a turn keeps is the static one less that angle.
        turn_lean = np.arctan(c.speed_mps * np.abs(w) / _GRAVITY) if c.turn_lean else 0.0
        side_short = (math.radians(c.margin_threshold_deg) + turn_lean
                      - np.where(known, attitude.side_margin, np.inf))
        axle_threshold = math.radians(c.fore_aft_margin_threshold_deg)
        if c.climb_fore_aft_margin_threshold_deg is not None:
            # Nose up (negative Drake pitch) the speed pushes the chassis into the wall, not over the axle.
            axle_threshold = np.where(attitude.pitch < 0, math.radians(c.climb_fore_aft_margin_threshold_deg),
                                      axle_threshold)
        axle_short = axle_threshold - np.where(known, attitude.axle_margin, np.inf)
        obstructed = attitude.obstructed
        if grace_steps > 0:
            obstructed = obstructed.copy()
            obstructed[:, :grace_steps] = False
        worst = np.maximum(np.maximum(side_short, axle_short).max(axis=1), 0.0)
        score = worst + _OBSTRUCTION_PENALTY_RAD * obstructed.mean(axis=1) + 1e-3 * cost
        tips = (worst > 0.0) | obstructed.any(axis=1)
        return np.where(tips, np.inf, cost), attitude, score

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
        heights = self.planning_heights(grid, heights, origin, pose)
        nominal = np.clip(np.nan_to_num(np.asarray(nominal, dtype=float)), -c.max_w, c.max_w)
        # Where the robot's own pose already has its underside on the map (a map artefact, or the
        # chassis already touching), the first steps cannot avoid it: they are not held against it.
        now = predict_attitude(grid, heights, origin, pose[None], clearance_m=c.clearance_m)
        grace = round(c.obstruction_grace_s / c.step_s) if now.obstructed[0] else 0
        contour = (self.contour_sequences(grid, heights, origin, pose, goal_xy)[:self._contour_count]
                   if self._contour_count else np.zeros((0, self.steps)))
        noisy = c.samples - len(self._fixed) - len(contour) - 1
        eps = rng.normal(0.0, c.noise_sigma_w, size=(noisy, self.steps))
        w = np.concatenate([self._fixed, contour, nominal[None], np.clip(nominal + eps, -c.max_w, c.max_w)])
        poses = rollout(pose, w, c.speed_mps, c.step_s)
        costs, _, score = self._costs(grid, heights, origin, poses, w, last_w, goal_xy, grace, nominal)
        finite = np.isfinite(costs)
        if not finite.any():
            return self._result(False, w[int(np.argmin(score))] if c.fallback else nominal, poses, costs, grid,
                                heights, origin, pose, last_w, goal_xy, fallback=c.fallback)
        weights = np.where(finite, np.exp(-(np.where(finite, costs, 0.0) - costs[finite].min()) / c.temperature), 0.0)
        # Average within the best sample's way round only: a left and a right turn past a drop
        # average to straight into it, and an alternating choice between them is no choice.
        best = int(np.argmin(costs))
        turn = w.sum(axis=1) * c.step_s
        if abs(turn[best]) > _SIDE_MIN_TURN_RAD:
            weights = np.where(turn * turn[best] > 0.0, weights, 0.0)
        optimal = weights @ w / weights.sum()
        mean_cost, _, _ = self._costs(grid, heights, origin, rollout(pose, optimal, c.speed_mps, c.step_s),
                                      optimal[None], last_w, goal_xy, grace, nominal)
        if not mean_cost[0] <= costs[best]:
            optimal = w[best]
        return self._result(True, optimal, poses, costs, grid, heights, origin, pose, last_w, goal_xy)

    def _result(self, admissible, optimal, poses, costs, grid, heights, origin, pose, last_w, goal_xy,
                fallback=False) -> MppiResult:
        c = self.config
        chosen = rollout(pose, optimal, c.speed_mps, c.step_s)
        _, attitude = self.costs(grid, heights, origin, chosen, optimal[None], last_w, goal_xy)
        drive = admissible or fallback
        label = actions.quantize([c.speed_mps, optimal[0]]) if drive else -1
        command = actions.label_to_command(label) if drive else np.zeros(2)
        return MppiResult(admissible, command, label, optimal.copy(), np.append(optimal[1:], optimal[-1]),
                          poses, costs, chosen[0], attitude.margin[0], attitude.roll[0], attitude.pitch[0],
                          attitude.unknown[0], fallback=bool(fallback and not admissible))
