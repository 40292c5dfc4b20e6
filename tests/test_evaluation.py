"""Batch evaluation: seeded rollouts, the results file, resuming, Wilson intervals."""

import dataclasses
import json

import pytest
import torch

from ditch_drake.common.config_yaml import config_digest, config_to_yaml, type_path
from ditch_drake.diagrams.rollout import LearnedPolicyConfig
from ditch_drake.evaluation import batch, rollout_worker
from ditch_drake.evaluation.batch import evaluate, make_specs, run_rollout
from ditch_drake.evaluation.results import RecordWriter, ResultsError, read_records
from ditch_drake.evaluation.summary import group_by, summarize, wilson_interval
from ditch_drake.learning.checkpoint import CheckpointError, checkpoint_digest, make_checkpoint, save_checkpoint
from ditch_drake.learning.model import FourInputClassifier
from ditch_drake.world.environments import ConfigError

# Short episodes: the expert is still on its approach when they time out.
SPECS = make_specs("expert", "", "wide", tasks=[0], rollouts=2, seed=3, time_limit_s=1.5)


def outcome_fields(record) -> dict:
    values = dataclasses.asdict(record)
    values.pop("wall_s")
    return values


def test_wilson_interval_on_known_counts():
    assert wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-4)
    assert wilson_interval(10, 10) == pytest.approx((0.7225, 1.0), abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError, match="successes=11"):
        wilson_interval(11, 10)


def test_same_seed_gives_the_same_rollout_twice():
    first, second = run_rollout(SPECS[0]), run_rollout(SPECS[0])
    assert first.status == "timeout" and first.failure_region == "approach"
    assert first.path_length_m > 0.5
    assert outcome_fields(first) == outcome_fields(second)


def test_evaluate_records_every_rollout_once_and_resumes_after_an_interruption(tmp_path):
    full = tmp_path / "full.jsonl"
    report = evaluate(SPECS, full, workers=0, progress=False)
    assert (report.recorded, report.skipped, report.errors) == (2, 0, 0)
    complete = {record.key: outcome_fields(record) for record in read_records(full)[0]}
    assert set(complete) == {spec.key for spec in SPECS}

    again = evaluate(SPECS, full, workers=0, progress=False)
    assert (again.recorded, again.skipped) == (0, 2)
    assert len(read_records(full)[0]) == 2

    # An interruption while the second record was being written: one whole line and a torn one.
    interrupted = tmp_path / "interrupted.jsonl"
    first_line, second_line = full.read_text().splitlines()
    interrupted.write_text(first_line + "\n" + second_line[:40])
    records, warnings = read_records(interrupted)
    assert len(records) == 1 and "cut short" in warnings[0]
    resumed = evaluate(SPECS, interrupted, workers=0, progress=False)
    assert (resumed.recorded, resumed.skipped) == (1, 1)
    records, warnings = read_records(interrupted)
    assert warnings == []
    assert {record.key: outcome_fields(record) for record in records} == complete


def test_worker_processes_give_the_same_records_as_one_process(tmp_path, monkeypatch):
    evaluate(SPECS, tmp_path / "pool.jsonl", workers=2, progress=False)
    evaluate(SPECS, tmp_path / "here.jsonl", workers=0, progress=False)
    monkeypatch.setattr(batch, "ROLLOUTS_PER_WORKER", 1)  # A fresh pool (and worker) for every rollout.
    evaluate(SPECS, tmp_path / "recycled.jsonl", workers=1, progress=False)
    by_key = [{r.key: outcome_fields(r) for r in read_records(tmp_path / name)[0]}
              for name in ("pool.jsonl", "here.jsonl", "recycled.jsonl")]
    assert by_key[0] == by_key[1] == by_key[2] and len(by_key[0]) == len(SPECS)


