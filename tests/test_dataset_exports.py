"""Exports: a LeRobotDataset v3 folder and a robomimic HDF5 file that read back equal to the store."""

import io
import json

import numpy as np
import pytest

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError, DatasetError
from ditch_drake.demos import exports, lerobot_export
from ditch_drake.demos.dataset import Demonstration, standard_metadata
from ditch_drake.demos.exports import export_dataset
from ditch_drake.demos.store import DatasetStore
from ditch_drake.spec import actions

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
h5py = pytest.importorskip("h5py")
Image = pytest.importorskip("PIL.Image")

# Stored index -> (steps, environment, task index): a gap in the indices (2), a generated ditch
# of the train split, one of the val split and a packaged environment (the paper's split).
EPISODES = {0: (6, "ditch_0012", 0), 1: (4, "ditch_1003", 1), 3: (7, "wide", 0)}


def _demonstration(index: int) -> Demonstration:
    steps, environment, task = EPISODES[index]
    rng = np.random.default_rng(index)
    arrays = {
        "image": rng.integers(0, 256, (steps, 128, 128), dtype=np.uint8),
        "imu_stack": rng.normal(size=(steps, 8)).astype(np.float32),
        "distance_stack": rng.uniform(0, 20, (steps, 4)).astype(np.float32),
        "bearing_stack": rng.uniform(-3, 3, (steps, 4)).astype(np.float32),
        "label": rng.integers(0, actions.NUM_LABELS, steps).astype(np.int16),
        "time_s": np.arange(steps) * 0.1 + 0.004,
        "pose": rng.normal(size=(steps, 6)).astype(np.float32),
        "raw_command": rng.normal(size=(steps, 2)).astype(np.float32),
        "intervention": rng.random(steps) < 0.5,
    }
    task_info = {"index": task, "name": f"task{task}", "start": [0.0, -11.0, 90.0], "goal": [float(task), 11.0]}
    status = "reached_goal" if index != 1 else "rolled_over"
    metadata = standard_metadata(environment=environment, task=task_info, seed=index, outcome={"status": status},
                                 control_period_s=0.1)
    return Demonstration(arrays, metadata)


@pytest.fixture
def store(tmp_path):
    store = DatasetStore.create(tmp_path / "store")
    for index in EPISODES:
        store.append(_demonstration(index), index)
    return store


def _sources(store):
    return [store.load(episode).arrays for episode in store.episodes()]


def _png_pixels(cell: dict) -> np.ndarray:
    assert cell["path"] is None
    return np.array(Image.open(io.BytesIO(cell["bytes"])))


