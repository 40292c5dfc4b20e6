"""The generalist policy: behavioural cloning over the train split, DAgger, chosen on val.

    ditch-drake train-generalist --out ditch_drake/models/generalist.pt

Stages, each skipping what an earlier run finished (so the command resumes):

1. the train split's first `train_geometries` ditches, drawn from `train_ranges` (the benchmark's
   ranges, with craters from 8 m across as the paper's crater), written to
   `<work>/train.ditches.yaml`;
2. expert demonstrations, `demos_per_task` per task of each (`<work>/demos`), the expert making
   room along the ditch first as in the benchmark (`ExpertVariation.lead_in`);
3. round 0: a clone of those (`<work>/round0.pt`);
4. each DAgger round r: the previous round's clone drives once per task, the expert labels
   what it sees (`<work>/dagger<r>`), and a clone of everything so far (`<work>/round<r>.pt`);
   with `mirror`, every clone also learns from the left-right reflection of each rollout
   whose crossing turns clearly to one side (`GeneralistConfig.mirror`); with
   `canonical_side`, every step whose crossing turns left along the edge is reflected, and
   the clone is told the side to cross on (`GeneralistConfig.canonical_side`);
5. every round's clone runs the val split's first `val_geometries` ditches
   (`<work>/val.jsonl`); the most successful (the later round on a tie) is copied to `out`;
6. with `ensemble` K, K clones of the chosen round's data, each on a bootstrap resample of its
   demonstrations and DAgger rollouts (as `ditch-drake train --ensemble`), in `<work>/ensemble.pt`:
   the gated policy of the `shared` controller.

A work dir records the settings that shape its data and rounds (`recipe.json`: the train
ranges, demonstrations per task, DAgger stride, mirror, canonical side, seed, class balancing)
and refuses to be resumed with others. The test split plays no part.
"""

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ditch_drake.benchmark.ranges import BenchmarkRanges, load_ranges, packaged_ranges_path
from ditch_drake.benchmark.run import BenchmarkConfig, run_benchmark
from ditch_drake.benchmark.splits import split_ditches, write_ditches
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.files import atomic_write_bytes, atomic_write_text, prepare_output, remove_stale_temporaries
from ditch_drake.common.progress import log_progress
from ditch_drake.common.ray_tasks import check_backend
from ditch_drake.evaluation.batch import load_results
from ditch_drake.evaluation.results import current_records
from ditch_drake.learning.bootstrap import MIN_MEMBERS
from ditch_drake.pipelines.stages import (
    collect_demonstrations,
    ensemble_or_resume,
    pass_on_stop,
    train_or_resume,
    training_device,
    training_precision,
)
from ditch_drake.world.crossing import crossing_sides, crossing_turn_deg
from ditch_drake.world.environments import load_environments
from ditch_drake.world.terrain import DitchTerrain

# DAgger rollouts use seeds from here on, apart from the demonstrations' (whose failed
# attempts use seed + 1000 k).
DAGGER_SEED = 50_000
# A reflected rollout's task turns at least this much more than the expert's convention
# (`straight_across_deg`) from square: near that limit the side it chose on the approach, from
# where the robot was, can still be the convention's.
MIRROR_MARGIN_DEG = 5.0
# The packaged ranges of the train ditches (`GeneralistConfig.train_ranges`).
GENERALIST_TRAIN_RANGES = "generalist_train_ranges.yaml"
# The settings a work dir's demonstrations and rounds were made with (`_check_recipe`).
RECIPE_FILE = "recipe.json"
# What a work dir's recipe made before a setting was recorded was made with.
_RECIPE_BEFORE = {"balancing": "smote"}
# The ensemble of the chosen round's data, in the work dir (`GeneralistConfig.ensemble`).
ENSEMBLE_FILE = "ensemble.pt"


