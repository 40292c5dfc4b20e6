"""The shared controller's options, for the commands that record with it: teleop and collect."""

import argparse

from ditch_drake.cli.options import ConfigDefault

SHARED = "ditch_drake.diagrams.shared_controller:SharedControlControllerConfig"


def add_gate_options(sub: argparse.ArgumentParser, fallbacks: list[str]) -> None:
    """`--signal`, `--upper-threshold`, `--lower-threshold`, `--calm-steps`, `--budget`,
    `--calibration`, `--progress-limit`, `--regress-limit` and `--fallback`:
    the gate of `SharedControlControllerConfig` (defaults its own: the shipped clones' gate)."""
    from ditch_drake.learning.uncertainty import GATE_SIGNALS

    gate = sub.add_argument_group("the gate (with --shared)")
    gate.add_argument("--signal", choices=list(GATE_SIGNALS), default=ConfigDefault(SHARED, "gate.signal"),
                      help="the policy's uncertainty signal the gate reads, or random: a uniform draw in [0, 1) "
                           "each step, the chance baseline (thresholds then in [0, 1]) (default %(default)s)")
    gate.add_argument("--upper-threshold", type=float, default=ConfigDefault(SHARED, "gate.upper_threshold"),
                      help="hand over when the signal is above this, in its unit (default %(default)s)")
    gate.add_argument("--lower-threshold", type=float, default=ConfigDefault(SHARED, "gate.lower_threshold"),
                      help="hand back after the signal stayed below this for --calm-steps steps "
                           "(default %(default)s)")
    gate.add_argument("--calm-steps", type=int, default=ConfigDefault(SHARED, "gate.calm_steps"),
                      help="control steps below the lower threshold before handing back (default %(default)s)")
    gate.add_argument("--budget", type=float, default=None,
                      help="the share of control steps the fallback may drive, in (0, 1): both thresholds then "
                           "come from --calibration, the gated policy's own validation rollouts (in place of "
                           "--upper-threshold and --lower-threshold; with --signal random, from no file)")
    gate.add_argument("--calibration", default="", metavar="SIGNALS_NPZ",
                      help="with --budget: the signals file of `ditch-drake gate-signals` for the gated policy "
                           "(with --risk for a risk signal)")
    gate.add_argument("--progress-limit", type=float, default=None, metavar="S",
                      help="a watchdog beside the signal: also hand over once the robot has come no nearer its "
                           "goal for more than S seconds, until it is nearer than before (default: none)")
    gate.add_argument("--regress-limit", type=float, default=None, metavar="M",
                      help="a watchdog beside the signal: also hand over once the robot has fallen back more "
                           "than M metres from the goal since it last came nearer, until it is nearer than "
                           "before (default: none)")
    if len(fallbacks) > 1:
        gate.add_argument("--fallback", choices=fallbacks, default=fallbacks[0],
                          help="who takes over where the policy is unsure (default %(default)s)")


def shared_config_from_options(args, checkpoint: str | None, fallback: str | None = None):
    """The `SharedControlControllerConfig` of the gate options and `checkpoint` (None or "":
    the config's default policy, the shipped generalist ensemble), with `fallback` (None:
    `--fallback`).

    Raises:
        ConfigError: a bad gate value, naming it (`SharedControlConfig.validate`).
    """
    import dataclasses

    from ditch_drake.diagrams.shared_controller import SharedControlControllerConfig

    config = SharedControlControllerConfig()
    if checkpoint:
        config = config.with_checkpoint(checkpoint)
    gate = dataclasses.replace(config.gate, signal=args.signal, upper_threshold=args.upper_threshold,
                               lower_threshold=args.lower_threshold, calm_steps=args.calm_steps,
                               fallback=fallback or args.fallback, budget=args.budget,
                               calibration=args.calibration, progress_limit_s=args.progress_limit,
                               regress_limit_m=args.regress_limit)
    gate.validate()
    if gate.budget is not None:
        gate.resolved()
    return dataclasses.replace(config, gate=gate)
