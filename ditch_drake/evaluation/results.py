"""Rollout records: one JSON object per line, appended as each rollout ends.

A results file is JSON Lines. Every line is one finished rollout (`RolloutRecord`) with
`schema` and `schema_version`; a line is written whole and flushed to disk before the next
starts, so a run killed at any moment leaves at most a torn last line, which `read_records`
reports and drops (its rollout simply runs again). Rollouts are identified by their `key`,
which names the checkpoint by its contents' digest as well as by its name, so a rerun skips
what is already recorded and never records a rollout twice, and a checkpoint retrained at the
same path is evaluated afresh. An error record is history, not a result: a rerun runs its
rollout again, and `current_records` leaves it out once a real record of the key exists.

Each record also carries its controller's full config (YAML, and its digest in the key), so
that a controller with other parameters is another rollout, and its type ("module:Class") so
that a worker process can build it.

Files of schema versions 2 and 3 (whose records named only the controller, with its default
parameters) still read: their controller configs and keys are rebuilt from their fields as
they load, the same as a new spec of the same controller, so a rerun skips what they hold.
Schema 5 added `halts_by_region`; records of older versions read with it empty (not counted),
and their keys are unchanged, so a rerun skips them too. Schema 6 added `privileged`,
`crossing_side_source` and the perceived side's agreement with the oracle (`side_*`); older
records read with them empty (nothing declared, no side block recorded, nothing counted), keys
unchanged. Schema 7 added the shared controller's `handover_fraction`, `switches` and
`handover_regions`; every other controller's records carry them as 0, 0 and [] (no gate), and
older records read with those values, keys unchanged.
"""

import json
import math
import os
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path

from ditch_drake.common.errors import ResultsError

SCHEMA = "ditch_drake.rollout_record"
SCHEMA_VERSION = 7
# Older versions that still read (see the module docstring).
READABLE_VERSIONS = (2, 3, 4, 5, 6, 7)


@dataclass(frozen=True)
class RolloutSpec:
    """One seeded rollout to run.

    Attributes:
        controller: the registered controller's name (`ditch_drake.diagrams.controllers`).
        controller_type: its config class, "module:Class".
        controller_config: its config, as `config_to_yaml` writes it.
        controller_sha256: `config_digest` of that config (in the key).
        checkpoint: the learned policy's shipped name or file ("" for other controllers).
        checkpoint_sha256: first 16 hex digits of that file's SHA-256 when the spec was made
            ("" for other controllers); a worker that finds other contents records an error.
        environment: the environment the robot drives in.
        environments_file: the YAML file that defines it ("" for the packaged one).
        task: index of its start/goal task.
        seed: the episode's seed (start jitter, sensor noise, expert style).
        time_limit_s: the episode's timeout (s).
        goal_radius_m: success within this planar distance of the goal (m).
    """

    controller: str
    controller_type: str
    controller_config: str
    controller_sha256: str
    checkpoint: str
    checkpoint_sha256: str
    environment: str
    environments_file: str
    task: int
    seed: int
    time_limit_s: float
    goal_radius_m: float

    @property
    def key(self) -> str:
        """Identifies the rollout within a results file."""
        return record_key(self)


def record_key(fields) -> str:
    """The key of a spec or record: every field that changes what the rollout does."""
    environment = fields.environment + (f"@{fields.environments_file}" if fields.environments_file else "")
    return (f"{fields.controller}#{fields.controller_sha256}|{fields.checkpoint}@{fields.checkpoint_sha256}|"
            f"{environment}|{fields.task}|{fields.seed}|{fields.time_limit_s:g}|{fields.goal_radius_m:g}")