def test_lerobot_export_reads_back_equal(store, tmp_path):
    out = tmp_path / "lerobot"
    summary = export_dataset(store.root, "lerobot", out, progress=False)
    sources = _sources(store)
    frames = sum(len(arrays["label"]) for arrays in sources)
    assert (summary["episodes"], summary["frames"], summary["fps"]) == (3, frames, 10)

    info = json.loads((out / "meta/info.json").read_text())
    assert info["codebase_version"].startswith("v3")
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"], info["fps"]) == (3, frames, 3, 10)
    assert info["robot_type"] == "husky" and info["video_path"] is None
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["features"]["observation.image"] == {"dtype": "image", "shape": [128, 128, 1],
                                                     "names": ["height", "width", "channels"]}
    assert info["features"]["observation.state"]["names"][:3] == ["roll_t", "pitch_t", "roll_t-1"]
    assert len(info["features"]["observation.state"]["names"]) == 16

    tasks = pq.read_table(out / "meta/tasks.parquet").to_pylist()
    task_of = {row["task_index"]: row["task"] for row in tasks}
    assert task_of[0] == "cross the ditch ditch_0012 from (0, -11) to (0, 11)"

    episodes = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    data = pq.read_table(out / "data/chunk-000/file-000.parquet")
    assert sorted(data.column_names) == sorted(info["features"])
    rows = data.to_pylist()
    assert len(rows) == frames
    first = 0
    for new_index, (row, arrays) in enumerate(zip(episodes, sources)):
        steps = len(arrays["label"])
        assert (row["episode_index"], row["length"]) == (new_index, steps)
        assert (row["dataset_from_index"], row["dataset_to_index"]) == (first, first + steps)
        assert (row["data/chunk_index"], row["data/file_index"]) == (0, 0)
        assert row["source_episode"] == store.episodes()[new_index].name
        assert row["intervened_steps"] == int(arrays["intervention"].sum())
        for t, frame in enumerate(rows[first:first + steps]):
            assert (frame["index"], frame["episode_index"], frame["frame_index"]) == (first + t, new_index, t)
            assert task_of[frame["task_index"]] == row["tasks"][0]
            assert np.array_equal(_png_pixels(frame["observation.image"]), arrays["image"][t])
            state = np.concatenate([arrays["imu_stack"][t], arrays["distance_stack"][t], arrays["bearing_stack"][t]])
            assert np.array_equal(np.array(frame["observation.state"], np.float32), state)
            assert np.array_equal(np.array(frame["action"], np.float32),
                                  actions.COMMANDS[arrays["label"][t]].astype(np.float32))
            assert frame["label"] == arrays["label"][t] and frame["intervention"] == arrays["intervention"][t]
            assert np.array_equal(np.array(frame["pose"], np.float32), arrays["pose"][t])
            assert np.array_equal(np.array(frame["raw_command"], np.float32), arrays["raw_command"][t])
            assert frame["timestamp"] == pytest.approx(t * 0.1, abs=1e-6)
        first += steps
    assert [row["ditch_split"] for row in episodes] == ["train", "val", "paper"]
    assert [row["outcome"] for row in episodes] == ["reached_goal", "rolled_over", "reached_goal"]

    stats = json.loads((out / "meta/stats.json").read_text())
    states = np.concatenate([np.concatenate([a["imu_stack"], a["distance_stack"], a["bearing_stack"]], axis=1)
                             for a in sources])
    assert stats["observation.state"]["count"] == [frames]
    assert np.allclose(stats["observation.state"]["mean"], states.mean(axis=0), atol=1e-6)
    assert np.allclose(stats["observation.state"]["std"], states.std(axis=0), atol=1e-6)
    assert np.allclose(stats["observation.state"]["min"], states.min(axis=0))
    assert np.allclose(stats["observation.state"]["max"], states.max(axis=0))
    images = np.concatenate([a["image"] for a in sources]) / 255.0
    assert np.allclose(stats["observation.image"]["mean"], [[[images.mean()]]])
    assert np.allclose(stats["observation.image"]["std"], [[[images.std()]]])
    assert set(stats["label"]) == {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}


def test_lerobot_data_files_roll_over_whole_episodes(store, tmp_path, monkeypatch):
    monkeypatch.setattr(lerobot_export, "DATA_FILE_MB", 1e-6)  # Every episode starts a new file.
    out = tmp_path / "lerobot"
    assert export_dataset(store.root, "lerobot", out, progress=False)["data_files"] == 3
    episodes = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    for row in episodes:
        path = out / f"data/chunk-{row['data/chunk_index']:03d}/file-{row['data/file_index']:03d}.parquet"
        table = pq.read_table(path)
        assert table.column("episode_index").to_pylist() == [row["episode_index"]] * row["length"]
        assert table.column("index").to_pylist() == list(range(row["dataset_from_index"], row["dataset_to_index"]))


