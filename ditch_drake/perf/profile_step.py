"""Where a control step's time goes: a cProfile of one learned rollout and of Gym steps.

    python -m ditch_drake.perf.profile_step [--env wide] [--task 1] [--seed 300] [--gym-steps 300]
        [--checkpoint CHECKPOINT] [--pstats FILE]

One learned rollout (the shipped model of the environment, as `ditch-drake evaluate` runs it)
is run once unprofiled, so that the renderer's set-up and the first-call costs are paid, and
then again under cProfile from the same seed. The time inside the Simulator's `AdvanceTo` is
split by the blocks whose Python callbacks it calls: the lidar's update (the depth renders and
the cloud), the normal-image converter, the frame stacker (less the normal image it pulls), the
learned policy, the other Python blocks, and the rest: what `AdvanceTo` spends in C++ outside
those callbacks (the plant's dynamics and contact, the integrator, SceneGraph's pose updates,
the framework's event dispatch). Each is given per control step (ms) and as a share of the step.

The same for `--gym-steps` steps of `DitchDrake-v0` driving straight (label 8) from seeded
resets, with the environment's own Python (action, observation dictionary, reward) apart.

cProfile costs each Python call a little, so the absolute figures run above an unprofiled run's
(`ditch-drake bench --json`); the shares are what this is for. Prints one JSON object.
"""

import argparse
import cProfile
import json
import pstats
import sys
import time

from ditch_drake.perf.bench import measure_host_reference_ms
from ditch_drake.spec import robot

# (label, (file suffix, function name)) of the Python callbacks a control step runs, matched on
# the end of their file name; the first match wins.
BLOCK_CALLBACKS = {
    "lidar_render_and_cloud": ("systems/lidar.py", "_update"),
    "normal_image": ("systems/normal_image_converter.py", "_calc_image"),
    "frame_stacker": ("systems/frame_stacker.py", "_push"),
    "policy": ("systems/policy.py", "_update"),
}
ADVANCE = ("~", "<built-in method pydrake.systems.analysis.AdvanceTo>")


def _cumulative(stats: pstats.Stats, suffix: str, name: str) -> float:
    """Summed cumulative seconds of the functions named `name` in files ending in `suffix`."""
    return sum(entry[3] for (file, _, function), entry in stats.stats.items()
               if function == name and file.replace("\\", "/").endswith(suffix))


def _advance_callees(stats: pstats.Stats) -> dict:
    """{function key: cumulative seconds when called from `AdvanceTo`}."""
    callees = {}
    for key, (_, _, _, _, callers) in stats.stats.items():
        for caller, edge in callers.items():
            if caller[2] == ADVANCE[1]:
                callees[key] = callees.get(key, 0.0) + edge[3]
    return callees


def split_control_step(stats: pstats.Stats, control_steps: int) -> dict:
    """The time inside `AdvanceTo` per control step (ms) by block, and each block's share."""
    advance_s = sum(entry[3] for key, entry in stats.stats.items() if key[2] == ADVANCE[1])
    blocks = {label: _cumulative(stats, *callback) for label, callback in BLOCK_CALLBACKS.items()}
    # The stacker pulls the normal image when it pushes a frame; the image is counted apart.
    blocks["frame_stacker"] = max(blocks["frame_stacker"] - blocks["normal_image"], 0.0)
    python_from_advance = sum(_advance_callees(stats).values())
    blocks["other_python_blocks"] = max(python_from_advance - sum(blocks.values()), 0.0)
    blocks["plant_and_framework_cpp"] = max(advance_s - python_from_advance, 0.0)
    per_step = {f"{label}_ms": 1e3 * seconds / control_steps for label, seconds in blocks.items()}
    total = sum(blocks.values())
    shares = {f"{label}_share": seconds / total for label, seconds in blocks.items()} if total > 0 else {}
    return {"control_steps": control_steps, "advance_ms_per_step": 1e3 * advance_s / control_steps,
            **per_step, **shares}


def network_multiply_adds(checkpoint: str = "wide") -> int:
    """Multiply-adds of one batch-1 forward pass of a checkpoint's network (its convolutions
    and linear layers, counted by forward hooks)."""
    import torch

    from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path

    model = load_checkpoint(resolve_checkpoint_path(checkpoint)).build_model().eval()
    counts = []

    def count(module, _, output):
        if isinstance(module, torch.nn.Conv2d):
            per_output = module.in_channels // module.groups * module.kernel_size[0] * module.kernel_size[1]
            counts.append(output.numel() * per_output)
        elif isinstance(module, torch.nn.Linear):
            counts.append(output.numel() * module.in_features)

    hooks = [module.register_forward_hook(count) for module in model.modules()
             if isinstance(module, (torch.nn.Conv2d, torch.nn.Linear))]
    config = model.config
    with torch.inference_mode():
        model(torch.zeros(1, config.image_channels, config.image_size, config.image_size),
              torch.zeros(1, config.imu_size), torch.zeros(1, config.distance_size), torch.zeros(1, config.bearing_size))
    for hook in hooks:
        hook.remove()
    return int(sum(counts))