@dataclass
class RolloutRecord:
    """What one rollout did (SI units, angles in degrees).

    Attributes:
        key: `RolloutSpec.key`.
        controller, checkpoint, environment, task, seed, time_limit_s, goal_radius_m,
        controller_type, controller_config, controller_sha256, environments_file: the spec.
        checkpoint_sha256: first 16 hex digits of the checkpoint file's hash ("" if none).
        status: reached_goal, rolled_over, timeout, stuck, or error.
        success: status == reached_goal.
        time_s: simulated time at the end.
        path_length_m: planar distance driven.
        peak_abs_roll_deg, peak_abs_pitch_deg, peak_tilt_deg: largest chassis attitudes.
        min_stability_margin_deg: smallest static tip-over margin seen.
        final_x_m, final_y_m: where the chassis ended.
        failure_region: where it ended relative to the ditch: "approach" (outside, on the
            start side), "down_wall" (the wall it entered by), "floor", "up_wall" (the wall
            it leaves by), "beyond" (outside, past the ditch), or "" on success.
        wall_s: wall-clock time of the rollout, building excluded (s).
        error: the exception's type and message when status is error, else "".
        halts_by_region: the controller's halts (|v| command below 0.05 m/s for 0.5 s or
            more, `ditch_drake.systems.halt_counter`) per region, every region of
            `ditch_drake.world.regions.REGIONS` a key; empty for an error record and for
            records of schema versions before 5 (not counted).
        privileged: what the controller declared it reads beyond its sensors, its pose and
            the goal, for its config (`ControllerEntry.privileged_inputs`: e.g. ["terrain"]);
            empty for none and for records of schema versions before 6.
        crossing_side_source: where a side-conditioned clone was told its crossing side:
            "perceived" (the diagram has a "perceived_crossing_side" block), "oracle" (an
            "oracle_crossing_side" block), else "" (no such block, a rollout whose diagram was
            never built, or a record of a schema version before 6).
        side_zone_steps, side_agreeing_steps, side_unseen_steps, side_disagreement_edge_m: for a
            perceived side, the control steps in the approach zone (the oracle's: from where the
            chassis first came within the expert's approach margin of the hinge line), those
            where the perceived side equalled the oracle's, those told no side yet, and the
            nearest and farthest distance to the hinge line (m, negative inside it) of a step
            where they differed ([] if none did); 0 and [] otherwise
            (`ditch_drake.systems.crossing_side_agreement`).
        handover_fraction: for the `shared` controller, the share of the control steps its
            fallback drove (`ditch_drake.systems.handover_counter`); 0 for other controllers,
            error records and records of schema versions before 7.
        switches: for `shared`, how often its gate passed control either way (handovers plus
            handbacks, `SharedControl`'s count); 0 otherwise.
        handover_regions: for `shared`, the region (as `failure_region` names them) where each
            handover to the fallback began, in order; [] otherwise.
    """

    key: str
    controller: str
    checkpoint: str
    environment: str
    task: int
    seed: int
    time_limit_s: float
    goal_radius_m: float
    checkpoint_sha256: str
    status: str
    success: bool
    time_s: float
    path_length_m: float
    peak_abs_roll_deg: float
    peak_abs_pitch_deg: float
    peak_tilt_deg: float
    min_stability_margin_deg: float
    final_x_m: float
    final_y_m: float
    failure_region: str
    wall_s: float
    error: str = ""
    controller_type: str = ""
    controller_config: str = ""
    controller_sha256: str = ""
    environments_file: str = ""
    halts_by_region: dict[str, int] = field(default_factory=dict)
    privileged: list[str] = field(default_factory=list)
    crossing_side_source: str = ""
    side_zone_steps: int = 0
    side_agreeing_steps: int = 0
    side_unseen_steps: int = 0
    side_disagreement_edge_m: list[float] = field(default_factory=list)
    handover_fraction: float = 0.0
    switches: int = 0
    handover_regions: list[str] = field(default_factory=list)

    def to_json(self) -> str:
        """One line: the fields plus the schema and its version (non-finite numbers as null)."""
        values = {"schema": SCHEMA, "schema_version": SCHEMA_VERSION}
        for name, value in asdict(self).items():
            values[name] = None if isinstance(value, float) and not math.isfinite(value) else value
        return json.dumps(values, sort_keys=True)

    @classmethod
    def from_dict(cls, values: dict, where: str) -> "RolloutRecord":
        """The record of a parsed line.

        Raises:
            ResultsError: another schema or version, or missing fields, naming `where`.
        """
        if values.get("schema") != SCHEMA or values.get("schema_version") not in READABLE_VERSIONS:
            raise ResultsError(
                f"{where}: schema {values.get('schema')!r} version {values.get('schema_version')!r}; expected "
                f"{SCHEMA!r} version {' or '.join(map(str, READABLE_VERSIONS))} (a file from another version of "
                "ditch_drake: write to a new file)")
        if values["schema_version"] < 4:
            values = _upgraded(values, where)
        names = [f.name for f in fields(cls)]
        optional = {f.name for f in fields(cls) if f.default is not MISSING or f.default_factory is not MISSING}
        missing = [name for name in names if name not in values and name not in optional]
        if missing:
            raise ResultsError(f"{where}: record lacks {missing}")
        record = cls(**{name: (math.nan if values[name] is None else values[name]) for name in names if name in values})
        record.key = record_key(record)
        return record

    @property
    def is_error(self) -> bool:
        return self.status == "error"


