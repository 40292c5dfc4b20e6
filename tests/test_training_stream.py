"""Training from a dataset folder with its images on disk: the same samples and batches as the
in-memory path, the class balancing methods, and bad stores refused by name."""

import os
import warnings

import numpy as np
import pytest
import torch

from ditch_drake.common.errors import ConfigError, DatasetError
from ditch_drake.demos.dataset import (
    reflected,
    restack_images,
    to_array_set,
)
from ditch_drake.demos.store import DatasetStore, load_demonstrations
from ditch_drake.demos.training_set import dataset_episodes, load_training_set, training_set
from ditch_drake.learning.balance import (
    BALANCING,
    balance_training_split,
    balanced_class_weights,
    ordinal_soft_targets,
    synthetic_counts,
)
from ditch_drake.learning.config import BALANCING_METHODS, TrainConfig
from ditch_drake.learning.data import ArraySet, InputStats
from ditch_drake.learning.mirror import mirror_left_right
from ditch_drake.learning.stream import LazyImageStack, NpyRows, TrainingSamples, batch_loader, epoch_batches
from ditch_drake.learning.train import train

STEPS = (9, 6, 11, 5)
# A small and fast training configuration.
TINY = TrainConfig(epochs=1, batch_size=8, max_batches_per_epoch=2, num_threads=1, val_fraction=0.25, seed=3,
                   eval_batch_size=16)


@pytest.fixture
def store_path(tmp_path, random_demonstration):
    store = DatasetStore.create(tmp_path / "store")
    for index, steps in enumerate(STEPS):
        store.append(random_demonstration(index, steps))
    return tmp_path / "store"


def _same_sets(streamed: ArraySet, in_memory: ArraySet) -> None:
    assert not isinstance(streamed.image, np.ndarray) and isinstance(in_memory.image, np.ndarray)
    for name in ("imu", "distance", "bearing", "label", "demo_id"):
        assert np.array_equal(getattr(streamed, name), getattr(in_memory, name)), name
        assert getattr(streamed, name).dtype == getattr(in_memory, name).dtype, name
    assert streamed.image.shape == in_memory.image.shape and streamed.image.dtype == in_memory.image.dtype
    assert np.array_equal(streamed.image[np.arange(len(streamed))], in_memory.image)


def test_a_store_streams_the_samples_of_the_in_memory_path_with_strides_and_reflections(store_path):
    demonstrations = load_demonstrations(store_path)
    episodes = dataset_episodes(store_path)
    assert [episode.steps for episode in episodes] == list(STEPS)
    _same_sets(load_training_set([store_path]), to_array_set(demonstrations))

    # The generalist's recipes as they were made in memory: a reflected copy of a whole
    # episode (mirror), and the steps of one side reflected in place (canonical side).
    strides = [1, 2, 3, 1, 2]
    steps_kept = [len(range(0, demo.arrays["label"].shape[0], s)) for demo, s in
                  zip([*demonstrations, demonstrations[1]], strides, strict=True)]
    side = np.random.default_rng(0).random(steps_kept[2]) < 0.5
    reflect = [False, False, side, False, True]
    streamed = training_set([*episodes, episodes[1]], strides, reflect, first_demo_id=5)
    in_memory = to_array_set([*demonstrations, reflected(demonstrations[1])], 5, strides)
    rows = np.zeros(len(in_memory), bool)
    start = sum(steps_kept[:2])
    rows[start : start + steps_kept[2]] = side
    mirror_left_right({name: getattr(in_memory, name) for name in ("image", "imu", "bearing", "label")}, rows)
    _same_sets(streamed, in_memory)

    # Any rows, in any order, repeated; an integer; a slice.
    picks = np.array([7, 0, 7, len(in_memory) - 1, 3])
    assert np.array_equal(streamed.image[picks], in_memory.image[picks])
    assert np.array_equal(streamed.image[-2], in_memory.image[-2])
    assert np.array_equal(streamed.image[2:9:3], in_memory.image[2:9:3])
    # The stacks are restack_images' (newest first, zeros before the start).
    frames = demonstrations[2].arrays["image"]
    expected = restack_images(frames, stride=3)
    expected[side] = expected[side][..., ::-1]
    first = sum(steps_kept[:2])
    assert np.array_equal(streamed.image[np.arange(first, first + steps_kept[2])], expected)


