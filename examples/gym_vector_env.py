"""Two DitchDrake-v0 environments stepping in two spawned processes (docs/tutorials/gym.md).

    python examples/gym_vector_env.py

Each worker builds its own diagram (`"ditch_drake:DitchDrake-v0"` imports the package in the
worker); the observations come back batched. Every action here is label 8 (straight ahead),
which drives both robots into the wide ditch head-on: watch them roll over.
"""

import gymnasium
import numpy as np


def main() -> None:
    envs = gymnasium.make_vec("ditch_drake:DitchDrake-v0", num_envs=2, vectorization_mode="async",
                              vector_kwargs={"context": "spawn"}, env="wide", task=1)
    observations, _ = envs.reset(seed=[3, 4])
    print({key: value.shape for key, value in observations.items()})
    ended = np.zeros(2, dtype=bool)
    returns = np.zeros(2)
    while not ended.all():
        # Vector envs reset an ended sub-environment at its next step: count only the first episode.
        observations, rewards, terminated, truncated, infos = envs.step(np.full(2, 8))
        returns += np.where(ended, 0.0, rewards)
        for i in np.flatnonzero((terminated | truncated) & ~ended):
            print(f"env {i}: {infos['status'][i]} at {infos['time_s'][i]:.1f} s, return {returns[i]:.2f}")
        ended |= terminated | truncated
    envs.close()


if __name__ == "__main__":
    main()