def test_pending_rollouts_run_in_fresh_pools_of_workers_times_rollouts_per_worker(tmp_path, recorded_pools):
    pools = recorded_pools
    specs = make_specs("edge_angle", "", "wide", tasks=[0, 1], rollouts=3, time_limit_s=1.0)
    report = evaluate(specs, tmp_path / "results.jsonl", workers=2, progress=False, rollouts_per_worker=2)
    assert pools == [(4, 2), (2, 2)] and report.recorded == 6
    pools.clear()  # by default a worker runs ROLLOUTS_PER_WORKER (100): one pool for all six
    assert evaluate(specs, tmp_path / "default.jsonl", workers=2, progress=False).recorded == 6
    assert pools == [(6, 2)] and batch.ROLLOUTS_PER_WORKER == 100


def test_a_rollout_that_raises_is_recorded_as_an_error_and_the_run_goes_on(tmp_path):
    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="broken.pt"):  # `make_specs` checks the checkpoint up front.
        make_specs("learned", str(broken), "wide", tasks=[0], rollouts=1, time_limit_s=1.0)
    # A spec made by other means still fails inside its rollout, and the run goes on.
    learned = LearnedPolicyConfig(checkpoint=str(broken))
    bad = [dataclasses.replace(SPECS[0], controller="learned", controller_type=type_path(LearnedPolicyConfig),
                               controller_config=config_to_yaml(learned), controller_sha256=config_digest(learned),
                               checkpoint=str(broken), checkpoint_sha256=checkpoint_digest(str(broken)))]
    report = evaluate(bad + SPECS[:1], tmp_path / "results.jsonl", workers=0, progress=False)
    assert (report.recorded, report.errors, report.successes) == (2, 1, 0)
    errors = [r for r in read_records(tmp_path / "results.jsonl")[0] if r.status == "error"]
    assert len(errors) == 1 and "CheckpointError" in errors[0].error and str(broken) in errors[0].error


