"""Trained policies shipped with the package (`<environment>.pt`); see docs/learning.md for the commands that made them."""
