"""The learning package (network, data, SMOTE, mirroring, metrics, training, checkpoints) and LearnedPolicy."""

import os

import numpy as np
import pytest
import torch

from ditch_drake.learning import train as train_module
from ditch_drake.learning.balance import SmoteConfig, balance, smote_samples, synthetic_counts
from ditch_drake.learning.checkpoint import (
    SCHEMA,
    CheckpointError,
    load_checkpoint,
    make_checkpoint,
    save_checkpoint,
)
from ditch_drake.learning.data import (
    SYNTHETIC_DEMO_ID,
    ArraySet,
    InputStats,
    split_by_demo,
    split_indices_by_demo,
)
from ditch_drake.learning.metrics import confusion_matrix, exact_accuracy, ordinal_accuracy
from ditch_drake.learning.mirror import mirror_left_right
from ditch_drake.learning.model import FourInputClassifier, ModelConfig, parameter_count, parameter_groups
from ditch_drake.learning.train import TrainConfig, available_precision, resume_path, train
from ditch_drake.perception.normal_image import cloud_to_normal_image
from ditch_drake.spec import actions
from ditch_drake.spec.observation_layout import IMAGE_STACK_SHAPE, IMAGE_STACK_SIZE


def make_arrays(labels, demos: int, seed: int = 0, image_dtype=np.uint8) -> ArraySet:
    """Random samples with the given labels, spread over `demos` consecutive demonstrations."""
    rng = np.random.default_rng(seed)
    labels = np.asarray(labels)
    n = len(labels)
    image = rng.integers(0, 256, (n, *IMAGE_STACK_SHAPE), dtype=np.uint8)
    if image_dtype == np.float16:
        image = (image / 255.0).astype(np.float16)
    return ArraySet(
        image=image,
        imu=rng.normal(0.0, 0.2, (n, 8)),
        distance=rng.uniform(0.0, 20.0, (n, 4)),
        bearing=rng.uniform(-3.0, 3.0, (n, 4)),
        label=labels,
        demo_id=np.arange(n) * demos // n,
    )


def skewed_labels(n: int, seed: int = 0) -> np.ndarray:
    """About 60 % label 8, the rest anywhere."""
    rng = np.random.default_rng(seed)
    return np.where(rng.random(n) < 0.6, actions.STRAIGHT_LABEL, rng.integers(0, actions.NUM_LABELS, n))


# A small and fast training configuration (the default network, few batches).
TINY = TrainConfig(epochs=2, batch_size=8, max_batches_per_epoch=3, num_threads=1, val_fraction=0.25, seed=7)


def test_model_output_shape_and_parameter_count():
    model = FourInputClassifier().eval()
    batch = 3
    logits = model(
        torch.rand(batch, *IMAGE_STACK_SHAPE), torch.zeros(batch, 8), torch.zeros(batch, 4), torch.zeros(batch, 4)
    )
    assert logits.shape == (batch, actions.NUM_LABELS)
    assert ModelConfig().image_feature_size() == 32 * 8 * 8
    assert parameter_count(model) == 160_145


def test_parameter_groups_learning_rates():
    model = FourInputClassifier()
    groups = parameter_groups(model, lr=1e-3)
    rates = {group["name"]: group["lr"] for group in groups}
    assert rates == pytest.approx({"image_and_head": 1e-3, "scalar_branches": 1e-4})
    scalar = {id(p) for group in groups if group["name"] == "scalar_branches" for p in group["params"]}
    assert scalar == {
        id(p) for branch in (model.imu_branch, model.distance_branch, model.bearing_branch) for p in branch.parameters()
    }
    every = [id(p) for group in groups for p in group["params"]]
    assert sorted(every) == sorted(id(p) for p in model.parameters())  # Each parameter exactly once.
    optimizer = torch.optim.Adam(groups)
    assert [g["lr"] for g in optimizer.param_groups] == pytest.approx([1e-3, 1e-4])


