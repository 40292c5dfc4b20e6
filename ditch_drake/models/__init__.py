"""Trained policies shipped with the package (`<environment>.pt`); docs/results/shipped_models.md has the
commands that made them."""