@dataclass
class GeneralistConfig:
    """What `train_generalist` does (see the module docstring).

    Attributes:
        out: where the chosen checkpoint is copied ("": `<work_dir>/generalist.pt`). Not the
            shipped `ditch_drake/models/generalist.pt` by default: a run replaces that only
            when asked to, after its val scores were looked at.
        work_dir: demonstrations, each round's checkpoint and the val results.
        train_geometries: the train split's first N ditches.
        demos_per_task: expert demonstrations per task of each.
        dagger_rounds: DAgger rounds after round 0.
        val_geometries: the val split's first N ditches each candidate runs (one rollout per task).
        dagger_stride: train on every k-th control step of the DAgger rollouts. A round of 120
            learner rollouts, many of them timeouts circling for 120 s, holds about 80 k steps
            of which many are alike; the stride was chosen when the samples were held in memory
            (all of them beside the demonstrations' 52 k ran out of 24 GiB) and is kept so that
            the recipe, and its rounds, stay as they were. Streaming from the dataset folders,
            memory no longer depends on it.
        epochs, patience: training's.
        balancing: training's class balancing (`TrainConfig.balancing`; random oversampling
            by default, as `ditch-drake train`; the shipped generalist was trained with SMOTE,
            `--balancing smote`). Every round after the first is collected by the round before
            it, so a work dir keeps one (`recipe.json`).
        mirror: also train on the left-right reflection (`ditch_drake.learning.mirror`) of each
            demonstration and DAgger rollout whose task turns at least the expert's
            `straight_across_deg` + `MIRROR_MARGIN_DEG` from square across
            (`ditch_drake.world.crossing`). There the expert turns toward the goal's side, a
            rule the reflection keeps; nearer square it turns right by convention, whose
            reflection would teach the opposite answer to the same view. Without it, left
            turns along the edge are the rare ones (the convention's crossings all turn right).
        canonical_side: train in one side's frame: every step whose side along the edge
            (`ditch_drake.world.crossing.crossing_sides` along the recorded path, with the
            driver's own approach margin and convention) is left is reflected, so the clone
            learns only crossings turned right, and it is told the side when it drives
            (`ModelConfig.canonical_side`; `PerceivedCrossingSide` finds it in the lidar's rays,
            `OracleCrossingSide` reads it off the ditch's course). Which side is then not the
            clone's choice but a command, as a route planner's turn command conditions a
            driving policy; the paper's clone has no such input. Not with `mirror`.
        seed: seeds the demonstrations, training and the val rollouts.
        ensemble: 0, or K >= 2: after the choice, train K clones on the chosen round's data
            (`<work_dir>/ensemble.pt`), member k on a bootstrap resample of its demonstrations
            and DAgger rollouts (whole rollouts, with their reflections) with seed `seed` + k,
            under the recipe's training settings (`ditch_drake.learning.ensemble_training`;
            resumed member by member).
        workers: processes for collection and evaluation (None: one per core).
        ranges: the val split's ranges YAML file ("": the benchmark's, `ranges.yaml`).
        train_ranges: the train ditches' ranges YAML file ("": `generalist_train_ranges.yaml`).
        backend, address: where the collection rounds and the val rollouts run: "local" (process
            pools on this machine) or "ray" (a Ray cluster at `address`; None or "local" starts
            Ray here), as for `collect` and `evaluate`, which write what the tasks return
            into the work dir here. Training stays in this process: on a cluster, run the
            whole command on the node with the GPU.
    """

    out: str = ""
    work_dir: str = "data/generalist"
    train_geometries: int = 40
    demos_per_task: int = 1
    dagger_rounds: int = 4
    val_geometries: int = 25
    dagger_stride: int = 3
    epochs: int = 12
    patience: int = 6
    balancing: str = "oversample"
    mirror: bool = False
    canonical_side: bool = False
    seed: int = 0
    ensemble: int = 0
    workers: int | None = None
    ranges: str = ""
    train_ranges: str = ""
    backend: str = "local"
    address: str | None = None


def _collect(config: GeneralistConfig, names: list[str], ditches: str, out: Path, learner: str | None,
             seed: int, progress: bool) -> None:
    from ditch_drake.demos.collect import LABELLER_VARIATION, CollectConfig
    from ditch_drake.systems.expert import ExpertVariation

    variation = replace(LABELLER_VARIATION if learner else ExpertVariation(), lead_in=True)
    collect_demonstrations(CollectConfig(environment=names[0], environments=names, environments_file=ditches,
                                         demos=len(names) * 3 * (1 if learner else config.demos_per_task),
                                         seed=seed, out=str(out), workers=config.workers, variation=variation,
                                         learner=learner, backend=config.backend, address=config.address),
                           str(out), progress)


