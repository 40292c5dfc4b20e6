"""Expert, recorder and the dataset format."""

import hashlib
import json
import os

import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.systems.analysis import Simulator

from ditch_drake.demos.collect import CollectConfig, MakeDemonstrationDiagram, collect
from ditch_drake.demos.dataset import (
    DatasetError,
    Demonstration,
    dataset_summary,
    load_dataset,
    load_demonstration,
    log_to_arrays,
    restack_images,
    save_demonstration,
    standard_metadata,
    to_array_set,
)
from ditch_drake.demos.store import EPISODE_FILE, DatasetStore, load_demonstrations
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.learning.checkpoint import resolve_checkpoint_path
from ditch_drake.spec import actions
from ditch_drake.systems.expert import draw_expert_style


def test_expert_style_is_seeded():
    assert draw_expert_style(3) == draw_expert_style(3)
    assert draw_expert_style(3) != draw_expert_style(4)
    style = draw_expert_style(3)
    assert 17 <= style.driver.wall_angle_deg <= 23 and 32 <= style.driver.climb_angle_deg <= 38


@pytest.fixture(scope="module")
def short_recording():
    """Two simulated seconds of the expert with perception and the recorder."""
    rig = MakeDemonstrationDiagram(SceneConfig(environment="wide", task=1), style_seed=0)
    simulator = Simulator(rig.diagram)
    context = simulator.get_mutable_context()
    rig.diagram.SetRandomContext(context, RandomGenerator(0))
    simulator.AdvanceTo(2.05)
    log = rig.recorder.log(rig.recorder.GetMyContextFromRoot(context))
    stacker_context = rig.observation.stacker.GetMyContextFromRoot(context)
    image_stack = rig.observation.stacker.GetOutputPort("image_stack").Eval(stacker_context)
    return log, image_stack


def test_recorder_records_every_control_step(short_recording):
    log, _ = short_recording
    times = np.array([step.time_s for step in log.steps])
    assert len(log) == 21
    assert np.allclose(np.diff(times), 0.1)
    assert all(0 <= step.label < actions.NUM_LABELS for step in log.steps)
    # The executed label is the quantized raw command.
    assert all(step.label == actions.quantize(step.raw_command) for step in log.steps)


def test_restacked_images_equal_what_the_stacker_holds(short_recording):
    log, image_stack = short_recording
    arrays = log_to_arrays(log)
    restacked = restack_images(arrays["image"])[-1].astype(np.float32) / 255.0
    assert restacked.shape == (4, 128, 128)
    assert np.allclose(restacked.ravel(), image_stack, atol=0.5 / 255 + 1e-6)


def _demonstration(steps=5, label=8):
    arrays = {
        "image": np.zeros((steps, 128, 128), np.uint8),
        "imu_stack": np.zeros((steps, 8), np.float32),
        "distance_stack": np.ones((steps, 4), np.float32),
        "bearing_stack": np.zeros((steps, 4), np.float32),
        "label": np.full(steps, label, np.int16),
        "time_s": np.arange(steps) * 0.1,
        "pose": np.zeros((steps, 6), np.float32),
        "raw_command": np.zeros((steps, 2), np.float32),
    }
    return Demonstration(arrays, standard_metadata(environment="wide", task={"index": 0, "name": "a"}, seed=1))


def test_round_trip_and_atomic_write(tmp_path):
    path = save_demonstration(tmp_path / "demo_000.npz", _demonstration())
    assert [p.name for p in tmp_path.iterdir()] == ["demo_000.npz"]  # No temporary file left.
    loaded = load_demonstration(path)
    assert len(loaded) == 5 and loaded.metadata["environment"] == "wide"
    assert loaded.metadata["action_table"] == actions.COMMANDS.tolist()


def test_corrupt_and_wrong_files_are_named(tmp_path):
    truncated = tmp_path / "demo_000.npz"
    save_demonstration(truncated, _demonstration())
    truncated.write_bytes(truncated.read_bytes()[:100])
    with pytest.raises(DatasetError, match="demo_000.npz is corrupt"):
        load_demonstration(truncated)
    bad_label = _demonstration(label=17)
    with pytest.raises(DatasetError, match=r"labels span 17..17; expected 0..16"):
        save_demonstration(tmp_path / "demo_001.npz", bad_label)
    wrong = _demonstration()
    wrong.arrays["imu_stack"] = np.zeros((5, 3), np.float32)
    with pytest.raises(DatasetError, match=r"'imu_stack' has shape \(5, 3\)"):
        save_demonstration(tmp_path / "demo_002.npz", wrong)
    old = _demonstration()
    old.metadata["schema_version"] = 0
    np.savez(tmp_path / "demo_003.npz", metadata=np.array(json.dumps(old.metadata)), **old.arrays)
    with pytest.raises(DatasetError, match="schema_version 0, expected 1"):
        load_demonstration(tmp_path / "demo_003.npz")


