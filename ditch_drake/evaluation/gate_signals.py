"""The learned policy's uncertainty on its own rollouts: every signal its checkpoint has, at
every control step, with each episode's outcome (`ditch-drake gate-signals`).

The policy drives, ungated (the `learned` controller), and `SignalWatch`, a `RunEpisode` watch
called once per control step, reads its block's inputs and decision: it runs the block's own
`decide` on the stacks the block read (they do not change between its tick and the next
stacker tick), so it gets every member's probabilities, checks that the label is the one the
block chose, and evaluates every signal of `ditch_drake.learning.uncertainty` the checkpoint
has (all three for an ensemble, "mean_softmax_entropy" for a single clone) on them. The extra
forward pass per step is the price of not changing the policy block's ports. It also counts the
reversals of the policy's commanded turn over the last second ("command_reversals",
`ditch_drake.systems.command_reversals`), from the commands it has seen: the count that block
gives a gate at the same step; and the seconds since the robot last came nearer its goal
("seconds_without_progress", `ditch_drake.systems.goal_progress`), and the most it has fallen
back from the goal since ("metres_regressed"), from the distances to the goal the policy read:
the counts that block gives a gate. With `risk`, the
diagram also has a "tip_risk" block (`ditch_drake.systems.tip_risk`), and the watch records its
two signals, minus the tip margin now and along the commanded arc, at the same steps.

A recording of many episodes takes long, so each episode is kept as it finishes
(`EpisodeParts`): an interrupted recording keeps its finished episodes and the same command
continues it; the signals file is assembled from them in the order of the runs, so a resumed
recording's file equals one made without a stop.

Worker processes (`workers` > 0) each run (environment, task) pairs, one diagram per pair, and
a process's memory grows by tens of MB with every diagram it has built and dropped (on Drake
1.51, a diagram holding a LeafSystem written in Python is never freed, not even by
`gc.collect()`). So the pairs run in chunks of workers x `PAIRS_PER_WORKER`,
each chunk in a fresh pool, as `ditch_drake.evaluation.batch` does for rollouts.
"""

import hashlib
import json
import math
import os
import re
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ditch_drake.common.errors import ConfigError
from ditch_drake.common.files import atomic_output, remove_stale_temporaries
from ditch_drake.common.parallel import WorkerPool, check_workers, deferred_interrupts
from ditch_drake.common.progress import log_progress
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import LearnedPolicyConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.learning.uncertainty import (
    DISAGREEMENT_SIGNALS,
    PROGRESS_SIGNAL,
    REGRESS_SIGNAL,
    REVERSAL_SIGNAL,
    RISK_SIGNALS,
    UNCERTAINTY_SIGNALS,
)
from ditch_drake.spec.schedule import ScheduleConfig
from ditch_drake.systems.command_reversals import REVERSAL_WINDOW_STEPS, count_reversals
from ditch_drake.systems.episode_monitor import EpisodeConfig
from ditch_drake.systems.goal_progress import Progress, progress_step
from ditch_drake.systems.policy import LearnedPolicy
from ditch_drake.systems.tip_risk import TipRisk, TipRiskConfig

# The policy block's observation inputs, in `LearnedPolicy.decide`'s order.
STACK_PORTS = ("image_stack", "imu_stack", "distance_stack", "bearing_stack")
# About how many (environment, task) pairs, each its own diagram, a worker process records
# before a fresh pool replaces it (see the module docstring).
PAIRS_PER_WORKER = 25


def supported_signals(members: int) -> list[str]:
    """The signals a policy of `members` clones has: the disagreement ones need two or more."""
    return [name for name in UNCERTAINTY_SIGNALS if members >= 2 or name not in DISAGREEMENT_SIGNALS]