def _training_entries(config: GeneralistConfig, data: list[Path], ditches: str):
    """The training entries of the demonstrations of data[0] and every dagger_stride-th step of
    the rest: each episode (followed by its reflection where `config.mirror` asks for one), its
    stride, its reflect flags (reflected where it crosses turned left with
    `config.canonical_side`), the index of the demonstration it comes from, and each
    demonstration's name (`<directory>[<index>]`, as an ensemble's bootstrap names them)."""
    from ditch_drake.demos.training_set import dataset_episodes

    environments = dict(load_environments(ditches, prove_walls=False)) if (
        config.mirror or config.canonical_side) else {}
    episodes, strides, reflect, demonstration, names = [], [], [], [], []
    for index, directory in enumerate(data):
        stride = 1 if index == 0 else config.dagger_stride
        for position, episode in enumerate(dataset_episodes(directory)):
            names.append(f"{directory}[{position}]")
            episodes.append(episode)
            strides.append(stride)
            demonstration.append(len(names) - 1)
            if config.canonical_side:
                pose = episode.read(["pose"])["pose"]
                reflect.append(_crossing_sides(episode.metadata, pose, environments)[::stride] < 0.0)
            else:
                reflect.append(False)
            if config.mirror and _turns_clearly(episode.metadata, environments):
                episodes.append(episode)
                strides.append(stride)
                reflect.append(True)
                demonstration.append(len(names) - 1)
    return TrainingEntries(episodes, strides, reflect, np.asarray(demonstration, dtype=np.int64), names)


@dataclass
class TrainingEntries:
    """`_training_entries`'s lists, entry i of each belonging together."""

    episodes: list
    strides: list[int]
    reflect: list
    demonstration: np.ndarray
    names: list[str]

    def samples(self, demonstrations: np.ndarray | None = None):
        """The training `ArraySet` of every entry, demo_id the entry's index (None), or of the
        given demonstrations' entries, in that order, a demonstration given twice giving its
        samples twice, demo_id the demonstration's position in `demonstrations` (so that a
        reflection is held out for validation with its demonstration)."""
        from ditch_drake.demos.training_set import training_set

        if demonstrations is None:  # As the rounds were always trained: a reflection has an id of its own.
            return training_set(self.episodes, self.strides, self.reflect)
        chosen = [(position, entry) for position, index in enumerate(demonstrations)
                  for entry in np.flatnonzero(self.demonstration == index)]
        arrays = training_set([self.episodes[entry] for _, entry in chosen],
                              [self.strides[entry] for _, entry in chosen],
                              [self.reflect[entry] for _, entry in chosen])
        positions = np.asarray([position for position, _ in chosen], dtype=np.int64)
        return replace(arrays, demo_id=positions[arrays.demo_id])


def _training_samples(config: GeneralistConfig, data: list[Path], ditches: str, progress: bool = False):
    """The demonstrations of data[0] and every dagger_stride-th step of the rest, each followed
    by its reflection where `config.mirror` asks for one, or reflected where it crosses turned
    left with `config.canonical_side`.

    The images of a dataset folder stay on disk and are stacked (and reflected) batch by batch
    as training reads them (`ditch_drake.demos.training_set`); a folder of `.npz` files of the
    older format is loaded into memory (every step's frames: 4.6 GiB for the demonstrations and
    five DAgger rounds here).
    """
    entries = _training_entries(config, data, ditches)
    arrays = entries.samples()
    if config.canonical_side:
        left = int(sum(np.count_nonzero(flags) for flags in entries.reflect))
        log_progress(progress, f"canonical side: {left} of {len(arrays)} samples reflected (their crossings turn left)")
    return arrays


def _crossing_sides(metadata: dict, pose: np.ndarray, environments: dict) -> np.ndarray:
    """The side along the edge (+1 right, -1 left) at each step of a recorded rollout (its
    metadata and (T, 6) poses), by the rule of `OracleCrossingSide` with its driver's approach
    margin and convention."""
    driver = metadata["expert_style"]["driver"]
    environment = environments[metadata["environment"]]
    return crossing_sides(DitchTerrain(environment.terrain), np.asarray(pose)[:, :2],
                          np.asarray(metadata["task"]["goal"], dtype=float), driver["approach_margin_m"],
                          driver["straight_across_deg"])


