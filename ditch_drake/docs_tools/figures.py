"""Figures for docs/, each made by a `ditch-drake figure ...` command."""

from pathlib import Path

import numpy as np

from ditch_drake.common.files import atomic_write_text, save_figure
from ditch_drake.demos.collect import record_demonstration


def normal_image_figure(environment: str, out_dir: str | Path, seed: int = 0) -> Path:
    """Surface-normal images from an expert run: on the flat, at the hinge, on the wall.

    Saves `normal_image_<environment>.png` in `out_dir` and returns its path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    demonstration = record_demonstration(environment, 0, seed)
    images, pose = demonstration.arrays["image"], demonstration.arrays["pose"]
    tilt = np.degrees(np.abs(pose[:, 3:5]).max(axis=1))
    moments = {
        "flat approach": 10,
        "at the hinge": int(np.argmax(tilt > 5.0)),
        "on the wall": int(np.argmax(tilt > 40.0)),
    }
    figure, axes = plt.subplots(1, 3, figsize=(10, 3.8))
    for axis, (title, step) in zip(axes, moments.items()):
        shown = axis.imshow(images[step] / 255.0, cmap="gray", vmin=0.0, vmax=1.0)
        axis.set_title(f"{title} (t = {demonstration.arrays['time_s'][step]:.1f} s)")
        axis.set_xticks([])
        axis.set_yticks([])
    figure.colorbar(shown, ax=axes, fraction=0.02, label="normal z (1 = flat, 0.57 = 55 deg wall)")
    figure.suptitle(f"{environment}: surface-normal images (paper Fig. 1a), forward is up, seed {seed}")
    return save_figure(figure, Path(out_dir) / f"normal_image_{environment}.png", dpi=80)


def diagram_figure(out_dir: str | Path, environment: str = "wide", controller: str = "learned",
                   max_depth: int = 1) -> Path:
    """The rollout diagram (scene, observation blocks, `controller`: a registered name) drawn by Drake's own
    `GetGraphvizString` and rendered by Graphviz's `dot` to `<out_dir>/diagram.svg`.

    Raises:
        FileNotFoundError: Graphviz's `dot` is not installed (Debian: apt-get install graphviz).
    """
    import shutil
    import subprocess

    from ditch_drake.diagrams.controllers import controller_config
    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig

    dot = shutil.which("dot")
    if dot is None:
        raise FileNotFoundError("Graphviz's `dot` is needed to draw the diagram (apt-get install graphviz)")
    config = controller_config(controller)  # Any registered controller, by name.
    diagram, _ = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment=environment), controller=config))
    svg = subprocess.run([dot, "-Tsvg"], input=diagram.GetGraphvizString(max_depth=max_depth), capture_output=True,
                         text=True, check=True).stdout
    return atomic_write_text(Path(out_dir) / "diagram.svg", svg)


# The ditches' wall angle (paper 4.1: "walls sloped at approximately 55 deg"), marked on the curves.
DITCH_WALL_DEG = 55.0


def cost_curves() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The slope cost of each registered DWA baseline against the slope angle.

    Returns:
        controller name -> (slope angles (deg), costmap cost), from the controllers' default
        costmaps (`slope_cost` of the normal z = cos(slope)), every tenth of a degree.
    """
    from ditch_drake.diagrams.controllers import controller_config
    from ditch_drake.planning.costmap import slope_cost

    slope_deg = np.linspace(0.0, 90.0, 901)
    curves = {}
    for name in ("dwa", "dwa_paper"):
        costmap = controller_config(name).planner.costmap
        curves[name] = (slope_deg, slope_cost(np.cos(np.radians(slope_deg)), costmap.free_slope_deg,
                                              costmap.lethal_slope_deg))
    return curves


def cost_curve_figure(out_dir: str | Path) -> Path:
    """The costmap cost of `dwa` and `dwa_paper` against the slope angle, the ditch walls'
    55 deg marked: saves `costmap_cost_curves.png` in `out_dir` and returns its path.

    Quick (no simulation): `ditch-drake figure cost-curves --out docs/img`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ditch_drake.planning.costmap import LETHAL_OBSTACLE, MAX_NON_OBSTACLE

    styles = {"dwa": ("tab:red", "dwa: lethal from 45 deg"), "dwa_paper": ("tab:blue", "dwa_paper: never lethal")}
    figure, axis = plt.subplots(figsize=(7.5, 4.2))
    for name, (slope_deg, cost) in cost_curves().items():
        color, label = styles[name]
        axis.plot(slope_deg, cost, color=color, lw=2.0, label=label)
        at_wall = float(np.interp(DITCH_WALL_DEG, slope_deg, cost))
        axis.plot(DITCH_WALL_DEG, at_wall, "o", color=color)
        axis.annotate(f"{at_wall:.0f}", (DITCH_WALL_DEG, at_wall), textcoords="offset points", xytext=(6, -12),
                      color=color)
    axis.axvline(DITCH_WALL_DEG, color="0.4", ls=":", lw=1.2)
    axis.text(DITCH_WALL_DEG + 0.8, 30, f"ditch walls ({DITCH_WALL_DEG:g} deg)", color="0.3", fontsize=9)
    # The two levels are 2 apart: one label under its line, one over.
    for level, text, offset, align in ((MAX_NON_OBSTACLE, "252: highest non-lethal", -3, "top"),
                                       (LETHAL_OBSTACLE, "254: LETHAL", 3, "bottom")):
        axis.axhline(level, color="0.7", ls="--", lw=0.8)
        axis.text(1.0, level + offset, text, color="0.4", fontsize=8, va=align)
    axis.set_xlim(0.0, 90.0)
    axis.set_ylim(-5.0, 275.0)
    axis.set_xticks(np.arange(0, 91, 15))
    axis.set_xlabel("slope (deg from horizontal): acos of the normal's world z")
    axis.set_ylabel("costmap cost")
    axis.set_title("Slope cost of a costmap cell, per DWA baseline\n(vertical obstacles: lethal in both, "
                   "dwa_paper by step height)", fontsize=10)
    axis.legend(loc="center left", fontsize=9)
    figure.tight_layout()
    return save_figure(figure, Path(out_dir) / "costmap_cost_curves.png", dpi=80)