def test_a_learned_policy_checkpoint_drives_a_rollout(tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "random.pt"
    save_checkpoint(make_checkpoint(FourInputClassifier()), path)
    specs = make_specs("learned", str(path), "wide", tasks=[1], rollouts=1, time_limit_s=1.0)
    record = run_rollout(specs[0])
    assert record.status == "timeout", record.error
    assert len(record.checkpoint_sha256) == 16


def test_bad_specs_are_refused_with_the_bad_value_named(tmp_path):
    with pytest.raises(ConfigError, match="'teleporter'"):
        make_specs("teleporter", "", "wide")
    with pytest.raises(ConfigError, match="'moon'"):
        make_specs("expert", "", "moon")
    with pytest.raises(ConfigError, match=r"tasks \[7\]"):
        make_specs("expert", "", "wide", tasks=[7])
    with pytest.raises(ConfigError, match="missing.pt"):
        make_specs("learned", str(tmp_path / "missing.pt"), "wide")


def test_a_results_file_of_another_schema_version_is_refused(tmp_path):
    path = tmp_path / "old.jsonl"
    path.write_text(json.dumps({"schema": "ditch_drake.rollout_record", "schema_version": 1, "key": "x"}) + "\n")
    with pytest.raises(ResultsError, match="version 1"):
        read_records(path)
    with pytest.raises(ResultsError, match="version 1"):
        evaluate(SPECS, path, workers=0, progress=False)
    assert path.read_text().count("\n") == 1  # Nothing was written to it.


def test_summaries_count_successes_failures_and_errors(tmp_path):
    record = run_rollout(SPECS[0])
    succeeded = dataclasses.replace(record, key="a", status="reached_goal", success=True, failure_region="")
    errored = dataclasses.replace(record, key="b", status="error", error="boom")
    summary = summarize([record, succeeded, errored])
    assert (summary.trials, summary.successes, summary.errors) == (2, 1, 1)
    assert summary.rate == 0.5 and summary.failure_regions == {"timeout@approach": 1}
    assert list(group_by([record, succeeded], "environment", "task")) == [("wide", 0)]
    with RecordWriter(tmp_path / "r.jsonl") as writer:
        writer.append(errored)
    assert read_records(tmp_path / "r.jsonl")[0][0].error == "boom"


def test_a_worker_keeps_only_its_most_recently_used_rigs(monkeypatch):
    built = []
    monkeypatch.setattr(rollout_worker, "MakeRolloutDiagram",
                        lambda config: built.append(config) or (object(), object()))
    monkeypatch.setattr(rollout_worker, "Simulator", lambda diagram: object())
    monkeypatch.setattr(rollout_worker, "_WORKER_RIGS", type(rollout_worker._WORKER_RIGS)())
    specs = [spec for env in ("wide", "sine") for spec in make_specs("edge_angle", "", env, rollouts=1)]
    first = rollout_worker._rig(specs[0])
    assert rollout_worker._rig(dataclasses.replace(specs[0], seed=9)) is first and len(built) == 1  # Reused.
    for spec in specs[1:]:
        rollout_worker._rig(spec)
    assert len(rollout_worker._WORKER_RIGS) == rollout_worker.MAX_WORKER_RIGS < len(specs)
    assert rollout_worker._rig(specs[-1]) is rollout_worker._WORKER_RIGS[next(reversed(rollout_worker._WORKER_RIGS))]
    rollout_worker._rig(specs[0])  # Evicted long ago: built again.
    assert len(built) == len(specs) + 1


def test_the_expert_builds_a_rig_per_seed_and_other_controllers_share_one(monkeypatch):
    built = []
    monkeypatch.setattr(rollout_worker, "MakeRolloutDiagram",
                        lambda config: built.append(config) or (object(), object()))
    monkeypatch.setattr(rollout_worker, "Simulator", lambda diagram: object())
    monkeypatch.setattr(rollout_worker, "_WORKER_RIGS", type(rollout_worker._WORKER_RIGS)())
    for spec in make_specs("expert", "", "wide", [0], rollouts=2) + make_specs("dwa", "", "wide", [0], rollouts=2):
        rollout_worker._rig(spec)
    assert [type(config.controller).__name__ for config in built] == ["ExpertConfig", "ExpertConfig",
                                                                        "DwaBaselineConfig"]
    assert [config.controller.style_seed for config in built[:2]] == [0, 1]


def test_spec_keys_identify_rollouts():
    (a,) = make_specs("learned", "wide", "narrow", [1], rollouts=1, seed=4)
    assert a.key == f"learned#{a.controller_sha256}|wide@{a.checkpoint_sha256}|narrow|1|4|120|1.5"
    assert a.key != dataclasses.replace(a, seed=5).key
    assert a.key != dataclasses.replace(a, checkpoint_sha256="fedcba9876543210").key
    assert a.key != make_specs("learned", "narrow", "narrow", [1], rollouts=1, seed=4)[0].key


def test_checkpoints_of_another_action_table_or_input_shape_are_refused(tmp_path):
    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig, MakeRolloutDiagram, RolloutConfig
    from ditch_drake.learning.checkpoint import CheckpointError, load_checkpoint
    from ditch_drake.learning.model import ModelConfig
    from ditch_drake.spec import actions

    other_table = tmp_path / "other_table.pt"
    checkpoint = make_checkpoint(FourInputClassifier())
    save_checkpoint(dataclasses.replace(checkpoint, action_commands=actions.COMMANDS * 2.0), other_table)
    with pytest.raises(CheckpointError, match="another action table"):
        load_checkpoint(other_table)
    assert load_checkpoint(other_table, allow_other_action_table=True).action_commands[0][0] == 2 * actions.COMMANDS[0][0]

    small_images = tmp_path / "small_images.pt"
    save_checkpoint(make_checkpoint(FourInputClassifier(ModelConfig(image_size=64))), small_images)
    config = RolloutConfig(scene=SceneConfig(environment="wide"), controller=LearnedPolicyConfig(str(small_images)))
    with pytest.raises(CheckpointError, match="expects image_stack of 16384 values; the observation blocks give 65536"):
        MakeRolloutDiagram(config)


def test_the_ray_backend_gives_the_same_records_as_the_local_pool(tmp_path):
    pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[ray]')")
    report = evaluate(SPECS, tmp_path / "ray.jsonl", workers=2, progress=False, backend="ray", address="local")
    assert (report.recorded, report.errors) == (2, 0)
    evaluate(SPECS, tmp_path / "here.jsonl", workers=0, progress=False)
    by_key = [{r.key: outcome_fields(r) for r in read_records(tmp_path / name)[0]} for name in ("ray.jsonl", "here.jsonl")]
    assert by_key[0] == by_key[1]
    again = evaluate(SPECS, tmp_path / "ray.jsonl", workers=2, progress=False, backend="ray", address="local")
    assert (again.recorded, again.skipped) == (0, 2)


def test_an_unknown_backend_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="'spark'"):
        evaluate(SPECS, tmp_path / "r.jsonl", backend="spark")


