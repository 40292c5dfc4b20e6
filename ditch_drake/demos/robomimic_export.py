"""robomimic's HDF5 layout, written with h5py (`export_dataset(..., "robomimic", ...)`).

    FILE.hdf5
      data/                   attrs: total (frames), env_args (JSON: env_name, env_type, env_kwargs)
        demo_0/               attrs: num_samples, source_episode, metadata (the episode.json)
          actions             (T, 2) float64   [v m/s, w rad/s] of the label, from the action table
          obs/image           (T, 128, 128, 1) uint8   newest surface-normal image, channel last
          obs/imu             (T, 8) float32   [roll, pitch] newest first (rad)
          obs/distance        (T, 4) float32   distance to the goal, newest first (m)
          obs/bearing         (T, 4) float32   bearing to the goal, newest first (rad)
          rewards             (T,) float64     1 at the last step of an episode that reached its goal
          dones               (T,) int64       1 at the last step
          states              (T, 6) float32   the chassis pose [x, y, z, roll, pitch, yaw]
          labels, intervention, raw_command    the store's other fields, as stored
      mask/<split>            the demo names of each ditch split present (filter keys)

`demo_<i>` counts 0..N-1 in the store's order. There is no `next_obs`: robomimic loads it for
offline reinforcement learning only (`config.train.hdf5_load_next_obs`, False by default and
for every behavioural-cloning algorithm), and it would double the file. `states` is not a full
simulator state (robomimic resets robosuite scenes from it, nothing else): it is the pose.
The actions lie in [-1, 1] as robomimic expects (v is 1, |w| <= 0.85). Datasets are stored
uncompressed, as robomimic's own, so a training batch reads without decoding.
"""

import json
from pathlib import Path

import numpy as np

from ditch_drake.demos.exports import driver_of, label_commands, task_text

# robomimic's `EnvType.GYM_TYPE`: the environment is a Gym id made with its keyword arguments.
GYM_ENV_TYPE = 2
ENV_NAME = "DitchDrake-v0"


def _env_args(episodes: list) -> dict:
    """`data`'s env_args: the Gym id, and, since an environment and task differ per demo, the
    keyword arguments only where every demo shares them."""
    environments = {episode.metadata.get("environment") for episode in episodes}
    tasks = {(episode.metadata.get("task") or {}).get("index") for episode in episodes}
    kwargs = {}
    if len(environments) == 1:
        kwargs["env"] = environments.pop()
        if len(tasks) == 1 and None not in tasks:
            kwargs["task"] = tasks.pop()
    return {"env_name": ENV_NAME, "env_type": GYM_ENV_TYPE, "env_kwargs": kwargs}


def write_robomimic(store, episodes: list, out: Path, progress: bool = True) -> dict:
    """Writes `episodes` of `store` as one robomimic HDF5 file at `out`."""
    import h5py
    from tqdm import tqdm

    splits: dict[str, list[str]] = {}
    frames = 0
    with h5py.File(out, "w") as file:
        data = file.create_group("data")
        for index, episode in enumerate(tqdm(episodes, desc=f"export {store.root}", disable=not progress)):
            arrays = store.read(episode)
            name = f"demo_{index}"
            demo = data.create_group(name)
            steps = episode.steps
            demo.attrs["num_samples"] = steps
            demo.attrs["source_episode"] = episode.name
            demo.attrs["task"] = task_text(episode.metadata)
            demo.attrs["driver"] = driver_of(episode.metadata)
            demo.attrs["metadata"] = json.dumps(episode.metadata)
            demo.create_dataset("actions", data=label_commands(arrays["label"]))
            demo.create_dataset("obs/image", data=np.asarray(arrays["image"])[..., np.newaxis])
            demo.create_dataset("obs/imu", data=arrays["imu_stack"])
            demo.create_dataset("obs/distance", data=arrays["distance_stack"])
            demo.create_dataset("obs/bearing", data=arrays["bearing_stack"])
            reached = (episode.metadata.get("outcome") or {}).get("status") == "reached_goal"
            rewards = np.zeros(steps)
            rewards[-1] = float(reached)
            dones = np.zeros(steps, dtype=np.int64)
            dones[-1] = 1
            demo.create_dataset("rewards", data=rewards)
            demo.create_dataset("dones", data=dones)
            demo.create_dataset("states", data=arrays["pose"])
            demo.create_dataset("labels", data=arrays["label"])
            demo.create_dataset("intervention", data=arrays["intervention"])
            demo.create_dataset("raw_command", data=arrays["raw_command"])
            split = (episode.metadata.get("ditch") or {}).get("split")
            if split:
                splits.setdefault(split, []).append(name)
            frames += steps
        data.attrs["total"] = frames
        data.attrs["env_args"] = json.dumps(_env_args(episodes))
        for split, names in splits.items():
            file.create_dataset(f"mask/{split}", data=np.array(names, dtype="S"))
    return {"episodes": len(episodes), "frames": frames, "filter_keys": {key: len(names) for key, names in splits.items()}}