class SignalWatch:
    """Records every signal at each of the policy's decisions; a `RunEpisode` watch.

    Called with the root Context at the end of each control period (`watch_period_s` = the
    control period), when the policy's latest tick is `offset_s` into the period just ended.
    A tick already recorded (an episode that ended mid-period) is not recorded twice; before
    the policy's first tick nothing is. With `tip_risk` (the diagram's `TipRisk` block on the
    policy's command), its signals are recorded too.
    """

    def __init__(self, policy: LearnedPolicy, schedule: ScheduleConfig, tip_risk: TipRisk | None = None):
        self._policy = policy
        self._tip_risk = tip_risk
        self._period_s = schedule.control_period_s
        self._offset_s = schedule.controller_offset_s
        self._uncertainty = supported_signals(policy.members)
        self._risk = list(RISK_SIGNALS) if tip_risk is not None else []
        self.signals = self._uncertainty + [REVERSAL_SIGNAL, PROGRESS_SIGNAL, REGRESS_SIGNAL] + self._risk
        self._rates = policy.action_commands[:, 1]
        self._commanded_rates: list[float] = []
        self._progress = Progress()
        self.time_s: list[float] = []
        self.values: dict[str, list[float]] = {name: [] for name in self.signals}

    def __call__(self, root_context) -> bool:
        context = self._policy.GetMyContextFromRoot(root_context)
        label = int(self._policy.GetOutputPort("label").Eval(context)[0])
        tick_s = self._offset_s + math.floor((root_context.get_time() - self._offset_s) / self._period_s + 1e-9) * (
            self._period_s)
        if label < 0 or tick_s < 0 or (self.time_s and tick_s <= self.time_s[-1] + 1e-9):
            return False
        stacks = [self._policy.GetInputPort(name).Eval(context) for name in STACK_PORTS]
        side = (float(self._policy.GetInputPort("crossing_side").Eval(context)[0])
                if self._policy.HasInputPort("crossing_side") else 1.0)
        decision = self._policy.decide(*stacks, crossing_side=side)
        if decision.label != label:
            raise RuntimeError(f"the policy chose label {label} at {tick_s:.3f} s but its inputs now give "
                               f"{decision.label}: the watch does not see what the policy saw")
        self.time_s.append(tick_s)
        for name in self._uncertainty:
            self.values[name].append(float(UNCERTAINTY_SIGNALS[name](decision.member_probabilities, self._rates)))
        self._commanded_rates.append(float(self._policy.GetOutputPort("command").Eval(context)[1]))
        self.values[REVERSAL_SIGNAL].append(float(count_reversals(self._commanded_rates[-REVERSAL_WINDOW_STEPS:])))
        distance_m = float(stacks[STACK_PORTS.index("distance_stack")][0])  # This step's, newest first.
        self._progress = progress_step(self._progress, distance_m, self._period_s)
        self.values[PROGRESS_SIGNAL].append(self._progress.stalled_s)
        self.values[REGRESS_SIGNAL].append(self._progress.regressed_m)
        if self._risk:
            risk_context = self._tip_risk.GetMyContextFromRoot(root_context)
            for name in self._risk:
                self.values[name].append(float(self._tip_risk.GetOutputPort(name).Eval(risk_context)[0]))
        return False


@dataclass
class EpisodeSignals:
    """One episode of `record_gate_signals`: which one, how it ended, and every signal at each of
    its control steps."""

    environment: str
    task: int
    seed: int
    status: str
    end_time_s: float
    time_s: list[float]
    values: dict[str, list[float]]

    @property
    def key(self) -> tuple[str, int, int]:
        return self.environment, self.task, self.seed