def read_records(path: str | os.PathLike) -> tuple[list[RolloutRecord], list[str]]:
    """The records of a results file (none if it does not exist) and warnings.

    A last line without its newline is a write cut short by an interruption: it is
    reported in the warnings and left out (its rollout runs again). A bad line elsewhere
    means the file is not ours.

    Raises:
        ResultsError: a line that is not a record of this schema version, naming the line.
    """
    path = Path(path)
    if not path.exists():
        return [], []
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise ResultsError(f"{path}: byte {error.start} is not UTF-8; expected a results file of JSON lines") from error
    lines = text.split("\n")
    warnings = []
    if lines and lines[-1] != "":
        warnings.append(f"{path}: the last line was cut short by an interruption; its rollout runs again")
    records = []
    for number, line in enumerate(lines[:-1], start=1):
        if not line.strip():
            continue
        try:
            values = json.loads(line)
        except json.JSONDecodeError as error:
            raise ResultsError(f"{path}:{number}: not a JSON record ({error})") from error
        if not isinstance(values, dict):
            raise ResultsError(f"{path}:{number}: expected a JSON object, got {type(values).__name__}")
        records.append(RolloutRecord.from_dict(values, f"{path}:{number}"))
    return records, warnings


def _upgraded(values: dict, where: str) -> dict:
    """A schema 2 or 3 record's fields as schema 4 has them: its controller's default config."""
    from ditch_drake.common.config_yaml import config_digest, config_to_yaml, type_path
    from ditch_drake.diagrams.controllers import controller_config

    try:
        config = controller_config(values.get("controller", ""), values.get("checkpoint", ""))
    except ValueError as error:
        raise ResultsError(f"{where}: {error}") from error
    return {**values, "controller_type": type_path(type(config)), "controller_config": config_to_yaml(config),
            "controller_sha256": config_digest(config), "environments_file": ""}


def finished_keys(records: list[RolloutRecord]) -> set[str]:
    """The keys with a real outcome: an error record does not finish its rollout (it runs again)."""
    return {record.key for record in records if not record.is_error}


def current_records(records: list[RolloutRecord],
                    digests: dict[str, str] | None = None) -> tuple[list[RolloutRecord], list[str]]:
    """The records a summary counts, one per key, and a note for each group set aside.

    Per key, the last record with a real outcome wins, else the last error record (a
    rollout that only ever errored is reported as an error). Per learned checkpoint name,
    only the records of one version of the file count: the digest in `digests` (by
    checkpoint name; the evaluated file's), else the digest of that name's last record in
    file order. Records of other versions are set aside, and said so in the notes.
    """
    by_key: dict[str, RolloutRecord] = {}
    for record in records:
        kept = by_key.get(record.key)
        if kept is None or not record.is_error or kept.is_error:
            by_key[record.key] = record
    wanted = dict(digests or {})
    for record in records:
        if record.checkpoint and record.checkpoint_sha256 and record.checkpoint not in (digests or {}):
            wanted[record.checkpoint] = record.checkpoint_sha256
    kept, set_aside = [], {}
    for record in by_key.values():
        digest = record.checkpoint_sha256
        if record.checkpoint and digest and digest != wanted.get(record.checkpoint, digest):
            set_aside[(record.checkpoint, digest)] = set_aside.get((record.checkpoint, digest), 0) + 1
            continue
        kept.append(record)
    notes = [f"{count} records of checkpoint {name!r} with digest {digest} set aside: they are of another version "
             f"of the file than {wanted[name]}" for (name, digest), count in set_aside.items()]
    return kept, notes


class RecordWriter:
    """Appends records to a results file, each line flushed and synced before `append` returns."""

    def __init__(self, path: str | os.PathLike):
        """Opens `path` for appending (creating its folder), first trimming a torn last line."""
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            data = self.path.read_bytes()
            if data and not data.endswith(b"\n"):
                # Cut back to the last whole line so the next record starts on its own line.
                with open(self.path, "r+b") as handle:
                    handle.truncate(data.rfind(b"\n") + 1)
        self._handle = open(self.path, "a", encoding="utf-8")

    def append(self, record: RolloutRecord) -> None:
        self._handle.write(record.to_json() + "\n")
        self._handle.flush()
        os.fsync(self._handle.fileno())

    def close(self) -> None:
        self._handle.close()

    def __enter__(self) -> "RecordWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
