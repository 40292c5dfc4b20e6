"""The world the robot drives in: the terrain family and the environments (data in environments.yaml)."""
