"""The dataset store: episodes written whole, read back equal, torn ones skipped, bad folders refused."""

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from ditch_drake.cli import main
from ditch_drake.common.errors import DatasetError
from ditch_drake.demos.dataset import Demonstration, save_demonstration, standard_metadata
from ditch_drake.demos.store import (
    EPISODE_FILE,
    FIELDS,
    STORE_FILE,
    DatasetStore,
    convert_npz_folder,
    demonstration_metadata,
    load_demonstrations,
    store_summary,
)
from ditch_drake.spec import actions


def _random_demonstration(seed: int, steps: int = 7, environment: str = "ditch_0012") -> Demonstration:
    rng = np.random.default_rng(seed)
    arrays = {
        "image": rng.integers(0, 256, (steps, 128, 128), dtype=np.uint8),
        "imu_stack": rng.normal(size=(steps, 8)).astype(np.float32),
        "distance_stack": rng.uniform(0, 20, (steps, 4)).astype(np.float32),
        "bearing_stack": rng.uniform(-3, 3, (steps, 4)).astype(np.float32),
        "label": rng.integers(0, actions.NUM_LABELS, steps).astype(np.int16),
        "time_s": np.arange(steps) * 0.1 + rng.uniform(),
        "pose": rng.normal(size=(steps, 6)).astype(np.float32),
        "raw_command": rng.normal(size=(steps, 2)).astype(np.float32),
    }
    metadata = standard_metadata(environment=environment, task={"index": seed % 3, "name": f"task{seed % 3}"},
                                 seed=seed, outcome={"status": "reached_goal"}, control_period_s=0.1)
    return Demonstration(arrays, metadata)


def test_an_npz_folder_converts_losslessly_and_a_rerun_converts_only_the_rest(tmp_path):
    source = tmp_path / "npz"
    originals = {index: _random_demonstration(index, steps=5 + index) for index in (0, 1, 3)}
    for index, demonstration in originals.items():
        save_demonstration(source / f"demo_{index:03d}.npz", demonstration)
    first = convert_npz_folder(source, tmp_path / "store", progress=False)
    assert (first["converted"], first["kept"], first["steps"]) == (3, 0, 5 + 6 + 8)
    store = DatasetStore.open(tmp_path / "store")
    episodes = store.episodes()
    assert [episode.index for episode in episodes] == [0, 1, 3]
    for episode in episodes:
        original = originals[episode.index]
        arrays = store.read(episode)
        for name in original.arrays:
            assert arrays[name].dtype == original.arrays[name].dtype
            assert np.array_equal(arrays[name], original.arrays[name]), name
        assert not arrays["intervention"].any()
        assert demonstration_metadata(episode.metadata) == original.metadata
        assert episode.metadata["ditch"] == {"name": "ditch_0012", "seed": 12, "split": "train"}
    second = convert_npz_folder(source, tmp_path / "store", progress=False)
    assert (second["converted"], second["kept"]) == (0, 3)
    assert [d.metadata["seed"] for d in load_demonstrations(tmp_path / "store")] == [0, 1, 3]


def test_appending_writes_whole_episodes_and_never_overwrites(tmp_path):
    store = DatasetStore.create(tmp_path / "d")
    first = store.append(_random_demonstration(0), intervention=np.array([0, 0, 1, 1, 0, 0, 0], bool))
    second = store.append(_random_demonstration(1))
    assert (first.name, second.name) == ("episode_000000", "episode_000001")
    assert sorted(path.name for path in first.path.iterdir()) == sorted([*(f"{name}.npy" for name in FIELDS),
                                                                           EPISODE_FILE])
    assert not store.temporary_episodes()
    with pytest.raises(DatasetError, match="episode_000001 exists"):
        store.append(_random_demonstration(2), index=1)
    assert store.read(first, ["intervention"])["intervention"].tolist() == [0, 0, 1, 1, 0, 0, 0]
    mapped = store.read(first, ["image"])["image"]
    assert isinstance(mapped, np.memmap) and not mapped.flags.writeable
    summary = store_summary(store)
    assert (summary["episodes"], summary["steps"], summary["intervened_steps"]) == (2, 14, 2)
    assert summary["per_split"] == {"train": 2}
    assert DatasetStore.create(tmp_path / "d").root == store.root  # Opening, not replacing, a store.


