"""Commands of one episode: scenario, demo, view, replay, teleop."""

import math
import sys
import time

from ditch_drake.cli.options import (
    Commands,
    ConfigDefault,
    add_checkpoint,
    add_environments_file,
    add_episode,
    add_out,
    add_scenario,
    check_task,
    checkpoint_for,
    print_table,
    scenario_from_options,
)
from ditch_drake.cli.shared_options import add_gate_options, shared_config_from_options
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.seeds import check_seed

# The demo's recording, which `figure screenshot` opens by default.
DEMO_HTML = "results/demo.html"


def check_realtime_rate(rate: float) -> None:
    """Refuses a rate the simulator cannot pace to: NaN, negative or infinite (0 runs unpaced)."""
    if not 0 <= rate < math.inf:
        raise ConfigError(f"--realtime-rate {rate}: expected a finite number of simulated seconds per wall-clock "
                          "second, >= 0 (0: as fast as it runs)")


def add_scenario_command(commands: Commands) -> None:
    scenario = commands.add("scenario", "print a Scenario as YAML: the default one (a template to edit), or the one "
                                        "the options make", with_environments=True)
    scenario.add_argument("--print", action="store_true", help="print it (the only action; kept for clarity)")
    add_scenario(scenario, "learned")
    scenario.set_defaults(run=cmd_scenario)


def cmd_scenario(args) -> int:
    """Prints a Scenario as YAML: the default one (a template), or the one the options make."""
    from ditch_drake.diagrams.scenario import scenario_yaml

    print(scenario_yaml(scenario_from_options(args)), end="")
    return 0


def add_demo(commands: Commands) -> None:
    demo = commands.add("demo", "the main job: shipped policy, DWA baseline and a head-on driver through a ditch; "
                                "outcome table and an HTML recording", with_environments=True)
    add_episode(demo)
    add_environments_file(demo)
    add_checkpoint(demo, "the environment's shipped model")
    demo.add_argument("--html", default=DEMO_HTML, help="where the recording goes")
    demo.set_defaults(run=cmd_demo)


def cmd_demo(args) -> int:
    """The main job: the shipped policy, the DWA baseline and a head-on driver through one ditch;
    an outcome table and the policy's rollout as a standalone HTML page."""
    check_task(args.env, args.task, args.environments)
    check_seed(args.seed)
    checkpoint = checkpoint_for(args, args.env)
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.controllers import controller_config
    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.replay import ReplayConfig, record_replay
    from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig, RunEpisode

    scene = SceneConfig(environment=args.env, task=args.task, environments_file=args.environments or "")
    rows = []

    def row(name, outcome, wall_s):
        rows.append({"controller": name, "outcome": outcome.status, "sim_time_s": f"{outcome.time_s:.1f}",
                     "path_m": f"{outcome.path_length_m:.1f}", "peak_tilt_deg": f"{outcome.peak_tilt_deg:.0f}",
                     "wall_s": f"{wall_s:.1f}"})

    print(f"[1/3] learned policy ({checkpoint} model), recorded as {args.html}", file=sys.stderr, flush=True)
    start = time.perf_counter()
    replay = record_replay(ReplayConfig(
        rollout=RolloutConfig(scene=scene, controller=controller_config("learned", checkpoint, args.seed)),
        seed=args.seed, out=args.html), progress="learned policy")
    row(f"learned policy ({checkpoint} model)", replay.outcome, time.perf_counter() - start)
    for step, (name, controller) in enumerate((("DWA baseline (move_base-style)", "dwa"),
                                               ("head-on scripted driver (reference)", "head_on")), start=2):
        print(f"[{step}/3] {name}", file=sys.stderr, flush=True)
        start = time.perf_counter()
        diagram, built = MakeRolloutDiagram(RolloutConfig(scene=scene,
                                                          controller=controller_config(controller, "", args.seed)))
        row(name, RunEpisode(Simulator(diagram), diagram, built, args.seed, progress=controller),
            time.perf_counter() - start)
    print(f"environment {args.env}, task {args.task} ({built.task.name}), seed {args.seed}")
    print_table(rows, ["controller", "outcome", "sim_time_s", "path_m", "peak_tilt_deg", "wall_s"])
    print(f"recording of the learned policy's rollout: {replay.html_path} (open it in any browser)")
    return 0


def add_view(commands: Commands) -> None:
    view = commands.add("view", "open the scene in meshcat and drive through it in real time", with_environments=True)
    add_scenario(view, "edge_angle")
    view.add_argument("--realtime-rate", type=float, default=1.0, help="simulated seconds per wall-clock second")
    view.add_argument("--wait", action="store_true", help="keep meshcat open until Enter")
    view.set_defaults(run=cmd_view)


def cmd_view(args) -> int:
    """Opens the scene in meshcat and drives it in real time (the scripted driver unless told otherwise)."""
    check_realtime_rate(args.realtime_rate)
    scenario = scenario_from_options(args, default_controller="edge_angle")
    from pydrake.geometry import StartMeshcat
    from pydrake.systems.analysis import ApplySimulatorConfig, Simulator

    from ditch_drake.diagrams.rollout import RunEpisode
    from ditch_drake.diagrams.scenario import MakeScenarioDiagram

    meshcat = StartMeshcat()
    diagram, scene = MakeScenarioDiagram(scenario, meshcat=meshcat)
    simulator = Simulator(diagram)
    ApplySimulatorConfig(scenario.simulator, simulator)
    simulator.set_target_realtime_rate(args.realtime_rate)
    print(f"meshcat: open {meshcat.web_url()} to watch  (Ctrl-C to stop)", flush=True)
    outcome = RunEpisode(simulator, diagram, scene, scenario.seed)
    print(f"outcome: {outcome.status} after {outcome.time_s:.1f} s")
    if args.wait:
        input("press Enter to close")
    return 0