def test_a_rollout_that_cannot_import_a_module_stops_the_run_naming_it(tmp_path, monkeypatch):
    def broken_install(spec):
        return rollout_worker.error_record(spec, "ModuleNotFoundError: No module named 'ditch_drake.models_sdf'")

    monkeypatch.setattr(batch, "run_rollout", broken_install)
    out = tmp_path / "results.jsonl"
    with pytest.raises(ConfigError, match=r"No module named 'ditch_drake.models_sdf'.*reinstall"):
        evaluate(SPECS, out, workers=0, progress=False)
    [record] = read_records(out)[0]  # The first rollout's error is kept; the second never ran.
    assert record.status == "error"


def test_a_rerun_naming_the_environments_file_another_way_resumes_instead_of_running_again(tmp_path, monkeypatch):
    from pathlib import Path

    import ditch_drake.world

    folder = Path(ditch_drake.world.__file__).parent
    monkeypatch.chdir(folder)
    out = tmp_path / "runs.jsonl"
    relative = make_specs("expert", "", "wide", [0], rollouts=2, seed=3, time_limit_s=1.5,
                          environments_file="environments.yaml")
    assert evaluate(relative, out, workers=0, progress=False).recorded == 2
    absolute = make_specs("expert", "", "wide", [0], rollouts=2, seed=3, time_limit_s=1.5,
                          environments_file=str(folder / "environments.yaml"))
    assert {spec.key for spec in absolute}.isdisjoint(spec.key for spec in relative)
    again = evaluate(absolute, out, workers=0, progress=False)
    assert (again.recorded, again.skipped) == (0, 2)
    assert [record.environments_file for record in read_records(out)[0]] == ["environments.yaml"] * 2
    assert [spec.key for spec in batch.spelled_as_recorded(absolute, read_records(out)[0])] == \
        [spec.key for spec in relative]


def test_a_rerun_naming_the_checkpoint_another_way_resumes_instead_of_running_again(tmp_path, monkeypatch):
    from pathlib import Path

    import ditch_drake

    folder = Path(ditch_drake.__file__).parent
    monkeypatch.chdir(folder)
    out = tmp_path / "runs.jsonl"
    relative = make_specs("learned", "models/wide.pt", "wide", [1], rollouts=2, seed=3, time_limit_s=0.3)
    assert evaluate(relative, out, workers=0, progress=False).recorded == 2
    for spelling in (str(folder / "models" / "wide.pt"), "./models/wide.pt"):
        other = make_specs("learned", spelling, "wide", [1], rollouts=2, seed=3, time_limit_s=0.3)
        # The path is in the key and in the controller's config, whose digest is in the key too.
        assert {spec.key for spec in other}.isdisjoint(spec.key for spec in relative)
        assert [spec.key for spec in batch.spelled_as_recorded(other, read_records(out)[0])] == \
            [spec.key for spec in relative]
        assert batch.spelled_as_recorded(other, []) == other  # Nothing recorded: as given.
        again = evaluate(other, out, workers=0, progress=False)
        assert (again.recorded, again.skipped) == (0, 2)
    assert [record.checkpoint for record in read_records(out)[0]] == ["models/wide.pt"] * 2
    # Another config of the same checkpoint is not the records' rollout: it keeps its spelling.
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig

    oracle = make_specs(LearnedPolicyConfig(checkpoint=str(folder / "models" / "wide.pt"), crossing_side="oracle"),
                        "", "wide", [1], rollouts=1, seed=3, time_limit_s=0.3)
    assert batch.spelled_as_recorded(oracle, read_records(out)[0]) == oracle