def test_summary_counts_labels_and_tasks(tmp_path):
    save_demonstration(tmp_path / "demo_000.npz", _demonstration(4, 8))
    save_demonstration(tmp_path / "demo_001.npz", _demonstration(2, 10))
    summary = dataset_summary(load_dataset(tmp_path))
    assert summary["per_label"][8] == 4 and summary["per_label"][10] == 2
    assert summary["straight_fraction"] == pytest.approx(4 / 6)
    assert summary["majority_to_minority_ratio"] == pytest.approx(2.0)
    assert summary["per_driver"] == {"expert": 2} and sum(summary["per_outcome"].values()) == 2


def test_restack_puts_newest_first_with_zeros_before_the_start():
    frames = np.arange(1, 4, dtype=np.uint8)[:, None, None] * np.ones((3, 2, 2), np.uint8)
    stacks = restack_images(frames)
    assert stacks[0, :, 0, 0].tolist() == [1, 0, 0, 0]
    assert stacks[2, :, 0, 0].tolist() == [3, 2, 1, 0]


def _numbered_frames(steps):
    """A demonstration whose frame i is all i + 1 and whose step i has label i."""
    demonstration = _demonstration(steps)
    demonstration.arrays["image"] = np.arange(1, steps + 1, dtype=np.uint8)[:, None, None] * np.ones(
        (steps, 128, 128), np.uint8)
    demonstration.arrays["label"] = np.arange(steps, dtype=np.int16)
    return demonstration


def test_thinned_steps_keep_stacks_of_consecutive_frames():
    samples = to_array_set([_numbered_frames(7), _numbered_frames(7)], strides=[1, 3])
    assert samples.label.tolist() == [0, 1, 2, 3, 4, 5, 6, 0, 3, 6]
    assert samples.demo_id.tolist() == [0] * 7 + [1] * 3
    # The kept step 6 (frame 7) stacks frames 7, 6, 5, 4 as the FrameStacker does, not 7, 4, 1, 0.
    assert samples.image[-1, :, 0, 0].tolist() == [7, 6, 5, 4]
    assert samples.image[7, :, 0, 0].tolist() == [1, 0, 0, 0]
    with pytest.raises(DatasetError, match=r"strides=\[1\]: expected one stride >= 1 per demonstration \(2\)"):
        to_array_set([_numbered_frames(7), _numbered_frames(7)], strides=[1])


def test_the_generalist_trains_on_every_dagger_stride_th_step_of_its_dagger_rollouts(tmp_path):
    from ditch_drake.pipelines.generalist import GeneralistConfig, _training_samples

    for name in ("demos", "dagger1"):
        save_demonstration(tmp_path / name / "demo_000.npz", _numbered_frames(7))
    samples = _training_samples(GeneralistConfig(dagger_stride=3), [tmp_path / "demos", tmp_path / "dagger1"], "")
    assert samples.label.tolist() == [0, 1, 2, 3, 4, 5, 6, 0, 3, 6]
    assert [stack[:, 0, 0].tolist() for stack in samples.image[7:]] == [[1, 0, 0, 0], [4, 3, 2, 1], [7, 6, 5, 4]]


