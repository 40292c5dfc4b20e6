"""`ditch-drake benchmark`: a controller's seeded rollouts over the ditches of a split.

The split's first `geometries` ditches are sampled (`sample_ditch`, from the split's ranges:
`splits.split_ranges`), written beside the results as an environments file
(`splits.ditches_file`), and every task of each runs
`rollouts` times (seeds seed .. seed + rollouts - 1) through the batch evaluation
(`ditch_drake.evaluation.batch.evaluate`): resumable, in parallel, on the local pool or Ray.
The paper split runs the four packaged environments instead.
"""

import shlex
import sys
from dataclasses import dataclass

from tqdm import tqdm

from ditch_drake.benchmark.generator import SampledDitch, sample_ditch
from ditch_drake.benchmark.ranges import BenchmarkRanges
from ditch_drake.benchmark.splits import (
    PAPER_SPLIT,
    check_split,
    ditches_file,
    split_ranges,
    split_seeds,
    split_time_limit_s,
    write_ditches,
)
from ditch_drake.common.checks import check_count, check_finite_positive
from ditch_drake.common.config_yaml import safe_load_yaml
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.files import prepare_output, remove_stale_temporaries
from ditch_drake.common.seeds import check_seed
from ditch_drake.diagrams.controllers import controller_config
from ditch_drake.evaluation.batch import EvaluationReport, evaluate, make_specs
from ditch_drake.evaluation.results import RolloutRecord, RolloutSpec
from ditch_drake.learning.checkpoint import GENERALIST_MODEL as GENERALIST
from ditch_drake.world.environments import environment_names

# Each generated ditch's rollouts build diagrams of their own, and a worker's memory grows by
# tens of MB for every diagram it has built (`ditch_drake.evaluation.batch`): a learned
# controller's worker held 5.3 GB after about 70 rollouts of the test split.
ROLLOUTS_PER_WORKER = 30


@dataclass
class BenchmarkConfig:
    """One benchmark run.

    Attributes:
        split: "train", "val", "test", "stress", "search", "search_val" or "paper" (`splits.SPLITS`).
        controller: a registered controller's name.
        checkpoint: the learned policy's ("": `GENERALIST`).
        crossing_side: the learned policy's `LearnedPolicyConfig.crossing_side` ("perceived" or
            "oracle"; "": the config's own, perceived).
        geometries: the split's first N ditches (None: all); ignored for "paper".
        rollouts: seeded rollouts per task.
        seed: rollout i of each task uses seed + i.
        out: the results file (JSON Lines); its ditches go to `<stem>.ditches.yaml` beside it.
        ranges: a ranges YAML file ("": the split's packaged one, `splits.SPLIT_RANGES`:
            `stress_ranges.yaml` for "stress", `search_ranges.yaml` for "search" and "search_val",
            `ranges.yaml` for the others).
        time_limit_s: each episode's limit (s); None: the split's (`splits.split_time_limit_s`:
            240 s for the search splits, 120 s for the others).
        override: YAML in the Scenario schema whose controller replaces the one of `controller`
            (e.g. "{controller: !LearnedPolicyConfig {search: {}}}"; a learned config naming no
            checkpoint takes `checkpoint`); "": none.
        workers, backend, address: as for `evaluate`.
    """

    split: str = "test"
    controller: str = "expert"
    checkpoint: str = ""
    crossing_side: str = ""
    geometries: int | None = None
    rollouts: int = 1
    seed: int = 0
    out: str = "results/benchmark/benchmark.jsonl"
    ranges: str = ""
    time_limit_s: float | None = None
    override: str = ""
    workers: int | None = None
    backend: str = "local"
    address: str | None = None


def benchmark_controller(name: str):
    """A registered controller's name, or the config the benchmark runs for it: the expert makes
    room along the ditch before crossing (`ExpertVariation.lead_in`), as the generated tasks
    cross anywhere in the middle 40 % of a course, some of them too near its end for a crossing
    that runs along the edge."""
    if name != "expert":
        return name
    from ditch_drake.diagrams.rollout import ExpertConfig
    from ditch_drake.systems.expert import ExpertVariation

    return ExpertConfig(variation=ExpertVariation(lead_in=True))