def _turns_clearly(metadata: dict, environments: dict) -> bool:
    """Whether a rollout's task turns far enough from square that its expert labels turn
    toward the goal's side (`GeneralistConfig.mirror`)."""
    convention_deg = metadata["expert_style"]["driver"]["straight_across_deg"]
    turn = crossing_turn_deg(environments[metadata["environment"]], metadata["task"]["index"])
    return abs(turn) >= convention_deg + MIRROR_MARGIN_DEG


def _train_config(config: GeneralistConfig):
    """Every round's (and ensemble member's) `TrainConfig`."""
    from ditch_drake.learning.config import ModelConfig, TrainConfig

    device = training_device("auto")
    return TrainConfig(epochs=config.epochs, patience=config.patience, seed=config.seed, device=device,
                       balancing=config.balancing, model=ModelConfig(canonical_side=config.canonical_side),
                       precision=training_precision(device))


def _train(config: GeneralistConfig, data: list[Path], ditches: str, out: Path, progress: bool) -> None:
    """Trains on the demonstrations of data[0] and every dagger_stride-th step of the rest
    (and their reflections, `GeneralistConfig.mirror`, or in one side's frame,
    `GeneralistConfig.canonical_side`), in the ditches of the file `ditches`."""
    train_or_resume(out, out.stem, lambda: _training_samples(config, data, ditches, progress), _train_config(config),
                    progress)


def _train_ensemble(config: GeneralistConfig, data: list[Path], ditches: str, out: Path, progress: bool) -> None:
    """Trains `config.ensemble` clones of what `_train` trains on, each on a bootstrap resample of
    its demonstrations and DAgger rollouts, into the ensemble file `out`, unless an earlier run
    finished it (an interrupted one resumes with its finished members kept)."""
    def demonstrations():
        entries = _training_entries(config, data, ditches)
        return entries.samples, entries.names

    ensemble_or_resume(out, "ensemble", demonstrations, _train_config(config), config.ensemble, progress)


def _check_recipe(work: Path, config: GeneralistConfig, train_ranges: BenchmarkRanges) -> None:
    """Refuses to resume a work dir made with other settings, and records them in a new one.

    The stages keep whatever an earlier run finished, so without this a run with another
    `canonical_side` (or ranges, stride, ...) would keep rounds trained the other way, or
    demonstrations of ditches that share a name but not a shape, and choose among them.
    """
    ranges = {f"train_ranges.{name}": value for name, value in asdict(train_ranges).items()}
    recipe = json.loads(json.dumps(ranges | {"demos_per_task": config.demos_per_task, "dagger_stride": config.dagger_stride,
                                             "mirror": config.mirror, "canonical_side": config.canonical_side,
                                             "seed": config.seed, "balancing": config.balancing}))
    path = work / RECIPE_FILE
    if not path.exists():
        atomic_write_text(path, json.dumps(recipe, indent=2) + "\n")
        return
    try:
        made_with = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:  # Unreadable, not UTF-8, or not JSON.
        raise ConfigError(f"{path}: {error}; expected the JSON object of the settings this work dir was made "
                          "with (or pass a fresh --work-dir)") from error
    if not isinstance(made_with, dict):
        raise ConfigError(f"{path} holds a JSON {type(made_with).__name__}; expected the JSON object of the "
                          "settings this work dir was made with (or pass a fresh --work-dir)")
    for name, value in recipe.items():
        expected = made_with.get(name, _RECIPE_BEFORE.get(name))
        if expected != value:
            raise ConfigError(f"{name}={value}: expected {expected}, the setting {work} was made with "
                              f"({path}); pass the same to resume it, or a fresh --work-dir")


def _val_success(results: Path, checkpoint: Path) -> tuple[int, int]:
    records, _ = current_records([r for r in load_results([results]) if r.checkpoint == str(checkpoint)])
    valid = [r for r in records if r.status != "error"]
    return sum(r.success for r in valid), len(valid)


