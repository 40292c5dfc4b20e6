"""When each stage runs within a control step: seconds after each 10 Hz tick.

Every stage updates periodically at `robot.CONTROL_PERIOD_S`. Drake hands all the
updates due at one instant the state from before any of them, so stages that share
an instant see each other's previous results. Staggering them by milliseconds
runs the chain lidar -> frame stacker -> controller -> recorder in order within each
control step, with simulated latency of milliseconds per link instead of a whole
control period.

The normal-image converter has no tick: its image is a cached function of the
lidar's cloud, made when the frame stacker reads it, so the stacker stacks the image
of the cloud rendered at the same control step's lidar tick. (It once had its own
tick at 1 ms; the later stages kept their times, so every rollout is unchanged.)
"""

from dataclasses import dataclass

from ditch_drake.common.errors import ConfigError
from ditch_drake.spec import robot

LIDAR_OFFSET_S = 0.0
STACKER_OFFSET_S = 0.002
CONTROLLER_OFFSET_S = 0.003
RECORDER_OFFSET_S = 0.004


@dataclass
class ScheduleConfig:
    """The control schedule every builder passes down: one period, and each stage's offset (s).

    The scene carries it (`SceneConfig.schedule`); the blocks take their period and offset
    from it, so changing the control rate is one setting, not a default in each constructor.
    The scripted drivers that read only the robot's pose (the edge-angle driver) act at the
    tick itself; the episode monitor checks at the tick too.
    """

    control_period_s: float = robot.CONTROL_PERIOD_S
    lidar_offset_s: float = LIDAR_OFFSET_S
    stacker_offset_s: float = STACKER_OFFSET_S
    controller_offset_s: float = CONTROLLER_OFFSET_S
    recorder_offset_s: float = RECORDER_OFFSET_S

    def __post_init__(self):
        offsets = [self.lidar_offset_s, self.stacker_offset_s, self.controller_offset_s, self.recorder_offset_s]
        if not self.control_period_s > 0 or not all(0 <= offset < self.control_period_s for offset in offsets):
            raise ConfigError(f"schedule {self}: expected control_period_s > 0 and every offset in "
                              "[0, control_period_s)")
        if not offsets == sorted(offsets):
            raise ConfigError(f"schedule {self}: the stages must run in order, lidar <= stacker <= controller "
                              "<= recorder")


def gate_signal_offset_s(controller_offset_s: float, recorder_offset_s: float) -> float:
    """When in the control period a block that gives the shared-control gate its signal ticks
    (s): after the controllers' tick, so it reads this step's command and observation, and
    before the gate's: midway between the controllers' tick and the gate's, which is midway
    between the controllers' and the recorder's."""
    return (3 * controller_offset_s + recorder_offset_s) / 4
