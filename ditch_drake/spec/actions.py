"""The action space (paper 3.3; docs/design.md, "The action table"): 17 labels <-> (v, w) commands.

v = 1.0 m/s for every label; label 8 drives straight; label l turns at
w = sign(l - 8) * (0.05 + 0.1 |l - 8|) rad/s, positive w turning left
(counter-clockwise seen from above). This module is the one place these numbers
live; everything else imports it.
"""

import numpy as np

NUM_LABELS = 17
STRAIGHT_LABEL = 8
SPEED_MPS = 1.0


def _angular_rate(label: int) -> float:
    offset = label - STRAIGHT_LABEL
    return 0.0 if offset == 0 else float(np.sign(offset) * (0.05 + 0.1 * abs(offset)))


ANGULAR_RATES_RADPS = np.array([_angular_rate(label) for label in range(NUM_LABELS)])
COMMANDS = np.column_stack([np.full(NUM_LABELS, SPEED_MPS), ANGULAR_RATES_RADPS])


def label_to_command(label: int) -> np.ndarray:
    """The [v m/s, w rad/s] command of a label in 0..16."""
    if not (isinstance(label, (int, np.integer)) and 0 <= label < NUM_LABELS):
        raise ValueError(f"action label {label!r} is out of range: expected an integer in 0..{NUM_LABELS - 1}")
    return COMMANDS[label].copy()


def quantize(command) -> int:
    """The label whose angular rate is nearest to a continuous command's w.

    Ties go to the label nearer to straight ahead. v is ignored: every label drives
    at `SPEED_MPS`, as the paper's demonstrators did.
    """
    command = np.asarray(command, dtype=float)
    if command.shape != (2,) or not np.all(np.isfinite(command)):
        raise ValueError(f"command {command.tolist()} must be a finite [v m/s, w rad/s]")
    distance = np.abs(ANGULAR_RATES_RADPS - command[1])
    candidates = np.flatnonzero(distance <= distance.min() + 1e-12)
    return int(candidates[np.argmin(np.abs(candidates - STRAIGHT_LABEL))])