@dataclass
class GateSignals:
    """What `record_gate_signals` recorded: the arrays of a signals file
    (`ditch_drake.learning.gate_calibration.save_signals`)."""

    signals: dict[str, list[float]] = field(default_factory=dict)
    steps: dict[str, list] = field(default_factory=lambda: {"time_s": [], "episode": []})
    episodes: dict[str, list] = field(default_factory=lambda: {
        "episode_environment": [], "episode_task": [], "episode_seed": [], "episode_status": [],
        "episode_end_time_s": []})

    @classmethod
    def of(cls, episodes: list[EpisodeSignals]) -> "GateSignals":
        """The episodes' steps one after another, episode i's steps with index i."""
        recorded = cls()
        for index, episode in enumerate(episodes):
            for name, values in episode.values.items():
                recorded.signals.setdefault(name, []).extend(values)
            recorded.steps["time_s"].extend(episode.time_s)
            recorded.steps["episode"].extend([index] * len(episode.time_s))
            for key, value in (("episode_environment", episode.environment), ("episode_task", episode.task),
                               ("episode_seed", episode.seed), ("episode_status", episode.status),
                               ("episode_end_time_s", episode.end_time_s)):
                recorded.episodes[key].append(value)
        return recorded


# The schema of an `EpisodeParts` folder's header.
PARTS_SCHEMA = "ditch_drake.gate_signals.parts"
PARTS_VERSION = 4  # 2: every episode has "command_reversals"; 3: "seconds_without_progress"; 4: "metres_regressed".
PARTS_HEADER = "header.json"


def parts_folder(out: str | os.PathLike) -> Path:
    """Where the episodes of the signals file `out` are kept while it is recorded: `<out>.parts`."""
    return Path(f"{out}.parts")


def parts_header(checkpoint_sha256: str, time_limit_s: float, environments_file: str = "",
                 risk: bool = False, risk_horizon_s: float = TipRiskConfig.horizon_s) -> dict:
    """What every episode of a recording depends on besides its (environment, task, seed): a
    recording continues only with the same (`EpisodeParts.open`). The tip risk's horizon is
    named only where it is not the default, so that a recording begun before it could be set
    continues."""
    environments = Path(environments_file).resolve() if environments_file else None
    horizon = {"risk_horizon_s": float(risk_horizon_s)} if risk and risk_horizon_s != TipRiskConfig.horizon_s else {}
    return {"schema": PARTS_SCHEMA, "version": PARTS_VERSION, "checkpoint_sha256": checkpoint_sha256,
            "time_limit_s": float(time_limit_s), "environments_file": str(environments or ""),
            "environments_file_sha256": hashlib.sha256(environments.read_bytes()).hexdigest() if environments else "",
            "risk": bool(risk), **horizon}