def add_teleop(commands: Commands) -> None:
    teleop = commands.add("teleop", "record your own demonstration: steer in meshcat", with_environments=True)
    add_episode(teleop)
    add_environments_file(teleop)
    add_out(teleop, "dataset folder (made if missing); the demonstration is appended as its next episode")
    teleop.add_argument("--realtime-rate", type=float, default=1.0, help="simulated seconds per wall-clock second")
    teleop.add_argument("--shared", action="store_true",
                        help="the learned policy drives and hands over to you where it is unsure (the page turns "
                             "red and says so); the steps you drove are stored as interventions")
    add_checkpoint(teleop, "the shipped generalist ensemble, generalist_k5; with --shared")
    add_gate_options(teleop, ["teleop"])
    teleop.set_defaults(run=cmd_teleop)


def cmd_teleop(args) -> int:
    """A person drives (arrow keys or gamepad in the meshcat page); a success is kept. With
    --shared the gated policy drives and the person only where it hands over; every episode is
    kept, its steps flagged by who drove them."""
    check_task(args.env, args.task, args.environments)
    check_seed(args.seed)
    check_realtime_rate(args.realtime_rate)
    if args.checkpoint is not None and not args.shared:
        raise ConfigError(f"--checkpoint {args.checkpoint}: a policy drives only with --shared")
    shared = shared_config_from_options(args, args.checkpoint, "teleop") if args.shared else None
    from pydrake.geometry import StartMeshcat

    from ditch_drake.demos.collect import record_person_demonstration
    from ditch_drake.demos.store import DatasetStore

    store = DatasetStore.create(args.out)  # A bad --out fails before a person drives.
    meshcat = StartMeshcat()
    if shared is None:
        print(f"meshcat: open {meshcat.web_url()} and steer with the arrow keys (or a gamepad) in that tab", flush=True)
    else:
        print(f"meshcat: open {meshcat.web_url()}; the policy drives, and where it is unsure the page turns red and "
              "you steer with the arrow keys (or a gamepad) in that tab", flush=True)
    demonstration = record_person_demonstration(args.env, args.task, meshcat, args.seed, args.realtime_rate,
                                                args.environments or "", shared)
    status = demonstration.metadata["outcome"]["status"]
    if shared is not None:
        print(f"outcome: {status}; you drove {demonstration.metadata['intervened_steps']} of {len(demonstration)} "
              f"steps ({demonstration.metadata['switches']} switches); saved {store.append(demonstration).path}")
        return 0 if status == "reached_goal" else 1
    if status != "reached_goal":
        print(f"outcome: {status}; not kept")
        return 1
    print(f"outcome: reached_goal; saved {store.append(demonstration).path}")
    return 0


def add_replay(commands: Commands) -> None:
    replay = commands.add("replay", "record one rollout as a standalone HTML page (meshcat animation)",
                          with_environments=True)
    add_scenario(replay, "learned")
    add_out(replay, "the HTML page to write", default=ConfigDefault("ditch_drake.diagrams.replay:ReplayConfig", "out"))
    replay.set_defaults(run=cmd_replay)


def cmd_replay(args) -> int:
    """One seeded rollout recorded as a standalone HTML page (opens offline in any browser)."""
    from ditch_drake.common.errors import ConfigError

    if args.time_limit is not None and not args.time_limit > 0:
        raise ConfigError(f"--time-limit {args.time_limit}: expected a positive episode timeout in s")
    if args.seed is not None:
        check_seed(args.seed)
    scenario = scenario_from_options(args)
    from ditch_drake.diagrams.replay import ReplayConfig, record_replay

    label = _controller_label(scenario, args.controller)
    config = ReplayConfig(rollout=scenario.rollout_config(), seed=scenario.seed, out=args.out)
    try:
        result = record_replay(config, progress=label.split(" ")[0])
    except OSError as error:  # An unwritable output (ReplayOutputError) or no such checkpoint file.
        print(f"ditch-drake: error: {error}", file=sys.stderr)
        return 2
    outcome = result.outcome
    print(f"{label} in {scenario.environment} task {scenario.task} seed {scenario.seed}: {outcome.status} after "
          f"{outcome.time_s:.1f} s, {outcome.path_length_m:.1f} m; wrote {result.html_path} "
          f"({result.html_bytes / 2**20:.1f} MiB, {result.snapshots} lidar snapshots)")
    return 0


def _controller_label(scenario, name: str | None = None) -> str:
    """The controller's registered name (the one asked for, where several share a config type)."""
    from ditch_drake.diagrams.controllers import entry_for_config

    name = name or entry_for_config(scenario.controller).name
    checkpoint = getattr(scenario.controller, "checkpoint", None)
    return name if checkpoint is None else f"{name} ({checkpoint})"
