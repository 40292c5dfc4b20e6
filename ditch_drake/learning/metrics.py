"""Classification metrics for the 17 ordered action labels (paper 3.6).

Neighbouring labels differ by 0.1 rad/s of turn rate, so the paper counts a prediction
within a tolerance of the true label as right (ordinal accuracy, tolerance 1).
"""

import numpy as np

from ditch_drake.spec.actions import NUM_LABELS

ORDINAL_TOLERANCE = 1
"""The paper's tolerance: a prediction one label off still counts."""


def _pair(predicted, true) -> tuple[np.ndarray, np.ndarray]:
    predicted = np.asarray(predicted, dtype=np.int64).ravel()
    true = np.asarray(true, dtype=np.int64).ravel()
    if predicted.shape != true.shape:
        raise ValueError(f"predicted labels {predicted.shape} and true labels {true.shape} differ in length")
    return predicted, true


def ordinal_accuracy(predicted, true, tolerance: int = ORDINAL_TOLERANCE) -> float:
    """Share of predictions with |predicted - true| <= tolerance; nan for no samples.

    Args:
        predicted: predicted labels.
        true: true labels, same length.
        tolerance: labels of slack (0: exact accuracy; the paper uses 1).

    Raises:
        ValueError: lengths differ or a negative tolerance.
    """
    if tolerance < 0:
        raise ValueError(f"tolerance={tolerance} must be >= 0")
    predicted, true = _pair(predicted, true)
    if predicted.size == 0:
        return float("nan")
    return float(np.mean(np.abs(predicted - true) <= tolerance))


def exact_accuracy(predicted, true) -> float:
    """Share of predictions equal to the true label; nan for no samples."""
    return ordinal_accuracy(predicted, true, tolerance=0)


def confusion_matrix(predicted, true, num_labels: int = NUM_LABELS) -> np.ndarray:
    """(num_labels, num_labels) int64 counts: row = true label, column = predicted label.

    Raises:
        ValueError: lengths differ or a label outside 0..num_labels-1.
    """
    predicted, true = _pair(predicted, true)
    for name, labels in (("predicted", predicted), ("true", true)):
        if labels.size and (labels.min() < 0 or labels.max() >= num_labels):
            raise ValueError(f"{name} labels must be in 0..{num_labels - 1}, got {np.unique(labels).tolist()}")
    matrix = np.zeros((num_labels, num_labels), dtype=np.int64)
    np.add.at(matrix, (true, predicted), 1)
    return matrix