def test_array_set_validation_names_field_and_shape():
    good = make_arrays(skewed_labels(6), demos=2)
    fields = {name: getattr(good, name) for name in ArraySet.__dataclass_fields__}
    with pytest.raises(ValueError, match=r"imu has shape \(6, 7\)"):
        ArraySet(**{**fields, "imu": np.zeros((6, 7))})
    with pytest.raises(ValueError, match=r"label .* outside 0\.\.16"):
        ArraySet(**{**fields, "label": np.full(6, 17)})
    with pytest.raises(ValueError, match="distance .* non-finite"):
        ArraySet(**{**fields, "distance": np.full((6, 4), np.nan)})
    with pytest.raises(ValueError, match="image .* dtype float32"):
        ArraySet(**{**fields, "image": good.image.astype(np.float32)})
    with pytest.raises(ValueError, match=r"image has shape \(6, 4, 64, 64\)"):
        ArraySet(**{**fields, "image": np.zeros((6, 4, 64, 64), np.uint8)})
    with pytest.raises(ValueError, match=r"demo_id has shape \(5,\)"):
        ArraySet(**{**fields, "demo_id": np.zeros(5, np.int64)})
    half = make_arrays(skewed_labels(6), demos=2, image_dtype=np.float16)
    assert half.image.dtype == np.float16 and half.imu.dtype == np.float32 and half.label.dtype == np.int64


def test_split_by_demo_holds_out_whole_demonstrations():
    arrays = make_arrays(skewed_labels(50), demos=10)
    train_set, val_set = split_by_demo(arrays, val_fraction=0.2, seed=3)
    assert len(train_set) + len(val_set) == len(arrays)
    assert set(train_set.demos()).isdisjoint(val_set.demos())
    assert len(val_set.demos()) == 2 and len(train_set.demos()) == 8
    train_rows, val_rows = split_indices_by_demo(arrays.demo_id, 0.2, 3)
    assert np.array_equal(arrays.label[train_rows], train_set.label)
    assert np.array_equal(arrays.label[val_rows], val_set.label)  # Same seed, same split.
    with pytest.raises(ValueError, match="only 1 demonstration"):
        split_by_demo(make_arrays(skewed_labels(5), demos=1), 0.2, 0)


def test_smote_raises_minority_counts_from_training_data_only():
    labels = np.concatenate([[5], np.full(30, 8), np.full(6, 3), np.full(4, 12), np.full(9, 8)])
    arrays = make_arrays(labels, demos=5)
    is_val = arrays.demo_id == 4  # The last 10 rows: 1 x 12, 9 x 8.
    train_rows, val_rows = np.flatnonzero(~is_val), np.flatnonzero(is_val)
    # Mark the validation rows: no interpolation of training rows can reach these values.
    arrays.distance[val_rows] = 1000.0
    arrays.image[val_rows] = 255
    arrays.image[train_rows] = np.minimum(arrays.image[train_rows], 200)
    config = SmoteConfig(target_fraction=1.0, max_synthetic_fraction=2.0)
    synthetic = smote_samples(arrays, config, seed=1, indices=train_rows)
    before = np.bincount(arrays.label[train_rows], minlength=17)
    after = before + synthetic.label_counts()
    assert np.all(synthetic.demo_id == SYNTHETIC_DEMO_ID)
    assert np.array_equal(after > before, (before > 0) & (before < before.max()))
    assert after[8] == before[8]
    assert after[5] > before[5] == 1  # A single sample is repeated, not a crash.
    assert synthetic.distance.max() <= 20.0 and synthetic.image.max() <= 200
    assert np.array_equal(synthetic.label_counts(), synthetic_counts(before, len(train_rows), config))
    balanced = balance(arrays.take(train_rows), config, seed=1)
    assert len(balanced) == len(train_rows) + len(synthetic)