def replay_command(record: RolloutRecord, out: str = "") -> str:
    """The `ditch-drake replay` command that records `record`'s rollout as an HTML page: its
    environment (and ditches file), task and seed, and its controller: by name where the name's
    default config is the record's, else the record's whole config as a `--override`."""
    import yaml

    from ditch_drake.common.config_yaml import config_to_yaml

    parts = ["ditch-drake", "replay"]
    if record.environments_file:
        parts += ["--environments", record.environments_file]
    parts += ["--env", record.environment, "--task", str(record.task), "--seed", str(record.seed)]
    if config_to_yaml(controller_config(record.controller, record.checkpoint)) == record.controller_config:
        parts += ["--controller", record.controller] + (["--checkpoint", record.checkpoint] if record.checkpoint else [])
    else:
        config = safe_load_yaml(record.controller_config, f"controller config of the record {record.key}")
        body = yaml.safe_dump(config, default_flow_style=True, width=10_000).strip()
        parts += ["--override", f"{{controller: !{record.controller_type.rpartition(':')[2]} {body}}}"]
    parts += ["--out", out or f"{record.environment}_{record.task}_{record.seed}.html"]
    return shlex.join(parts)


def overridden_controller(controller, checkpoint: str, override: str):
    """The controller config of the Scenario YAML `override` over `controller` (a name or a
    config); a config that takes a checkpoint and names none gets `checkpoint`.

    Raises:
        ConfigError: YAML that does not load as a Scenario, or a value out of range, named.
    """
    from ditch_drake.diagrams.controllers import with_checkpoint
    from ditch_drake.diagrams.scenario import Scenario, load_scenario

    base = controller_config(controller, checkpoint) if isinstance(controller, str) else controller
    overridden = load_scenario(override=override, defaults=Scenario(controller=base)).controller
    if checkpoint and hasattr(overridden, "checkpoint") and not overridden.checkpoint:
        overridden = with_checkpoint(overridden, checkpoint)
    return overridden


def sample_split(split: str, geometries: int | None, ranges: BenchmarkRanges,
                 progress: bool = True) -> list[SampledDitch]:
    seeds = split_seeds(split, geometries)
    return [sample_ditch(seed, ranges) for seed in tqdm(seeds, desc=f"sample {split}", disable=not progress,
                                                        file=sys.stderr)]


def check_benchmark_config(config: BenchmarkConfig) -> None:
    """Raises ConfigError naming the first setting out of range: split, geometries (None or
    >= 1, for every split), rollouts, seed, time limit, or a checkpoint given to a controller
    that takes none."""
    check_split(config.split)
    if config.geometries is not None:
        check_count(config.geometries, "geometries")
    check_count(config.rollouts, "rollouts")
    check_seed(config.seed, config.rollouts)
    if config.time_limit_s is not None:
        check_finite_positive(config.time_limit_s, "time_limit_s")
    if config.checkpoint and not hasattr(controller_config(config.controller), "checkpoint"):
        raise ConfigError(f"checkpoint {config.checkpoint!r} with controller {config.controller!r}, which takes "
                          "none; expected a checkpoint only with a controller that takes one, such as 'learned'")


def benchmark_specs(config: BenchmarkConfig, progress: bool = True) -> list[RolloutSpec]:
    """The run's rollouts; writes (adds to) its ditches file first.

    Raises:
        ConfigError: a bad split, count, controller, checkpoint, ranges file or results
            path, each named.
    """
    check_benchmark_config(config)
    prepare_output(config.out, "results file")
    ranges = split_ranges(config.split, config.ranges or None)
    checkpoint = (config.checkpoint or GENERALIST) if config.controller == "learned" else config.checkpoint
    if config.split == PAPER_SPLIT:
        names, environments_file = environment_names(), ""
    else:
        ditches = sample_split(config.split, config.geometries, ranges, progress)
        remove_stale_temporaries(ditches_file(config.out).parent)  # A killed run's half-written ditches file.
        environments_file = str(write_ditches(ditches_file(config.out), ditches))
        names = [ditch.name for ditch in ditches]
    controller = benchmark_controller(config.controller)
    if config.override:
        controller = overridden_controller(controller, checkpoint, config.override)
    if config.crossing_side:
        from ditch_drake.diagrams.rollout import with_crossing_side

        controller = with_crossing_side(controller_config(controller, checkpoint), config.crossing_side)
    time_limit_s = split_time_limit_s(config.split) if config.time_limit_s is None else config.time_limit_s
    specs = []
    for name in names:
        specs += make_specs(controller, checkpoint, name, None, config.rollouts, config.seed,
                            time_limit_s, environments_file)
    return specs


def run_benchmark(config: BenchmarkConfig, progress: bool = True,
                  specs: list[RolloutSpec] | None = None) -> EvaluationReport:
    """Runs the rollouts of `config` (or `specs`, its `benchmark_specs` made already) not yet
    in its results file (see the module docstring)."""
    check_benchmark_config(config)
    prepare_output(config.out, "results file")
    specs = benchmark_specs(config, progress) if specs is None else specs
    return evaluate(specs, config.out, workers=config.workers, progress=progress, backend=config.backend,
                    address=config.address, rollouts_per_worker=ROLLOUTS_PER_WORKER)