def test_the_generalist_also_learns_the_reflection_of_crossings_that_turn_clearly(tmp_path):
    from importlib import resources

    from ditch_drake.pipelines.generalist import MIRROR_MARGIN_DEG, GeneralistConfig, _training_samples

    # The packaged wide ditch: task 0 runs square across, task 1 turns 24 deg to the right.
    for index, task in enumerate((1, 0)):
        demonstration = _numbered_frames(3)
        demonstration.arrays["image"][:, :, 0] = 200  # the leftmost column: the reflection moves it
        demonstration.arrays["imu_stack"][:] = [0.1, 0.2] * 4
        demonstration.arrays["bearing_stack"][:] = 0.3
        demonstration.metadata.update(task={"index": task, "name": "t"},
                                      expert_style={"driver": {"straight_across_deg": 15.0}})
        save_demonstration(tmp_path / "demos" / f"demo_{index:03d}.npz", demonstration)
    ditches = str(resources.files("ditch_drake.world") / "environments.yaml")
    plain = _training_samples(GeneralistConfig(), [tmp_path / "demos"], ditches)
    samples = _training_samples(GeneralistConfig(mirror=True), [tmp_path / "demos"], ditches)
    assert len(plain.label) == 6 and len(samples.label) == 9
    assert samples.demo_id.tolist() == [0] * 3 + [1] * 3 + [2] * 3
    assert samples.label.tolist() == [0, 1, 2, 16, 15, 14, 0, 1, 2]
    reflected = samples.image[3:6]
    assert np.array_equal(reflected, samples.image[0:3][..., ::-1])
    assert reflected[2, 0, 5, -1] == 200 and reflected[2, 0, 5, 0] != 200
    assert np.allclose(samples.imu[3], [-0.1, 0.2] * 4) and np.allclose(samples.bearing[3], -0.3)
    assert np.array_equal(samples.distance[3], samples.distance[0])
    # A convention wider than the turn (24 deg) leaves it unreflected.
    save_demonstration(tmp_path / "demos" / "demo_000.npz", _with_convention(tmp_path / "demos" / "demo_000.npz",
                                                                             24.5 - MIRROR_MARGIN_DEG))
    assert len(_training_samples(GeneralistConfig(mirror=True), [tmp_path / "demos"], ditches).label) == 6


def test_an_ensemble_of_the_generalist_resamples_whole_rollouts_with_their_reflections(tmp_path):
    from importlib import resources

    from ditch_drake.pipelines.generalist import GeneralistConfig, _training_entries

    # As above: demo_000 turns clearly (it and its reflection), demo_001 runs square across.
    for index, task in enumerate((1, 0)):
        demonstration = _numbered_frames(3)
        demonstration.metadata.update(task={"index": task, "name": "t"},
                                      expert_style={"driver": {"straight_across_deg": 15.0}})
        save_demonstration(tmp_path / "demos" / f"demo_{index:03d}.npz", demonstration)
    ditches = str(resources.files("ditch_drake.world") / "environments.yaml")
    entries = _training_entries(GeneralistConfig(mirror=True), [tmp_path / "demos"], ditches)
    assert entries.names == [f"{tmp_path / 'demos'}[0]", f"{tmp_path / 'demos'}[1]"]
    assert entries.demonstration.tolist() == [0, 0, 1]
    # A resample drawing demo_001 once and demo_000 twice: each draw keeps its reflection, and
    # its position in the resample is its id, so validation holds out a rollout with its reflection.
    samples = entries.samples(np.array([1, 0, 0]))
    assert samples.label.tolist() == [0, 1, 2] + [0, 1, 2, 16, 15, 14] * 2
    assert samples.demo_id.tolist() == [0] * 3 + [1] * 6 + [2] * 6
    # The rounds' own training set is as it always was: a reflection has an id of its own.
    assert entries.samples().demo_id.tolist() == [0] * 3 + [1] * 3 + [2] * 3


def test_the_generalists_ensemble_stage_trains_k_members_of_its_data_once(tmp_path, random_demonstration, capsys):
    from ditch_drake.demos.store import DatasetStore
    from ditch_drake.learning.ensemble import load_ensemble
    from ditch_drake.pipelines.generalist import GeneralistConfig, _train_ensemble

    for name, lengths in (("demos", (9, 6, 11)), ("dagger1", (8, 7))):
        store = DatasetStore.create(tmp_path / name)
        for index, steps in enumerate(lengths):
            store.append(random_demonstration(index, steps))
    config = GeneralistConfig(epochs=1, patience=1, dagger_stride=2, ensemble=2, balancing="oversample")
    out = tmp_path / "ensemble.pt"
    _train_ensemble(config, [tmp_path / "demos", tmp_path / "dagger1"], "", out, progress=False)
    ensemble = load_ensemble(out)
    assert len(ensemble.members) == 2
    assert ensemble.bootstrap["demonstrations"] == [f"{tmp_path / 'demos'}[{i}]" for i in range(3)] + [
        f"{tmp_path / 'dagger1'}[{i}]" for i in range(2)]
    assert [member.training["train_config"]["balancing"] for member in ensemble.members] == ["oversample"] * 2
    written = out.stat().st_mtime_ns
    _train_ensemble(config, [tmp_path / "demos", tmp_path / "dagger1"], "", out, progress=True)
    assert out.stat().st_mtime_ns == written and "exists, kept" in capsys.readouterr().err


