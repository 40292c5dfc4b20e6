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

LIDAR_OFFSET_S = 0.0
STACKER_OFFSET_S = 0.002
CONTROLLER_OFFSET_S = 0.003
RECORDER_OFFSET_S = 0.004