def test_robomimic_export_reads_back_equal(store, tmp_path):
    out = tmp_path / "demos.hdf5"
    summary = export_dataset(store.root, "robomimic", out, progress=False)
    sources = _sources(store)
    with h5py.File(out, "r") as file:
        data = file["data"]
        assert data.attrs["total"] == summary["frames"] == sum(len(a["label"]) for a in sources)
        env_args = json.loads(data.attrs["env_args"])
        assert (env_args["env_name"], env_args["env_type"], env_args["env_kwargs"]) == ("DitchDrake-v0", 2, {})
        assert sorted(data) == ["demo_0", "demo_1", "demo_2"]
        for index, arrays in enumerate(sources):
            demo = data[f"demo_{index}"]
            steps = len(arrays["label"])
            assert demo.attrs["num_samples"] == steps
            assert np.array_equal(demo["actions"][:], actions.COMMANDS[arrays["label"]])
            assert demo["obs/image"].shape == (steps, 128, 128, 1) and demo["obs/image"].dtype == np.uint8
            assert np.array_equal(demo["obs/image"][..., 0], arrays["image"])
            for key, field in (("imu", "imu_stack"), ("distance", "distance_stack"), ("bearing", "bearing_stack")):
                assert np.array_equal(demo[f"obs/{key}"][:], arrays[field])
            assert np.array_equal(demo["states"][:], arrays["pose"])
            assert np.array_equal(demo["labels"][:], arrays["label"])
            assert np.array_equal(demo["intervention"][:], arrays["intervention"])
            assert demo["dones"][:].tolist() == [0] * (steps - 1) + [1]
            reached = json.loads(demo.attrs["metadata"])["outcome"]["status"] == "reached_goal"
            assert demo["rewards"][:].tolist() == [0.0] * (steps - 1) + [float(reached)]
        masks = {key: [name.decode() for name in file[f"mask/{key}"][:]] for key in file["mask"]}
        assert masks == {"train": ["demo_0"], "val": ["demo_1"], "paper": ["demo_2"]}


@pytest.mark.parametrize("format, name", [("lerobot", "lerobot"), ("robomimic", "demos.hdf5")])
def test_an_existing_target_is_refused_and_left_alone(store, tmp_path, format, name):
    out = tmp_path / name
    out.write_text("mine")
    with pytest.raises(ConfigError, match=f"export target {out} exists"):
        export_dataset(store.root, format, out, progress=False)
    assert out.read_text() == "mine"
    assert sorted(path.name for path in tmp_path.iterdir()) == sorted([name, "store"])


def test_an_interrupted_export_leaves_nothing(store, tmp_path, monkeypatch):
    calls = []

    def interrupt_at_the_fifth_frame(frame):
        calls.append(frame)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return b""

    monkeypatch.setattr(lerobot_export, "_png", interrupt_at_the_fifth_frame)
    with pytest.raises(KeyboardInterrupt):
        export_dataset(store.root, "lerobot", tmp_path / "lerobot", progress=False)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["store"]


def test_bad_inputs_are_named(store, tmp_path, monkeypatch):
    with pytest.raises(ConfigError, match="export format 'rlds' is unknown"):
        export_dataset(store.root, "rlds", tmp_path / "x", progress=False)
    with pytest.raises(DatasetError, match="does not exist"):
        export_dataset(tmp_path / "missing", "lerobot", tmp_path / "x", progress=False)
    odd = DatasetStore.create(tmp_path / "odd")
    demonstration = _demonstration(0)
    demonstration.metadata["control_period_s"] = 0.15
    odd.append(demonstration)
    with pytest.raises(DatasetError, match="LeRobot's fps is an integer"):
        export_dataset(odd.root, "lerobot", tmp_path / "x", progress=False)
    demonstration.metadata["control_period_s"] = 0.1
    odd.append(demonstration)
    with pytest.raises(DatasetError, match="different control periods"):
        export_dataset(odd.root, "lerobot", tmp_path / "x", progress=False)
    monkeypatch.setitem(exports.EXPORT_FORMATS, "lerobot",
                        exports.ExportFormat("unused:unused", ("no_such_library_here",), "a folder"))
    with pytest.raises(ConfigError, match=r"needs no_such_library_here: pip install -e '\.\[export\]'"):
        export_dataset(store.root, "lerobot", tmp_path / "x", progress=False)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["odd", "store"]


def test_the_command_line_exports_and_refuses_an_existing_target(store, tmp_path, capsys):
    out = tmp_path / "lerobot"
    assert main(["dataset", "export", str(store.root), "--format", "lerobot", "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 17
    assert main(["dataset", "export", str(store.root), "--format", "lerobot", "--out", str(out)]) == 2
    assert f"export target {out} exists" in capsys.readouterr().err
    assert main(["dataset", "export", str(store.root), "--format", "robomimic",
                 "--out", str(tmp_path / "demos.hdf5")]) == 0