def test_synthetic_counts_respect_fraction_and_budget():
    counts = np.zeros(17, np.int64)
    counts[8], counts[7], counts[9], counts[0] = 1000, 100, 300, 1
    assert synthetic_counts(counts, 1401, SmoteConfig(target_fraction=0.5))[[0, 7, 8, 9, 10]].tolist() == [
        499,
        400,
        0,
        200,
        0,
    ]
    capped = synthetic_counts(counts, 1401, SmoteConfig(target_fraction=1.0, max_synthetic_fraction=0.5))
    assert capped.sum() <= 700 and capped[8] == 0
    assert not synthetic_counts(counts, 1401, SmoteConfig(target_fraction=0.0)).any()


def test_ordinal_accuracy_on_hand_made_examples():
    predicted = [8, 9, 10, 0, 16]
    true = [8, 8, 8, 16, 15]
    assert ordinal_accuracy(predicted, true) == pytest.approx(3 / 5)  # 8/8, 9/8, 16/15
    assert ordinal_accuracy(predicted, true, tolerance=2) == pytest.approx(4 / 5)
    assert ordinal_accuracy(predicted, true, tolerance=0) == exact_accuracy(predicted, true) == pytest.approx(1 / 5)
    assert np.isnan(ordinal_accuracy([], []))
    matrix = confusion_matrix(predicted, true)
    assert matrix.shape == (17, 17) and matrix.sum() == 5
    assert matrix[8, 9] == 1 and matrix[16, 0] == 1 and matrix[8, 8] == 1
    with pytest.raises(ValueError):
        ordinal_accuracy([1, 2], [1])


def _weights(result) -> dict[str, torch.Tensor]:
    return result.checkpoint.state_dict


def _same_weights(a, b) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _metrics(result) -> list[dict]:
    return [{k: v for k, v in record.items() if k != "seconds"} for record in result.history]


def test_tiny_training_is_deterministic_and_resumable(tmp_path, monkeypatch):
    arrays = make_arrays(skewed_labels(60), demos=6, seed=1)
    generator_state = torch.get_rng_state()
    first = train(arrays, TINY, progress=False)
    second = train(arrays, TINY, progress=False)
    assert torch.equal(torch.get_rng_state(), generator_state)  # The caller's generator is untouched.
    assert len(first.history) == 2 and 0 <= first.best_epoch <= 1
    assert _same_weights(_weights(first), _weights(second))
    assert _metrics(first) == _metrics(second)
    training = first.checkpoint.training
    assert set(training["train_demo_ids"]).isdisjoint(training["val_demo_ids"])
    assert training["num_val_samples"] == sum(training["val_label_counts"])  # No synthetic validation samples.
    val_rows = np.flatnonzero(np.isin(arrays.demo_id, training["val_demo_ids"]))
    assert training["val_label_counts"] == np.bincount(arrays.label[val_rows], minlength=17).tolist()
    train_rows = np.flatnonzero(np.isin(arrays.demo_id, training["train_demo_ids"]))
    fitted = InputStats.fit(arrays, train_rows)
    assert np.allclose(first.checkpoint.input_stats.distance_mean, fitted.distance_mean)

    # Interrupted after one epoch, then resumed to two: the same as two epochs in one go. (A
    # run that finishes removes its resume file, so the first part is an interrupted run.)
    output = tmp_path / "policy.pt"
    real_evaluate = train_module.evaluate
    calls = {"n": 0}

    def evaluate_then_interrupt(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real_evaluate(*args, **kwargs)

    monkeypatch.setattr(train_module, "evaluate", evaluate_then_interrupt)
    partial = train(arrays, TINY, progress=False, output_path=output)
    assert output.exists() and resume_path(output).exists() and len(partial.history) == 1
    monkeypatch.undo()
    resumed = train(arrays, TINY, progress=False, output_path=output, resume=True)
    assert _metrics(resumed) == _metrics(first)
    assert _same_weights(_weights(resumed), _weights(first))
    assert _same_weights(load_checkpoint(output).state_dict, _weights(first))
    assert not resume_path(output).exists()


def test_bf16_training_is_deterministic_recorded_and_differs_from_fp32():
    arrays = make_arrays(skewed_labels(60), demos=6, seed=1)
    bf16 = TrainConfig(**{**vars(TINY), "precision": "bf16"})
    first, second = train(arrays, bf16, progress=False), train(arrays, bf16, progress=False)
    assert _same_weights(_weights(first), _weights(second))
    assert all(value.dtype != torch.bfloat16 for value in _weights(first).values())  # Weights stay fp32.
    fp32 = train(arrays, TINY, progress=False)
    assert not _same_weights(_weights(first), _weights(fp32))  # The autocast took effect.
    assert first.checkpoint.summary()["device"] == "cpu bf16" and fp32.checkpoint.summary()["device"] == "cpu"


def test_training_without_the_nan_fill_gives_the_same_weights(monkeypatch):
    arrays = make_arrays(skewed_labels(60), demos=6, seed=1)
    previous = torch.utils.deterministic.fill_uninitialized_memory
    for config in (TINY, TrainConfig(**{**vars(TINY), "precision": "bf16"})):
        unfilled = train(arrays, config, progress=False)
        assert torch.utils.deterministic.fill_uninitialized_memory == previous  # Restored after training.
        monkeypatch.setattr(train_module, "FILL_UNINITIALIZED_MEMORY", True)
        filled = train(arrays, config, progress=False)
        monkeypatch.undo()
        assert _same_weights(_weights(unfilled), _weights(filled)) and _metrics(unfilled) == _metrics(filled)


def test_precision_choice_and_bad_value(monkeypatch):
    with pytest.raises(ValueError, match="precision='fp16'"):
        TrainConfig(precision="fp16")
    assert available_precision("cuda") == "fp32"
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False, raising=False)
    assert available_precision("cpu") == "fp32"
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True, raising=False)
    assert available_precision("cpu") == "bf16"


