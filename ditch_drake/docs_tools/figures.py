"""Figures for docs/, each made by a `ditch-drake figure ...` command."""

from pathlib import Path

import numpy as np

from ditch_drake.common.files import atomic_write_text
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
    path = Path(out_dir) / f"normal_image_{environment}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)
    plt.close(figure)
    return path


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
