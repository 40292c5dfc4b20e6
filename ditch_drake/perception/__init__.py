"""Perception: turning the lidar's point cloud into the network's surface-normal image."""
