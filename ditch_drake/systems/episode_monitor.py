"""Episode monitor: ends a rollout on goal, rollover, timeout or being stuck."""

import enum
import math
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import EventStatus, LeafSystem

from ditch_drake.spec import robot


class EpisodeStatus(enum.IntEnum):
    RUNNING = 0
    REACHED_GOAL = 1
    ROLLED_OVER = 2
    TIMEOUT = 3
    STUCK = 4


@dataclass
class EpisodeConfig:
    """When an episode ends (m, s, degrees).

    Attributes:
        goal_radius_m: success when the chassis origin is this close to the goal, in the plane.
            Larger than the tightest turn at full speed (v / w_max = 1.0 / 0.85 = 1.18 m):
            with 1.0 m, a policy that passed the goal a little off could only circle it
            just outside the radius until the timeout (measured: docs/concepts/learning.md).
        time_limit_s: timeout.
        rollover_tilt_deg: rolled over when the chassis up-axis leans further than
            this from vertical. The static tip-over angles are about 60 deg
            (docs/concepts/physics.md), and a 55 deg wall crossed at a shallow angle tilts
            the chassis by about 55 deg, so 75 deg means the robot is going over.
        stuck_window_s: stuck when the robot has not moved `stuck_distance_m`
            within this long.
        stuck_distance_m: see `stuck_window_s`.
    """

    goal_radius_m: float = 1.5
    time_limit_s: float = 120.0
    rollover_tilt_deg: float = 75.0
    stuck_window_s: float = 10.0
    stuck_distance_m: float = 0.5


@dataclass
class EpisodeOutcome:
    """What happened in one episode (SI units; angles in degrees)."""

    status: str
    time_s: float
    path_length_m: float
    peak_abs_roll_deg: float
    peak_abs_pitch_deg: float
    peak_tilt_deg: float
    min_stability_margin_deg: float
    final_xy: tuple[float, float]

    @property
    def success(self) -> bool:
        return self.status == EpisodeStatus.REACHED_GOAL.name.lower()


# Layout of the monitor's discrete state.
_STATUS, _END_TIME, _PATH, _ROLL, _PITCH, _TILT, _MARGIN, _LAST_X, _LAST_Y, _ANCHOR_X, _ANCHOR_Y, _ANCHOR_T, _STARTED = range(13)
_STATE_SIZE = 13
# Static tip-over angles about the side and the front/rear wheel lines.
_LATERAL_TIP_RAD = robot.tip_angle_sideways_rad()
_LONGITUDINAL_TIP_RAD = robot.tip_angle_fore_aft_rad()


def stability_margins_rad(R_WB: np.ndarray) -> list[float]:
    """Static tip-over margins (rad) about the left, right, front and rear wheel lines.

    A margin is how much further the chassis could lean toward that edge of the
    wheel support rectangle before the centre of mass passes over it; negative
    means it has passed.
    """
    return _margins_of_up(*R_WB[2].tolist())  # The world's +z expressed in B.


def _margins_of_up(up_x: float, up_y: float, up_z: float) -> list[float]:
    """`stability_margins_rad` of the world's +z expressed in B."""
    lean_y = math.atan2(up_y, up_z)
    lean_x = math.atan2(up_x, up_z)
    return [_LATERAL_TIP_RAD + lean_y, _LATERAL_TIP_RAD - lean_y,
            _LONGITUDINAL_TIP_RAD + lean_x, _LONGITUDINAL_TIP_RAD - lean_x]