def test_the_canonical_side_generalist_reflects_the_steps_that_cross_turned_left(tmp_path):
    from importlib import resources

    from ditch_drake.pipelines.generalist import GeneralistConfig, _training_samples

    # The packaged wide ditch runs along x; from y = -8 (in the approach zone) facing +y, the
    # goal at x = -8 lies 20 deg to the left, at x = +8 to the right (tests/test_terrain.py).
    for index, goal_x in enumerate((-8.0, 8.0)):
        demonstration = _numbered_frames(3)
        demonstration.arrays["image"][:, :, 0] = 200
        demonstration.arrays["bearing_stack"][:] = 0.3
        demonstration.arrays["pose"][:, :2] = [0.0, -8.0]
        demonstration.metadata.update(task={"index": 0, "name": "t", "goal": [goal_x, 11.0]},
                                      expert_style={"driver": {"straight_across_deg": 15.0,
                                                               "approach_margin_m": 2.5}})
        save_demonstration(tmp_path / "demos" / f"demo_{index:03d}.npz", demonstration)
    ditches = str(resources.files("ditch_drake.world") / "environments.yaml")
    plain = _training_samples(GeneralistConfig(), [tmp_path / "demos"], ditches)
    samples = _training_samples(GeneralistConfig(canonical_side=True), [tmp_path / "demos"], ditches)
    assert samples.demo_id.tolist() == plain.demo_id.tolist() == [0] * 3 + [1] * 3
    assert samples.label.tolist() == [16, 15, 14, 0, 1, 2]
    assert np.array_equal(samples.image[:3], plain.image[:3][..., ::-1])
    assert np.array_equal(samples.image[3:], plain.image[3:])
    assert np.allclose(samples.bearing[:3], -0.3) and np.allclose(samples.bearing[3:], 0.3)


def _with_convention(path, straight_across_deg):
    demonstration = load_demonstration(path)
    demonstration.metadata["expert_style"]["driver"]["straight_across_deg"] = straight_across_deg
    return demonstration


def test_collect_resumes_keeping_what_is_written(tmp_path):
    config = CollectConfig(environment="narrow", demos=1, seed=0, out=str(tmp_path), workers=0)
    first = collect(config, progress=False)
    store = DatasetStore.open(tmp_path)
    assert first["recorded"] == 1 and store.has_episode(0)
    written = os.path.getmtime(store.episode_path(0) / EPISODE_FILE)
    # A torn second episode (its folder without episode.json) is set aside and its slot recorded
    # again; the whole first one is kept; a killed writer's temporary folder is removed.
    store.episode_path(1).mkdir()
    (store.episode_path(1) / "label.npy").write_bytes(b"half")
    (store.episodes_dir / ".episode_000002.999999999.0123456789ab.tmp").mkdir()
    config.demos = 2
    second = collect(config, progress=False)
    assert second["kept_before"] == 1 and second["recorded"] == 1
    assert (store.episodes_dir / "episode_000001.torn" / "label.npy").read_bytes() == b"half"
    assert second["torn_episodes_set_aside"] == [str(store.episodes_dir / "episode_000001.torn")]
    assert not store.temporary_episodes()
    assert os.path.getmtime(store.episode_path(0) / EPISODE_FILE) == written
    demonstrations = load_demonstrations(tmp_path)
    assert [demo.metadata["task"]["index"] for demo in demonstrations] == [0, 1]
    assert all(demo.metadata["outcome"]["status"] == "reached_goal" for demo in demonstrations)
    assert [episode.metadata["ditch"] for episode in store.episodes()] == [
        {"name": "narrow", "seed": None, "split": "paper"}] * 2


def test_collect_refuses_bad_arguments(tmp_path):
    from ditch_drake.world.environments import ConfigError

    with pytest.raises(ConfigError, match="unknown environment 'moat'"):
        collect(CollectConfig(environment="moat", out=str(tmp_path)))
    with pytest.raises(ConfigError, match="demos=0 must be a positive integer"):
        collect(CollectConfig(demos=0, out=str(tmp_path)))
    a_file = tmp_path / "file.npz"
    a_file.write_bytes(b"keep me")
    with pytest.raises(ConfigError, match="is a file"):
        collect(CollectConfig(out=str(a_file)))
    assert a_file.read_bytes() == b"keep me"


