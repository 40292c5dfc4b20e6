"""A short PPO run on DitchDrake-v0 with Stable-Baselines3 (run by hand; not a dependency).

    pip install stable-baselines3
    python examples/gym_ppo.py [total_timesteps]

Stable-Baselines3's `MultiInputPolicy` takes the Dict observation as it is (the float image
stack goes through its flattening MLP extractor; a CNN extractor wants uint8 images). The
default 2048 timesteps are one PPO update, a smoke test of the wiring, not a trained policy:
crossing takes many more (docs/tutorials/gym.md).
"""

import sys

import gymnasium
from stable_baselines3 import PPO

import ditch_drake.gym  # noqa: F401  (registers DitchDrake-v0)


def main(total_timesteps: int = 2048) -> None:
    env = gymnasium.make("DitchDrake-v0", env="wide", task=1)
    model = PPO("MultiInputPolicy", env, n_steps=256, batch_size=64, seed=0, verbose=1)
    model.learn(total_timesteps=total_timesteps)
    observation, _ = env.reset(seed=1)
    while True:
        action, _ = model.predict(observation, deterministic=True)
        observation, _, terminated, truncated, info = env.step(int(action))
        if terminated or truncated:
            print(f"after {total_timesteps} timesteps: {info['status']} at {info['time_s']:.1f} s")
            break
    env.close()


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 2048)