def test_a_torn_episode_is_skipped_with_a_warning_and_never_half_read(tmp_path):
    store = DatasetStore.create(tmp_path / "d")
    store.append(_random_demonstration(0))
    torn = store.episode_path(1)
    torn.mkdir()
    np.save(torn / "label.npy", np.zeros(3, np.int16))
    (store.episodes_dir / ".episode_000002.999999999.0123456789ab.tmp").mkdir()
    with pytest.warns(UserWarning, match="skipped 2 torn episode"):
        episodes = store.episodes()
    assert [episode.index for episode in episodes] == [0]
    with pytest.warns(UserWarning):
        assert len(load_demonstrations(tmp_path / "d")) == 1
    assert [path.name for path in store.remove_stale_episodes()] == [".episode_000002.999999999.0123456789ab.tmp"]


def test_a_killed_writer_leaves_no_episode_only_a_temporary(tmp_path):
    store = DatasetStore.create(tmp_path / "d")
    code = ("import os, numpy as np\n"
            "from ditch_drake.demos import store as s\n"
            "real = s._write_synced\n"
            "def dying(path, write):\n"
            "    real(path, write)\n"
            "    if path.name == 'label.npy': os._exit(9)\n"
            "s._write_synced = dying\n"
            "from tests.test_dataset_store import _random_demonstration\n"
            f"s.DatasetStore.open({str(store.root)!r}).append(_random_demonstration(0))\n")
    completed = subprocess.run([sys.executable, "-c", code], check=False, cwd=os.path.dirname(os.path.dirname(__file__)))
    assert completed.returncode == 9
    assert not store.episode_path(0).exists() and len(store.temporary_episodes()) == 1
    with pytest.warns(UserWarning, match="torn"):
        assert store.episodes() == []
    time.sleep(0.1)
    assert len(store.remove_stale_episodes()) == 1 and not store.temporary_episodes()


def test_bad_folders_are_refused_naming_the_file(tmp_path, capsys):
    store = DatasetStore.create(tmp_path / "d")
    episode = store.append(_random_demonstration(0))
    np.save(episode.field_path("pose"), np.zeros((3, 6), np.float32))
    with pytest.raises(DatasetError, match=r"pose.npy: array 'pose' has shape \(3, 6\).*expected \(7, 6\)"):
        store.read(episode)
    header = json.loads((store.root / STORE_FILE).read_text())
    (store.root / STORE_FILE).write_text(json.dumps({**header, "schema_version": 99}))
    with pytest.raises(DatasetError, match="schema_version 99 is unknown; expected 1"):
        DatasetStore.open(store.root)
    assert main(["dataset", "info", str(store.root)]) == 2
    assert "schema_version 99" in capsys.readouterr().err
    assert main(["dataset", "info", str(tmp_path / "missing")]) == 2
    assert main(["dataset", "convert", str(tmp_path / "missing"), str(tmp_path / "out")]) == 2
    (tmp_path / "a_file").write_text("")
    with pytest.raises(DatasetError, match="a_file/d cannot be made: Not a directory"):
        DatasetStore.create(tmp_path / "a_file" / "d")


def test_dataset_info_reads_a_store(tmp_path, capsys):
    store = DatasetStore.create(tmp_path / "d")
    for seed in range(3):
        store.append(_random_demonstration(seed))
    assert main(["dataset", "info", str(store.root), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["episodes"], summary["steps"], summary["per_environment"]) == (3, 21, {"ditch_0012": 3})