class EpisodeParts:
    """The finished episodes of one recording, a file each in a folder (`parts_folder`).

    `header.json` (`parts_header`), written first, says what the episodes were recorded with; a
    rerun with another checkpoint or other settings is refused rather than mixed with them. Each
    episode is `<environment>.task<T>.seed<S>.npz`, written atomically as it finishes: one .npz
    a file keeps its floats bit for bit, and a stop can tear nothing (an append-only log would
    need its torn last line found and cut). Removing the folder removes the header first, so a
    half-removed folder is never taken for a recording in progress.
    """

    def __init__(self, folder: Path, header: dict):
        self.folder = folder
        self.header = header

    @staticmethod
    def begun(folder: str | os.PathLike) -> bool:
        """Whether `folder` holds a recording in progress (its header)."""
        return (Path(folder) / PARTS_HEADER).is_file()

    @classmethod
    def open(cls, folder: str | os.PathLike, header: dict) -> "EpisodeParts":
        """The recording in `folder`: begun here with `header`, or continued where its header is the same.

        Raises:
            ConfigError: the folder's header is unreadable or differs from `header`, naming what differs.
        """
        folder = Path(folder)
        path = folder / PARTS_HEADER
        if not path.is_file():
            folder.mkdir(parents=True, exist_ok=True)
            for leftover in folder.glob("*.npz"):  # Of a removal cut short: not this recording's.
                leftover.unlink()
            with atomic_output(path) as file:
                file.write((json.dumps(header, indent=1) + "\n").encode())
            return cls(folder, header)
        try:
            found = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise ConfigError(f"{path} is unreadable ({error}); expected the header of a gate-signals recording "
                              f"(delete {folder} to start afresh)") from error
        if found.get("version") != header["version"]:
            raise ConfigError(f"{folder} holds the episodes of a recording begun by another version of ditch-drake "
                              f"(parts version {found.get('version')!r} there, {header['version']!r} now: its "
                              f"episodes lack signals this one records); expected a folder of this version: delete "
                              f"{folder} to start afresh")
        differ = [f"{key} {found.get(key)!r} there, {value!r} now" for key, value in header.items()
                  if found.get(key) != value]
        if differ:
            raise ConfigError(f"{folder} holds the episodes of a recording with other settings ({'; '.join(differ)}); "
                              "expected the checkpoint, --time-limit and --environments of the run that began it, "
                              f"or delete {folder} to start afresh")
        remove_stale_temporaries(folder)
        return cls(folder, header)

    def path(self, key: tuple[str, int, int]) -> Path:
        environment, task, seed = key
        name = re.sub(r"[^A-Za-z0-9_-]+", "_", environment)
        if name != environment:  # Two names that read the same once cleaned keep files of their own.
            name += "-" + hashlib.sha256(environment.encode()).hexdigest()[:8]
        return self.folder / f"{name}.task{task}.seed{seed}.npz"

    def finished(self, key: tuple[str, int, int]) -> EpisodeSignals | None:
        """The episode kept under `key`, or None where there is none (or an unreadable one, run again)."""
        try:
            with np.load(self.path(key), allow_pickle=False) as data:
                episode = EpisodeSignals(
                    str(data["environment"]), int(data["task"]), int(data["seed"]), str(data["status"]),
                    float(data["end_time_s"]), data["time_s"].tolist(),
                    {str(name): data[f"signal_{name}"].tolist() for name in data["signals"]})
        except (OSError, ValueError, KeyError):
            return None
        return episode if episode.key == key else None

    def keep(self, episode: EpisodeSignals) -> None:
        """Writes `episode`'s file atomically."""
        with atomic_output(self.path(episode.key)) as file:
            np.savez(file, environment=np.array(episode.environment), task=np.array(episode.task),
                     seed=np.array(episode.seed, dtype=np.int64), status=np.array(episode.status),
                     end_time_s=np.array(float(episode.end_time_s)),
                     time_s=np.asarray(episode.time_s, dtype=float), signals=np.array(list(episode.values), dtype=str),
                     **{f"signal_{name}": np.asarray(values, dtype=float) for name, values in episode.values.items()})

    def remove(self) -> None:
        """Removes the folder, once the signals file holds its episodes."""
        (self.folder / PARTS_HEADER).unlink(missing_ok=True)
        shutil.rmtree(self.folder, ignore_errors=True)