def core_gflops(size: int = 512, repeats: int = 20) -> float:
    """This core's float32 rate (GFLOP/s): the median of one-thread 512 x 512 matrix products
    in torch, about the best a convolution's inner product reaches."""
    import numpy as np
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        a, b = torch.rand(size, size), torch.rand(size, size)
        for _ in range(3):
            a @ b
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            a @ b
            times.append(time.perf_counter() - start)
    finally:
        torch.set_num_threads(threads)
    return 2 * size**3 / float(np.median(times)) / 1e9


def profile_learned_rollout(environment: str, task: int, seed: int, checkpoint: str = "",
                            pstats_file: str = "") -> dict:
    """The split of one learned rollout's control steps (see the module doc)."""
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode

    config = RolloutConfig(scene=SceneConfig(environment=environment, task=task),
                           controller=LearnedPolicyConfig(checkpoint=checkpoint))
    diagram, scene = MakeRolloutDiagram(config)
    simulator = Simulator(diagram)
    start = time.perf_counter()
    outcome = RunEpisode(simulator, diagram, scene, seed)
    unprofiled_wall_s = time.perf_counter() - start
    profiler = cProfile.Profile()
    profiler.enable()
    RunEpisode(simulator, diagram, scene, seed)
    profiler.disable()
    if pstats_file:
        profiler.dump_stats(pstats_file)
    simulated_s = simulator.get_context().get_time()
    steps = max(round(simulated_s / robot.CONTROL_PERIOD_S), 1)
    return {"environment": environment, "task": task, "seed": seed, "outcome": outcome.status,
            "simulated_s": simulated_s, "unprofiled_wall_ms_per_step": 1e3 * unprofiled_wall_s / steps,
            **split_control_step(pstats.Stats(profiler), steps)}


def profile_gym_steps(environment: str, task: int, seed: int, steps: int) -> dict:
    """The split of `steps` straight-ahead `DitchDrake-v0` steps, with the environment's own
    Python (everything in `step` outside `AdvanceTo`) apart."""
    from ditch_drake.gym.env import DitchDrakeEnv
    from ditch_drake.spec import actions

    env = DitchDrakeEnv(env=environment, task=task)

    def run(profiler: cProfile.Profile | None) -> float:
        # Resets are left out: only `step` is timed and profiled.
        episode_seed = seed
        env.reset(seed=episode_seed)
        wall = 0.0
        for _ in range(steps):
            start = time.perf_counter()
            if profiler:
                profiler.enable()
            _, _, terminated, truncated, _ = env.step(actions.STRAIGHT_LABEL)
            if profiler:
                profiler.disable()
            wall += time.perf_counter() - start
            if terminated or truncated:
                episode_seed += 1
                env.reset(seed=episode_seed)
        return wall

    unprofiled_s = run(None)
    profiler = cProfile.Profile()
    run(profiler)
    stats = pstats.Stats(profiler)

    step_s = _cumulative(stats, "ditch_drake/gym/env.py", "step")
    split = split_control_step(stats, steps)
    advance_ms = split["advance_ms_per_step"]
    env.close()
    return {"environment": environment, "steps": steps, "unprofiled_ms_per_step": 1e3 * unprofiled_s / steps,
            "env_step_ms": 1e3 * step_s / steps, "env_python_outside_advance_ms": 1e3 * step_s / steps - advance_ms,
            **split}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m ditch_drake.perf.profile_step", description=__doc__.split("\n")[0])
    parser.add_argument("--env", default="wide")
    parser.add_argument("--task", type=int, default=1)
    parser.add_argument("--seed", type=int, default=300)
    parser.add_argument("--checkpoint", default="", help="a checkpoint (default: the environment's shipped model)")
    parser.add_argument("--gym-steps", type=int, default=300, help="Gym steps to profile (0: none)")
    parser.add_argument("--pstats", default="", help="also write the rollout's raw profile here (pstats format)")
    args = parser.parse_args(argv)
    if args.gym_steps < 0:
        parser.error(f"--gym-steps {args.gym_steps}: expected >= 0")
    result = {"host_reference_start_ms": measure_host_reference_ms()}
    rollout = profile_learned_rollout(args.env, args.task, args.seed, args.checkpoint, args.pstats)
    result["learned_rollout"] = rollout
    if args.gym_steps:
        result["gym"] = profile_gym_steps(args.env, args.task, args.seed, args.gym_steps)
    multiply_adds = network_multiply_adds(args.checkpoint or args.env)
    gflops = core_gflops()
    network_ms = 2 * multiply_adds / gflops / 1e6
    result["floor"] = {
        "network_mflop": 2 * multiply_adds / 1e6, "core_gflops": gflops, "network_at_core_rate_ms": network_ms,
        # The plant, the network at this core's matrix-product rate and the lidar's renders:
        # what a control step would cost if everything else were free.
        "control_step_floor_ms": rollout["plant_and_framework_cpp_ms"] + network_ms
        + rollout["lidar_render_and_cloud_ms"],
    }
    result["host_reference_end_ms"] = measure_host_reference_ms()
    json.dump(result, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