class EpisodeMonitor(LeafSystem):
    """Watches the chassis at the control rate and ends the episode.

    Its periodic update returns `EventStatus.ReachedTermination` when the episode
    ends, so a `Simulator` stops by itself; `AdvanceTo` returns early and
    `outcome(context)` reads the result.

    .. pydrake_system::

        name: EpisodeMonitor
        input_ports:
        - body_poses
        output_ports:
        - episode_state

    Ports:
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        episode_state: [status, end time s, path length m, peak |roll| rad,
            peak |pitch| rad, peak tilt rad, min stability margin rad, x, y, ...].
    """

    def __init__(self, chassis_body_index, goal_xy, config: EpisodeConfig | None = None,
                 period_s: float = robot.CONTROL_PERIOD_S):
        super().__init__()
        self._chassis_index = int(chassis_body_index)
        self._goal_xy = (float(goal_xy[0]), float(goal_xy[1]))
        self._config = config or EpisodeConfig()
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        initial = np.zeros(_STATE_SIZE)
        initial[_MARGIN] = np.inf
        self._state_index = self.DeclareDiscreteState(initial)
        self.DeclareStateOutputPort("episode_state", self._state_index)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)

    def _update(self, context, discrete_state):
        # Plain floats: this runs every control step of every rollout, and small
        # numpy calls cost more than the arithmetic.
        state = context.get_discrete_state(self._state_index).get_value().tolist()
        if state[_STATUS] != EpisodeStatus.RUNNING:
            return EventStatus.DidNothing()
        time = context.get_time()
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        R_WB = X_WB.rotation()
        up = R_WB.row(2).tolist()  # The world's +z expressed in B.
        x, y, _ = X_WB.translation().tolist()
        rpy = RollPitchYaw(R_WB)
        tilt = math.acos(min(1.0, max(-1.0, up[2])))
        if not state[_STARTED]:
            state[_LAST_X], state[_LAST_Y], state[_ANCHOR_X], state[_ANCHOR_Y] = x, y, x, y
            state[_ANCHOR_T] = time
            state[_STARTED] = 1.0
        state[_PATH] += math.hypot(x - state[_LAST_X], y - state[_LAST_Y])
        state[_LAST_X], state[_LAST_Y] = x, y
        state[_ROLL] = max(state[_ROLL], abs(rpy.roll_angle()))
        state[_PITCH] = max(state[_PITCH], abs(rpy.pitch_angle()))
        state[_TILT] = max(state[_TILT], tilt)
        state[_MARGIN] = min(state[_MARGIN], min(_margins_of_up(*up)))
        if math.hypot(x - state[_ANCHOR_X], y - state[_ANCHOR_Y]) > self._config.stuck_distance_m:
            state[_ANCHOR_X], state[_ANCHOR_Y], state[_ANCHOR_T] = x, y, time
        config = self._config
        status = EpisodeStatus.RUNNING
        if tilt > math.radians(config.rollover_tilt_deg):
            status = EpisodeStatus.ROLLED_OVER
        elif math.hypot(x - self._goal_xy[0], y - self._goal_xy[1]) <= config.goal_radius_m:
            status = EpisodeStatus.REACHED_GOAL
        elif time >= config.time_limit_s:
            status = EpisodeStatus.TIMEOUT
        elif time - state[_ANCHOR_T] >= config.stuck_window_s:
            status = EpisodeStatus.STUCK
        state[_STATUS] = float(status)
        state[_END_TIME] = time
        discrete_state.set_value(self._state_index, state)
        if status != EpisodeStatus.RUNNING:
            return EventStatus.ReachedTermination(self, f"episode ended: {status.name.lower()}")
        return EventStatus.Succeeded()

    def outcome(self, context) -> EpisodeOutcome:
        """The episode's outcome so far, from this system's context."""
        state = context.get_discrete_state(self._state_index).get_value()
        return EpisodeOutcome(
            status=EpisodeStatus(int(state[_STATUS])).name.lower(),
            time_s=float(state[_END_TIME]),
            path_length_m=float(state[_PATH]),
            peak_abs_roll_deg=math.degrees(state[_ROLL]),
            peak_abs_pitch_deg=math.degrees(state[_PITCH]),
            peak_tilt_deg=math.degrees(state[_TILT]),
            min_stability_margin_deg=math.degrees(state[_MARGIN]) if np.isfinite(state[_MARGIN]) else float("nan"),
            final_xy=(float(state[_LAST_X]), float(state[_LAST_Y])),
        )