def test_a_lazy_stack_of_callables_with_few_open_files_equals_restack_images():
    rng = np.random.default_rng(1)
    frames = [rng.integers(0, 256, (steps, 128, 128), dtype=np.uint8) for steps in (5, 3, 7)]
    episode = np.repeat(np.arange(3), [5, 3, 7])
    step = np.concatenate([np.arange(5), np.arange(3), np.arange(7)])
    reflect = rng.random(15) < 0.5
    opened = []

    def opener(index):
        def open_frames():
            opened.append(index)
            return frames[index]
        return open_frames

    stack = LazyImageStack([opener(i) for i in range(3)], episode, step, reflect, max_open=1)
    expected = np.concatenate([restack_images(f) for f in frames])
    expected[reflect] = expected[reflect][..., ::-1]
    order = rng.permutation(15)
    assert np.array_equal(stack[order], expected[order])
    assert stack.shape == (15, 4, 128, 128) and stack.dtype == np.uint8 and len(stack) == 15
    assert opened == [0, 1, 2]  # Each episode's rows read together, one open at a time.
    with pytest.raises(DatasetError, match="a sample is of step 7"):
        LazyImageStack([lambda: frames[0]], np.zeros(1), [7])[0]


def test_the_loader_gives_the_in_memory_batches_and_training_the_same_weights(store_path):
    streamed, in_memory = load_training_set([store_path]), to_array_set(load_demonstrations(store_path))
    rows = np.arange(3, len(in_memory))
    order = np.random.default_rng([0, 2, 0]).permutation(len(rows))
    batches = epoch_batches(order, 8)
    assert [len(batch) for batch in batches][-1] >= 2 and sum(map(len, batches)) >= len(rows) - 1
    memory = list(batch_loader(TrainingSamples(in_memory, rows), batches))
    for workers in (0, 2):  # Each worker process opens its own files.
        loaded = list(batch_loader(TrainingSamples(streamed, rows), batches, num_workers=workers))
        assert len(loaded) == len(memory)
        for ours, theirs in zip(loaded, memory, strict=True):
            assert all(torch.equal(a, b) for a, b in zip(ours, theirs, strict=True))
    # The whole of training, SMOTE's samples (written to a file when streaming) included.
    first, second = train(streamed, TINY, progress=False), train(in_memory, TINY, progress=False)
    assert first.checkpoint.training["num_synthetic_samples"] > 0
    assert all(torch.equal(value, second.checkpoint.state_dict[name])
               for name, value in first.checkpoint.state_dict.items())
    assert first.history[0]["val_loss"] == second.history[0]["val_loss"]


