"""The project's numbers, each in one module: the robot, the action table, the observation, the control schedule,
planar angle conventions. docs/design.md explains them and how they were read from the paper.
"""
