"""The numbers of SPEC.md, each in one module: the action table, the robot, the observation, the control schedule, planar angle conventions."""
