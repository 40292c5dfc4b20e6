"""When each stage runs within a control step: seconds after each 10 Hz tick.

Every stage updates periodically at `robot.CONTROL_PERIOD_S`. Drake hands all the
updates due at one instant the state from before any of them, so stages that share
an instant see each other's previous results. Staggering them by a millisecond
runs the chain lidar -> normal image -> frame stacker -> controller -> recorder in
order within each control step, with one millisecond of simulated latency per link
instead of a whole control period.
"""

LIDAR_OFFSET_S = 0.0
NORMAL_IMAGE_OFFSET_S = 0.001
STACKER_OFFSET_S = 0.002
CONTROLLER_OFFSET_S = 0.003
RECORDER_OFFSET_S = 0.004