def test_training_interrupted_keeps_best_checkpoint(tmp_path, monkeypatch):
    arrays = make_arrays(skewed_labels(40), demos=4, seed=2)
    import ditch_drake.learning.train as train_module

    calls = {"n": 0}
    real_evaluate = train_module.evaluate

    def evaluate_then_interrupt(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real_evaluate(*args, **kwargs)

    monkeypatch.setattr(train_module, "evaluate", evaluate_then_interrupt)
    output = tmp_path / "policy.pt"
    result = train(arrays, TrainConfig(**{**vars(TINY), "epochs": 3}), progress=False, output_path=output)
    assert result.interrupted and result.best_epoch == 0 and len(result.history) == 1
    saved = load_checkpoint(output)
    assert saved.metrics["interrupted"] and saved.metrics["best_epoch"] == 0


def _checkpoint():
    torch.manual_seed(0)
    model = FourInputClassifier()
    stats = InputStats.fit(make_arrays(skewed_labels(10), demos=2))
    return make_checkpoint(model, stats, training={"label_counts": np.arange(17)}, metrics={"best_epoch": 3})


def test_checkpoint_round_trip(tmp_path):
    checkpoint = _checkpoint()
    path = save_checkpoint(checkpoint, tmp_path / "sub" / "policy.pt")
    assert [p.name for p in path.parent.iterdir()] == ["policy.pt"]  # No temporary file left.
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # Readable as any other file, not 0600.
    loaded = load_checkpoint(path)
    assert loaded.model_config == checkpoint.model_config and loaded.path == path
    assert _same_weights(loaded.state_dict, checkpoint.state_dict)
    assert np.array_equal(loaded.action_commands, actions.COMMANDS)
    assert loaded.training["label_counts"] == list(range(17)) and loaded.metrics == {"best_epoch": 3}
    assert np.array_equal(loaded.input_stats.imu_std, checkpoint.input_stats.imu_std)
    inputs = (torch.rand(2, *IMAGE_STACK_SHAPE), torch.randn(2, 8), torch.rand(2, 4) * 10, torch.randn(2, 4))
    with torch.no_grad():
        assert torch.equal(loaded.build_model()(*inputs), checkpoint.build_model()(*inputs))


def test_checkpoint_errors_name_the_file(tmp_path):
    path = save_checkpoint(_checkpoint(), tmp_path / "policy.pt")
    data = path.read_bytes()
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(data[: len(data) // 2])
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all")
    foreign = tmp_path / "foreign.pt"
    torch.save({"schema": "something.else", "schema_version": 1}, foreign)
    newer = tmp_path / "newer.pt"
    torch.save({"schema": SCHEMA, "schema_version": 99}, newer)
    code = tmp_path / "code.pt"
    torch.save({"schema": SCHEMA, "schema_version": 1, "model_config": ModelConfig()}, code)
    for bad in (truncated, garbage, foreign, newer, code):
        with pytest.raises(CheckpointError, match=bad.name) as error:
            load_checkpoint(bad)
        assert SCHEMA in str(error.value) or "schema_version" in str(error.value)
    payload = torch.load(path, weights_only=True)
    del payload["state_dict"]["head.3.bias"]
    broken = tmp_path / "broken.pt"
    torch.save(payload, broken)
    with pytest.raises(CheckpointError, match="broken.pt.*head.3.bias"):
        load_checkpoint(broken)
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_checkpoint(tmp_path / "missing.pt")


def test_learned_policy_commands_an_action():
    from pydrake.systems.analysis import Simulator

    from ditch_drake.systems.policy import LearnedPolicy

    policy = LearnedPolicy(_checkpoint())
    context = policy.CreateDefaultContext()
    rng = np.random.default_rng(0)
    policy.GetInputPort("image_stack").FixValue(context, rng.random(IMAGE_STACK_SIZE))
    policy.GetInputPort("imu_stack").FixValue(context, rng.normal(0.0, 0.2, 8))
    policy.GetInputPort("distance_stack").FixValue(context, [5.0, 5.1, 5.2, 5.3])
    policy.GetInputPort("bearing_stack").FixValue(context, [0.3, 0.3, 0.2, 0.2])
    assert policy.GetOutputPort("label").Eval(context)[0] == -1  # Before the first update.
    state = policy.AllocateDiscreteVariables()
    policy.CalcForcedDiscreteVariableUpdate(context, state)
    context.SetDiscreteState(state)
    command = policy.GetOutputPort("command").Eval(context)
    label = policy.GetOutputPort("label").Eval(context)[0]
    probabilities = policy.GetOutputPort("probabilities").Eval(context)
    assert np.any(np.all(np.isclose(actions.COMMANDS, command), axis=1))
    assert label == int(np.argmax(probabilities)) and np.array_equal(command, actions.COMMANDS[int(label)])
    assert probabilities.shape == (17,) and probabilities.sum() == pytest.approx(1.0) and probabilities.min() >= 0

    # The periodic update runs at the control rate too.
    simulator = Simulator(policy, policy.CreateDefaultContext())
    for name, value in (("image_stack", np.zeros(IMAGE_STACK_SIZE)), ("imu_stack", np.zeros(8))):
        policy.GetInputPort(name).FixValue(simulator.get_mutable_context(), value)
    for name in ("distance_stack", "bearing_stack"):
        policy.GetInputPort(name).FixValue(simulator.get_mutable_context(), np.ones(4))
    simulator.AdvanceTo(0.15)
    assert policy.GetOutputPort("label").Eval(simulator.get_context())[0] >= 0


def _batch(n: int = 5) -> dict:
    arrays = make_arrays(np.arange(n) * 4 % actions.NUM_LABELS, demos=1, seed=3)
    return {name: getattr(arrays, name).copy() for name in ("image", "imu", "distance", "bearing", "label")}


def test_mirror_reflects_the_chosen_samples_and_twice_is_identity():
    original = _batch()
    batch = {name: values.copy() for name, values in original.items()}
    rows = np.array([True, False, True, True, False])
    mirror_left_right(batch, rows)
    assert np.array_equal(batch["image"][rows], original["image"][rows][..., ::-1])
    assert np.array_equal(batch["imu"][rows][:, 0::2], -original["imu"][rows][:, 0::2])  # roll
    assert np.array_equal(batch["imu"][rows][:, 1::2], original["imu"][rows][:, 1::2])  # pitch
    assert np.array_equal(batch["bearing"][rows], -original["bearing"][rows])
    assert np.array_equal(batch["distance"], original["distance"])
    assert batch["label"][rows].tolist() == [16 - label for label in original["label"][rows]]
    for name in original:
        assert np.array_equal(batch[name][~rows], original[name][~rows])
    mirror_left_right(batch, rows)
    for name in original:
        assert np.array_equal(batch[name], original[name])


def test_mirrored_label_turns_the_other_way_at_the_same_speed():
    for label in range(actions.NUM_LABELS):
        v, w = actions.label_to_command(label)
        assert actions.label_to_command(actions.NUM_LABELS - 1 - label).tolist() == pytest.approx([v, -w])


def test_reflected_cloud_gives_the_column_reversed_normal_image():
    # A surface that is not symmetric about y = 0, with its exact normals.
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0.5, 4.0, 4000), rng.uniform(-2.0, 1.0, 4000)
    z = 0.4 * y + 0.2 * y**2 - 0.1 * x
    normals = np.column_stack([np.full_like(x, 0.1), -(0.4 + 0.4 * y), np.ones_like(x)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    image = cloud_to_normal_image(np.column_stack([x, y, z]), normals=normals)
    reflected = cloud_to_normal_image(np.column_stack([x, -y, z]), normals=normals * [1.0, -1.0, 1.0])
    assert image.any()
    np.testing.assert_allclose(reflected, image[:, ::-1], atol=1e-5)


def test_a_canonical_side_policy_reflects_its_view_and_its_answer_when_told_to_cross_left():
    from ditch_drake.systems.policy import LearnedPolicy

    assert not LearnedPolicy(_checkpoint()).HasInputPort("crossing_side")
    torch.manual_seed(0)
    policy = LearnedPolicy(make_checkpoint(FourInputClassifier(ModelConfig(canonical_side=True))))
    rng = np.random.default_rng(1)
    image, imu, distance, bearing = rng.random(IMAGE_STACK_SIZE), rng.normal(0, 0.2, 8), rng.random(4) * 9, rng.normal(
        0, 0.5, 4)
    reflected = {"image": image.reshape(IMAGE_STACK_SHAPE)[None].copy(), "imu": imu[None].copy(),
                 "bearing": bearing[None].copy(), "label": np.zeros(1, dtype=np.int64)}
    mirror_left_right(reflected)
    right_label, right = policy.infer(reflected["image"], reflected["imu"], distance, reflected["bearing"], 1.0)
    context = policy.CreateDefaultContext()
    for name, value in (("image_stack", image), ("imu_stack", imu), ("distance_stack", distance),
                        ("bearing_stack", bearing), ("crossing_side", [-1.0])):
        policy.GetInputPort(name).FixValue(context, value)
    state = policy.AllocateDiscreteVariables()
    policy.CalcForcedDiscreteVariableUpdate(context, state)
    context.SetDiscreteState(state)
    assert policy.GetOutputPort("label").Eval(context)[0] == actions.NUM_LABELS - 1 - right_label
    assert np.allclose(policy.GetOutputPort("probabilities").Eval(context), right[::-1])
    assert np.array_equal(policy.GetOutputPort("command").Eval(context),
                          actions.COMMANDS[actions.NUM_LABELS - 1 - right_label])
    # Told right, it answers for the view as it is.
    policy.GetInputPort("crossing_side").FixValue(context, [1.0])
    policy.CalcForcedDiscreteVariableUpdate(context, state)
    context.SetDiscreteState(state)
    assert np.allclose(policy.GetOutputPort("probabilities").Eval(context),
                       policy.infer(image, imu, distance, bearing)[1])