def record_gate_signals(checkpoint: str, runs: list[tuple[str, int]], rollouts: int = 10, seed: int = 0,
                        time_limit_s: float = EpisodeConfig.time_limit_s, environments_file: str = "",
                        progress: bool = True, parts: EpisodeParts | None = None, risk: bool = False,
                        workers: int = 0, risk_horizon_s: float = TipRiskConfig.horizon_s) -> GateSignals:
    """Runs `rollouts` episodes (seeds seed ..) of the learned policy of `checkpoint` on each
    (environment, task) of `runs`, ungated, and records every signal it has at every control step;
    with `risk`, the tip-risk signals too (`ditch_drake.systems.tip_risk`), the commanded arc
    held for `risk_horizon_s`.

    The episodes are in the order of `runs` and, within one, of their seeds; an (environment,
    task, seed) is run once however often `runs` repeats it. With `parts`, each episode is kept
    there as it finishes and one kept before is not run again; Ctrl-C (KeyboardInterrupt) then
    keeps every finished episode, and is re-raised. `progress`: a line on stderr per finished
    episode (k/N, which one, how it ended), beside `RunEpisode`'s bar of simulated time.
    `workers` > 0 (with `parts`): that many worker processes run the (environment, task)
    pairs, one thread each, and keep their episodes in `parts`; the signals are the same as
    in this process, episode for episode (each episode's seed, not its process, sets it).

    Raises:
        ConfigError: a bad environment, task or time limit, or `workers` without `parts`.
        CheckpointError: the checkpoint does not load.
    """
    from pydrake.systems.analysis import Simulator

    keys = list(dict.fromkeys((environment, task, episode_seed) for environment, task in runs
                              for episode_seed in range(seed, seed + rollouts)))
    finished = {key: parts.finished(key) for key in keys} if parts is not None else {}
    episodes = {key: episode for key, episode in finished.items() if episode is not None}
    if episodes:
        log_progress(progress, f"{len(episodes)}/{len(keys)} episodes finished before, kept in {parts.folder}")
    check_workers(workers)
    if workers and parts is None:
        raise ConfigError(f"workers={workers}: recording in worker processes needs a parts folder to keep "
                          "their episodes in; expected parts, or workers=0")
    if workers:
        _record_in_workers(checkpoint, keys, episodes, rollouts, seed, time_limit_s, environments_file, progress,
                           parts, risk, workers, risk_horizon_s)
    for environment, task in dict.fromkeys(runs):
        pending = [key[2] for key in keys if key[:2] == (environment, task) and key not in episodes]
        if not pending:
            continue
        scene = SceneConfig(environment=environment, task=task, environments_file=environments_file,
                            episode=replace(EpisodeConfig(), time_limit_s=time_limit_s))
        controller = LearnedPolicyConfig(checkpoint, tip_risk=TipRiskConfig(horizon_s=risk_horizon_s) if risk else None)
        diagram, built = MakeRolloutDiagram(RolloutConfig(scene=scene, controller=controller))
        policy = diagram.GetSubsystemByName("learned_policy")
        tip_risk = diagram.GetSubsystemByName("tip_risk") if risk else None
        simulator = Simulator(diagram)
        for episode_seed in pending:
            watch = SignalWatch(policy, built.schedule, tip_risk)
            description = f"{environment} task {task} seed {episode_seed}" if progress else None
            outcome = RunEpisode(simulator, diagram, built, episode_seed, progress=description, watch=watch,
                                 watch_period_s=built.schedule.control_period_s)
            episode = EpisodeSignals(environment, task, episode_seed, outcome.status, outcome.time_s, watch.time_s,
                                     watch.values)
            with deferred_interrupts():  # A stop lands before the episode is kept or after, never within.
                if parts is not None:
                    parts.keep(episode)
                episodes[episode.key] = episode
            log_progress(progress, f"episode {len(episodes)}/{len(keys)}: {environment} task {task} seed "
                                   f"{episode_seed}: {outcome.status} at {outcome.time_s:.1f} s, "
                                   f"{len(watch.time_s)} steps")
    return GateSignals.of([episodes[key] for key in keys])


def _record_pair(checkpoint: str, environment: str, task: int, rollouts: int, seed: int, time_limit_s: float,
                 environments_file: str, folder: str, header: dict, risk: bool,
                 risk_horizon_s: float) -> list[EpisodeSignals]:
    """A worker's share of `record_gate_signals`: the episodes of one (environment, task), in
    one diagram, each kept in the parts folder as it finishes (one kept before is not run again)."""
    # Not `EpisodeParts.open`: it clears stale temporaries, which may be another worker's file in writing.
    parts = EpisodeParts(Path(folder), header)
    record_gate_signals(checkpoint, [(environment, task)], rollouts, seed, time_limit_s, environments_file,
                        progress=False, parts=parts, risk=risk, risk_horizon_s=risk_horizon_s)
    return [parts.finished((environment, task, episode_seed)) for episode_seed in range(seed, seed + rollouts)]


