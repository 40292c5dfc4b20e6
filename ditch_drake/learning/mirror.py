"""Left-right mirroring of training samples (`train-generalist --mirror`).

A ditch crossed with the course on the robot's left is, reflected in the robot's x-z plane,
one crossed with it on the right, and the Husky and its lidar are symmetric about that plane.
The reflection of a sample, in the layouts of `ditch_drake.spec.observation_layout`:

- image: columns reversed (column 0 is +y of the body frame; a pixel is the normal's z
  component, which the reflection keeps);
- IMU stack: roll negated, pitch kept;
- distance stack: kept;
- bearing stack: negated (positive is the goal to the left);
- label: `NUM_LABELS - 1 - label`, the same turn rate the other way (`ditch_drake.spec.actions`).
"""

import numpy as np

from ditch_drake.spec.actions import NUM_LABELS
from ditch_drake.spec.observation_layout import IMU_SIZE

# Index of roll within each step of the IMU stack ([roll, pitch] per step).
_ROLL = 0


def mirror_left_right(batch: dict[str, np.ndarray], rows: np.ndarray | slice = slice(None)) -> None:
    """Reflects, in place, the samples `rows` (a boolean mask or indices) of `batch`.

    Args:
        batch: arrays named as `ArraySet`'s fields: "image" (N, ..., cols: stacked or single
            frames; absent when the images are reflected where they are read, as
            `ditch_drake.learning.stream.LazyImageStack` does), "imu" (N, stack * 2), "bearing"
            (N, stack) and, where there are labels, "label" (N,); any other key is kept.
        rows: which samples to reflect (default: all).
    """
    if "image" in batch:
        batch["image"][rows] = batch["image"][rows][..., ::-1]
    batch["imu"][rows, _ROLL::IMU_SIZE] = -batch["imu"][rows, _ROLL::IMU_SIZE]
    batch["bearing"][rows] = -batch["bearing"][rows]
    if "label" in batch:
        batch["label"][rows] = NUM_LABELS - 1 - batch["label"][rows]