def train_generalist(config: GeneralistConfig, progress: bool = True) -> dict:
    """Runs the stages (module docstring); returns each candidate's val success and the choice.

    Raises:
        ConfigError: counts out of range, a bad ranges file, a work dir or output that cannot
            be written, or a work dir made with other settings or with a damaged `recipe.json`.
        KeyboardInterrupt: Ctrl-C during a stage, or `Terminated` (a KeyboardInterrupt) for
            SIGTERM (what finished is kept).
    """
    for name, lowest in (("dagger_rounds", 0), ("demos_per_task", 1), ("dagger_stride", 1)):
        if getattr(config, name) < lowest:
            raise ConfigError(f"{name}={getattr(config, name)}: expected an integer >= {lowest} "
                              f"(--{name.replace('_', '-')})")
    if config.ensemble != 0 and (isinstance(config.ensemble, bool) or not isinstance(config.ensemble, int)
                                 or config.ensemble < MIN_MEMBERS):
        raise ConfigError(f"ensemble={config.ensemble!r}: expected an integer >= {MIN_MEMBERS} members, or 0 for "
                          "none (--ensemble; an ensemble's uncertainty is its members' disagreement)")
    if config.mirror and config.canonical_side:
        raise ConfigError("mirror and canonical_side: expected at most one (--mirror, --canonical-side); a clone "
                          "that learns only right-turned crossings has no use for their reflections")
    load_ranges(config.ranges or None)  # A bad val ranges file is refused before hours of training, not after.
    check_backend(config.backend, config.address)
    train_ranges = load_ranges(config.train_ranges or packaged_ranges_path(GENERALIST_TRAIN_RANGES))
    work = prepare_output(config.work_dir, "work dir", folder=True)
    remove_stale_temporaries(work)  # A killed run's recipe.json or choice.json half-written.
    out = prepare_output(config.out or work / "generalist.pt", "output checkpoint")
    _check_recipe(work, config, train_ranges)
    ditches = split_ditches("train", config.train_geometries, train_ranges)
    ditches_path = str(write_ditches(work / "train.ditches.yaml", ditches))
    names = [ditch.name for ditch in ditches]
    _collect(config, names, ditches_path, work / "demos", None, config.seed, progress)
    data = [work / "demos"]
    candidates = [work / "round0.pt"]
    _train(config, data, ditches_path, candidates[0], progress)
    for round_index in range(1, config.dagger_rounds + 1):
        dagger = work / f"dagger{round_index}"
        _collect(config, names, ditches_path, dagger, str(candidates[-1]), DAGGER_SEED + 1000 * round_index,
                 progress)
        data.append(dagger)
        candidates.append(work / f"round{round_index}.pt")
        _train(config, data, ditches_path, candidates[-1], progress)
    val_results = work / "val.jsonl"
    scores = {}
    for candidate in candidates:
        report = run_benchmark(BenchmarkConfig(split="val", controller="learned", checkpoint=str(candidate),
                                               geometries=config.val_geometries, rollouts=1, seed=config.seed,
                                               out=str(val_results), ranges=config.ranges, workers=config.workers,
                                               backend=config.backend, address=config.address),
                               progress)
        if report.interrupted:
            pass_on_stop(report.exit_code)
        scores[str(candidate)] = _val_success(val_results, candidate)
        log_progress(progress, f"val {candidate}: {scores[str(candidate)][0]}/{scores[str(candidate)][1]}")
    chosen = max(reversed(candidates), key=lambda c: scores[str(c)][0] / max(scores[str(c)][1], 1))
    atomic_write_bytes(out, chosen.read_bytes())
    summary = {"config": asdict(config), "val_success": {k: list(v) for k, v in scores.items()},
               "chosen": str(chosen), "out": str(out)}
    atomic_write_text(work / "choice.json", json.dumps(summary, indent=2) + "\n")
    if config.ensemble:
        ensemble = work / ENSEMBLE_FILE
        _train_ensemble(config, data[:candidates.index(chosen) + 1], ditches_path, ensemble, progress)
        summary["ensemble"] = str(ensemble)
        atomic_write_text(work / "choice.json", json.dumps(summary, indent=2) + "\n")
    return summary