def _record_in_workers(checkpoint: str, keys: list[tuple[str, int, int]], episodes: dict, rollouts: int, seed: int,
                       time_limit_s: float, environments_file: str, progress: bool, parts: EpisodeParts, risk: bool,
                       workers: int, risk_horizon_s: float) -> None:
    """Runs the episodes of `keys` not in `episodes` in `workers` processes, an (environment,
    task) pair per work item, and adds each to `episodes` as its item ends; a fresh pool per
    workers x `PAIRS_PER_WORKER` pairs (the module docstring)."""
    from concurrent.futures import as_completed

    from ditch_drake.evaluation.rollout_worker import initialize_worker

    pending = list(dict.fromkeys(key[:2] for key in keys if key not in episodes))
    chunk = workers * PAIRS_PER_WORKER
    for begin in range(0, len(pending), chunk):
        pairs = pending[begin:begin + chunk]
        with WorkerPool(min(workers, len(pairs)), initializer=initialize_worker) as pool:
            futures = [pool.submit(_record_pair, checkpoint, environment, task, rollouts, seed, time_limit_s,
                                   environments_file, str(parts.folder), parts.header, risk, risk_horizon_s)
                       for environment, task in pairs]
            for future in as_completed(futures):
                for episode in future.result():
                    if episode.key in episodes:  # Kept before this run.
                        continue
                    episodes[episode.key] = episode
                    log_progress(progress, f"episode {len(episodes)}/{len(keys)}: {episode.environment} task "
                                           f"{episode.task} seed {episode.seed}: {episode.status} at "
                                           f"{episode.end_time_s:.1f} s, {len(episode.time_s)} steps")


def write_signals_file(out: str | os.PathLike, checkpoint: str, checkpoint_sha256: str, runs: list[tuple[str, int]],
                       rollouts: int, seed: int, time_limit_s: float, environments_file: str = "",
                       horizon_s: float | None = None, progress: bool = True,
                       risk: bool = False, workers: int = 0,
                       risk_horizon_s: float = TipRiskConfig.horizon_s) -> tuple[GateSignals, dict]:
    """Records `checkpoint`'s signals (`record_gate_signals`) episode by episode into the parts
    folder beside `out` (continuing what it holds), then writes the signals file `out` and its
    AUC report (`<out>.auc.json`, a rollover within `horizon_s`; None: the default horizon), and
    removes the folder. The caller holds `out` (`exclusive_use`). Ctrl-C keeps the finished
    episodes in the folder and is re-raised. `risk`: the tip-risk signals too, on arcs of
    `risk_horizon_s` (the file says which). `workers`: worker processes (0: this one), as
    `record_gate_signals`.

    Returns:
        The recorded signals and the AUC report.

    Raises:
        ConfigError: the parts folder holds a recording with another checkpoint, time limit or
            environments file.
    """
    from ditch_drake.learning.gate_calibration import auc_report, load_signals, save_signals, write_auc_report

    folder = parts_folder(out)
    parts = EpisodeParts.open(folder, parts_header(checkpoint_sha256, time_limit_s, environments_file, risk,
                                                   risk_horizon_s))
    recorded = record_gate_signals(checkpoint, runs, rollouts, seed, time_limit_s, environments_file, progress,
                                   parts=parts, risk=risk, workers=workers, risk_horizon_s=risk_horizon_s)
    save_signals(out, checkpoint, checkpoint_sha256, recorded.signals, recorded.steps, recorded.episodes,
                 tip_risk_horizon_s=risk_horizon_s if risk else None)
    horizon = {} if horizon_s is None else {"horizon_s": horizon_s}
    report = auc_report(load_signals(out), seed=seed, **horizon)
    write_auc_report(Path(out).with_suffix(".auc.json"), report)
    parts.remove()
    return recorded, report
