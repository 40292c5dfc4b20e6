"""A gate's signal in the seconds before each rollover of a signals file, beside the upper
thresholds that budgets set on it: how early a gate reading it could have handed over, and why
a small budget warns late (`ditch-drake gate-thresholds --figure`)."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from ditch_drake.common.files import save_figure
from ditch_drake.learning.uncertainty import SIGNAL_UNITS


def rollover_signal_figure(traces: list[tuple[np.ndarray, np.ndarray]], signal: str,
                           thresholds: list[tuple[float, float]], path: str | Path, title: str) -> Path:
    """Draws each trace of `signal_before_rollovers` (one line per rollover, time before it on
    x) and a dashed line per (budget, upper threshold); writes the PNG at `path` atomically."""
    figure, axes = plt.subplots(figsize=(6.4, 4.2))
    for index, (before_s, values) in enumerate(traces):
        axes.plot(before_s, values, color="tab:red", alpha=0.55, linewidth=1.2,
                  label=f"the {len(traces)} rollovers" if index == 0 else None)
    shades = plt.get_cmap("viridis")(np.linspace(0.0, 0.85, max(1, len(thresholds))))
    for (budget, upper), shade in zip(thresholds, shades):
        axes.axhline(upper, color=shade, linestyle="--", linewidth=1.0, label=f"upper threshold, budget {budget:.0%}")
    axes.set_xlabel("time before the rollover (s)")
    axes.set_ylabel(f"{signal} ({SIGNAL_UNITS[signal]})")
    axes.set_title(title, fontsize=9)
    axes.legend(loc="best", fontsize=7)
    figure.tight_layout()
    return save_figure(figure, path)