def _tiny_set(seed: int = 0) -> tuple[ArraySet, np.ndarray]:
    rng = np.random.default_rng(seed)
    labels = np.concatenate([np.full(60, 8), np.full(12, 6), np.full(4, 11), [2]])
    n = len(labels)
    arrays = ArraySet(image=rng.integers(0, 256, (n, 4, 128, 128), dtype=np.uint8),
                      imu=rng.normal(size=(n, 8)), distance=rng.uniform(0, 20, (n, 4)),
                      bearing=rng.uniform(-3, 3, (n, 4)), label=rng.permutation(labels), demo_id=np.arange(n) // 10)
    return arrays, np.arange(n)


def test_every_balancing_method_is_registered_and_a_bad_name_is_refused():
    assert tuple(BALANCING) == BALANCING_METHODS
    with pytest.raises(ConfigError, match=r"balancing='smot': expected one of .*\(--balancing\)"):
        TrainConfig(balancing="smot")
    with pytest.raises(ConfigError, match=r"soft_label_sigma=0"):
        TrainConfig(soft_label_sigma=0)
    with pytest.raises(ConfigError, match=r"num_workers=-1.*\(--loader-workers\)"):
        TrainConfig(num_workers=-1)


def test_each_balancing_method_changes_what_it_should():
    arrays, rows = _tiny_set()
    counts = np.bincount(arrays.label, minlength=17)
    stats = InputStats.fit(arrays, rows)
    made = {method: balance_training_split(arrays, rows, stats, TrainConfig(balancing=method))
            for method in BALANCING_METHODS}
    for method, balancing in made.items():
        assert balancing.method == method and balancing.seconds >= 0
    assert np.array_equal(made["none"].rows, rows) and made["none"].synthetic is None
    # SMOTE makes new samples; oversampling draws rows again, as many per class, no copies.
    todo = synthetic_counts(counts, len(rows), TrainConfig().smote)
    assert np.array_equal(made["smote"].synthetic.label_counts(), todo)
    extra = made["oversample"].rows[len(rows):]
    assert np.array_equal(made["oversample"].rows[: len(rows)], rows)
    assert np.array_equal(np.bincount(arrays.label[extra], minlength=17), todo) and todo[8] == 0
    # The sampler's draws are seeded and favour the minority classes.
    sampler = made["weighted_sampler"]
    assert np.array_equal(sampler.epoch_order(3, 1), sampler.epoch_order(3, 1))
    assert not np.array_equal(sampler.epoch_order(3, 1), sampler.epoch_order(3, 2))
    drawn = np.concatenate([arrays.label[sampler.epoch_order(3, epoch)] for epoch in range(20)])
    assert np.mean(drawn == 8) < 0.5 * counts[8] / len(rows) and np.mean(drawn == 11) > 2 * counts[11] / len(rows)
    assert sorted(made["none"].epoch_order(3, 1)) == list(range(len(rows)))  # Otherwise a permutation.
    # Class weights inverse to the counts; absent classes weigh nothing.
    weights = made["class_weights"].class_weights
    present = counts > 0
    assert np.allclose(weights[present] * counts[present], weights[8] * counts[8]) and not weights[~present].any()
    assert np.isclose((weights[arrays.label]).mean(), 1.0)
    assert np.array_equal(weights, balanced_class_weights(counts))
    # Soft labels: each row sums to 1, peaks at its label and falls off with the distance.
    targets = made["ordinal_soft_labels"].soft_targets
    assert np.allclose(targets.sum(axis=1), 1.0) and np.array_equal(targets.argmax(axis=1), np.arange(17))
    assert targets[8, 7] == pytest.approx(targets[8, 9]) and targets[8, 9] > targets[8, 10] > 0
    assert np.all(ordinal_soft_targets(0.5)[8, 7] < targets[8, 7])  # Narrower: less to the neighbours.


@pytest.fixture(scope="module")
def unbalanced_weights():
    arrays, _ = _tiny_set(1)
    return train(arrays, TrainConfig(**{**vars(TINY), "balancing": "none", "max_batches_per_epoch": 1}),
                 progress=False).checkpoint.state_dict


@pytest.mark.parametrize("method", ["oversample", "weighted_sampler", "class_weights", "ordinal_soft_labels"])
def test_training_runs_with_each_method_and_records_its_time(method, unbalanced_weights):
    arrays, _ = _tiny_set(1)
    config = TrainConfig(**{**vars(TINY), "balancing": method, "max_batches_per_epoch": 1})
    result = train(arrays, config, progress=False)
    training = result.checkpoint.training
    assert training["balancing"] == method and training["balancing_seconds"] >= 0
    assert training["smote_seconds"] == 0.0 and training["train_config"]["balancing"] == method
    assert result.checkpoint.metrics["training_seconds"] >= training["balancing_seconds"]
    # Other batches (oversample, sampler) or another loss (weights, soft targets): other weights.
    assert not torch.equal(result.checkpoint.state_dict["head.3.weight"], unbalanced_weights["head.3.weight"])


def test_a_torn_episode_is_never_read(store_path):
    store = DatasetStore.open(store_path)
    torn = store.episodes_dir / f".episode_000009.{os.getpid()}.0123456789ab.tmp"
    unfinished = store.episode_path(8)  # A folder without its episode.json.
    for folder in (torn, unfinished):
        folder.mkdir()
        (folder / "image.npy").write_bytes(b"not an array")
        (folder / "label.npy").write_bytes(b"not an array")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        arrays = load_training_set([store_path])
    assert any("torn episode" in str(warning.message) for warning in caught)
    assert len(arrays) == sum(STEPS)
    assert {os.path.dirname(path) for path in arrays.image.frames} == {
        str(store.episode_path(index)) for index in range(len(STEPS))}
    assert arrays.image[np.arange(len(arrays))].shape == (sum(STEPS), 4, 128, 128)


def test_mismatched_array_lengths_are_refused_naming_the_file(store_path):
    store = DatasetStore.open(store_path)
    episode = store.episode_path(1)
    np.save(episode / "imu_stack.npy", np.zeros((STEPS[1] - 1, 8), np.float32))
    with pytest.raises(DatasetError, match=r"episode_000001/imu_stack.npy: array 'imu_stack' has shape \(5, 8\)"):
        load_training_set([store_path])
    np.save(episode / "imu_stack.npy", np.zeros((STEPS[1], 8), np.float32))
    np.save(episode / "image.npy", np.zeros((STEPS[1] + 2, 128, 128), np.uint8))
    with pytest.raises(DatasetError, match=r"episode_000001/image.npy: array 'image' has shape \(8, 128, 128\)"):
        load_training_set([store_path])


def test_a_truncated_frame_file_is_refused_naming_it(tmp_path):
    path = tmp_path / "image.npy"
    np.save(path, np.zeros((4, 128, 128), np.uint8))
    os.truncate(path, os.path.getsize(path) - 100)
    with pytest.raises(DatasetError, match=r"image.npy: .* a torn file"):
        NpyRows(path)
    with pytest.raises(DatasetError, match=r"image.npy: .* a torn file"):
        LazyImageStack([path], [0], [0])


@pytest.mark.slow
def test_the_bench_measures_streaming_memory_at_two_sizes():
    from ditch_drake.perf.bench_training import measure_streaming_memory

    figures = measure_streaming_memory(samples=400, scale=2)
    assert figures["train_peak_rss_mib"] > 0 and figures["train_peak_rss_8x_mib"] > 0
    assert {f"balancing_{method}_s" for method in BALANCING_METHODS if method != "smote"} <= set(figures)


@pytest.mark.parametrize("recipe", [{"mirror": True}, {"canonical_side": True}])
def test_the_generalists_samples_from_a_store_equal_those_from_npz_files(tmp_path, recipe, random_demonstration):
    from importlib import resources

    from ditch_drake.demos.dataset import save_demonstration
    from ditch_drake.demos.store import convert_npz_folder
    from ditch_drake.pipelines.generalist import GeneralistConfig, _training_samples

    # The packaged wide ditch: task 1 turns 24 deg (mirrored), task 0 runs square (not); from y = -8
    # facing +y the goal at x = -8 lies to the left (reflected with the canonical side), at +8 right.
    for folder, seed in (("demos", 0), ("dagger1", 10)):
        for index, (task, goal_x) in enumerate(((1, -8.0), (0, 8.0), (1, 8.0))):
            demonstration = random_demonstration(seed + index, 5 + index)
            demonstration.arrays["pose"][:, :2] = [0.0, -8.0]
            demonstration.metadata.update(task={"index": task, "name": "t", "goal": [goal_x, 11.0]},
                                          expert_style={"driver": {"straight_across_deg": 15.0,
                                                                   "approach_margin_m": 2.5}})
            save_demonstration(tmp_path / "npz" / folder / f"demo_{index:03d}.npz", demonstration)
        convert_npz_folder(tmp_path / "npz" / folder, tmp_path / "store" / folder, progress=False)
    ditches = str(resources.files("ditch_drake.world") / "environments.yaml")
    config = GeneralistConfig(dagger_stride=2, **recipe)
    streamed = _training_samples(config, [tmp_path / "store" / "demos", tmp_path / "store" / "dagger1"], ditches)
    in_memory = _training_samples(config, [tmp_path / "npz" / "demos", tmp_path / "npz" / "dagger1"], ditches)
    _same_sets(streamed, in_memory)
    assert streamed.image.reflect.any() and not streamed.image.reflect.all()