def test_a_reused_rig_records_what_a_fresh_build_records():
    """Collection workers reuse one built diagram per task; the style is set per demonstration."""
    from ditch_drake.demos.collect import _worker_rig, record_demonstration

    config = CollectConfig(environment="narrow")
    seed = 7
    delay = draw_expert_style(seed).reaction_delay_steps
    other = next(s for s in range(20, 60) if draw_expert_style(s).reaction_delay_steps == delay)
    rig = _worker_rig(config, "narrow", 1, delay)
    record_demonstration("narrow", 1, other, rig=rig)  # Another style first, on the same rig.
    reused = record_demonstration("narrow", 1, seed, rig=rig)
    fresh = record_demonstration("narrow", 1, seed)
    assert reused.metadata["expert_style"] == fresh.metadata["expert_style"]
    for key, array in fresh.arrays.items():
        assert np.array_equal(reused.arrays[key], array), key


def test_a_person_drives_through_meshcat_and_is_recorded():
    from pydrake.geometry import Meshcat

    rig = MakeDemonstrationDiagram(SceneConfig(environment="wide"), 0, meshcat=Meshcat(), person_drives=True)
    simulator = Simulator(rig.diagram)
    simulator.AdvanceTo(1.05)
    log = rig.recorder.log(rig.recorder.GetMyContextFromRoot(simulator.get_context()))
    assert len(log) == 11
    # No key pressed: straight ahead at the paper's speed.
    assert all(step.label == actions.STRAIGHT_LABEL for step in log.steps)


def test_in_a_dagger_round_the_learner_drives_and_the_expert_labels():
    from ditch_drake.demos.collect import LABELLER_VARIATION

    rig = MakeDemonstrationDiagram(SceneConfig(environment="wide", task=1), 0, variation=LABELLER_VARIATION,
                                   learner="wide")
    simulator = Simulator(rig.diagram)
    context = simulator.get_mutable_context()
    rig.diagram.SetRandomContext(context, RandomGenerator(0))
    simulator.AdvanceTo(2.05)
    policy = rig.diagram.GetSubsystemByName("learned_policy")
    driven = rig.scene.drive.GetInputPort("command").Eval(rig.scene.drive.GetMyContextFromRoot(context))
    policy_command = policy.GetOutputPort("command").Eval(policy.GetMyContextFromRoot(context))
    assert np.array_equal(driven, policy_command)
    log = rig.recorder.log(rig.recorder.GetMyContextFromRoot(context))
    assert len(log) == 21
    # The labels are the expert's quantized answers, not the commands that were driven.
    assert all(step.label == actions.quantize(step.raw_command) for step in log.steps)


def test_a_rollover_loses_its_last_second_and_a_success_nothing():
    from ditch_drake.demos.collect import trim_rollover

    steps = 30
    arrays = {"label": np.arange(steps) % actions.NUM_LABELS, "time_s": np.arange(steps) * 0.1}
    rolled = Demonstration(arrays, {"outcome": {"status": "rolled_over"}})
    trimmed = trim_rollover(rolled)
    assert len(trimmed) == 20 and trimmed.metadata["trimmed_steps"] == 10
    assert np.array_equal(trimmed.arrays["time_s"], arrays["time_s"][:20])
    reached = Demonstration(arrays, {"outcome": {"status": "reached_goal"}})
    assert trim_rollover(reached) is reached


def test_a_dagger_collection_keeps_every_rollout_with_expert_labels(tmp_path):
    from ditch_drake.demos.collect import LABELLER_VARIATION

    with pytest.raises(FileNotFoundError, match="no_such_model"):
        collect(CollectConfig(environment="narrow", out=str(tmp_path / "bad"), learner="no_such_model.pt"))
    assert not (tmp_path / "bad").exists()
    config = CollectConfig(environment="narrow", demos=1, seed=3, out=str(tmp_path), workers=1, learner="narrow",
                           variation=LABELLER_VARIATION)
    report = collect(config, progress=False)
    assert report["recorded"] == 1 and sum(report["recorded_by_status"].values()) == 1
    (demonstration,) = load_demonstrations(tmp_path)
    assert demonstration.metadata["learner"] == "narrow" and demonstration.metadata["seed"] == 3
    shipped = resolve_checkpoint_path("narrow").read_bytes()
    assert demonstration.metadata["learner_sha256"] == hashlib.sha256(shipped).hexdigest()[:16]
    assert demonstration.metadata["outcome"]["status"] in report["recorded_by_status"]
    assert np.array_equal(demonstration.arrays["label"],
                          [actions.quantize(command) for command in demonstration.arrays["raw_command"]])
