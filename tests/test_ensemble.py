"""Ensembles: bootstrap resamples by demonstration, the ensemble file and its checks, all members
in one forward pass, and `train --ensemble` with its resumption."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from ditch_drake.cli import main
from ditch_drake.common.errors import CheckpointError, ConfigError
from ditch_drake.demos.store import DatasetStore
from ditch_drake.demos.training_set import dataset_episodes, training_set
from ditch_drake.learning import ensemble_training
from ditch_drake.learning.bootstrap import bootstrap_demonstrations
from ditch_drake.learning.checkpoint import make_checkpoint, save_checkpoint, save_payload
from ditch_drake.learning.config import ModelConfig, TrainConfig
from ditch_drake.learning.data import InputStats
from ditch_drake.learning.ensemble import (
    EnsembleCheckpoint,
    EnsembleInference,
    is_ensemble_checkpoint,
    load_ensemble,
    save_ensemble,
)
from ditch_drake.learning.ensemble_network import EnsembleNetwork
from ditch_drake.learning.ensemble_training import members_folder, train_ensemble
from ditch_drake.learning.model import FourInputClassifier
from ditch_drake.learning.train import TrainResult
from ditch_drake.spec import actions

TINY = TrainConfig(epochs=1, batch_size=8, max_batches_per_epoch=2, num_threads=1, val_fraction=0.25, seed=3,
                   eval_batch_size=16)


def _member(seed: int, config: ModelConfig | None = None) -> FourInputClassifier:
    """A clone with random weights, BatchNorm statistics and input statistics of its own."""
    torch.manual_seed(seed)
    model = FourInputClassifier(config)
    with torch.no_grad():
        for norm in (m for m in model.modules() if isinstance(m, torch.nn.BatchNorm1d)):
            norm.running_mean.normal_()
            norm.running_var.uniform_(0.5, 2.0)
            norm.weight.normal_()
            norm.bias.normal_()
    rng = np.random.default_rng(seed)
    model.set_input_stats({f"{name}_{kind}": rng.uniform(0.5, 1.5, size).tolist()
                           for name, size in (("imu", 8), ("distance", 4), ("bearing", 4)) for kind in ("mean", "std")})
    return model.eval()


def _checkpoint(seed: int, config: ModelConfig | None = None):
    model = _member(seed, config)
    stats = InputStats.from_dict({key: getattr(model, key).tolist() for key in
                                  (f"{n}_{k}" for n in ("imu", "distance", "bearing") for k in ("mean", "std"))})
    return make_checkpoint(model, stats)


def _inputs(batch: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    generator = torch.Generator().manual_seed(seed)
    return (torch.rand(batch, 4, 128, 128, generator=generator), torch.randn(batch, 8, generator=generator),
            torch.rand(batch, 4, generator=generator) * 20, torch.randn(batch, 4, generator=generator))


def test_bootstrap_draws_whole_demonstrations_with_replacement_deterministically():
    names = [f"data[{i}]" for i in range(12)]
    first = bootstrap_demonstrations(names, 5, seed=4)
    assert first.to_dict() == bootstrap_demonstrations(names, 5, seed=4).to_dict()
    assert first.to_dict() != bootstrap_demonstrations(names, 5, seed=5).to_dict()
    assert first.demonstrations == names and first.count == 12
    assert [draw.seed for draw in first.draws] == [4, 5, 6, 7, 8]
    for draw in first.draws:
        assert len(draw.indices) == 12 and draw.indices.min() >= 0 and draw.indices.max() < 12
        assert len(draw.distinct()) < 12  # With replacement: 12 of 12 distinct has odds 12!/12**12.
        assert np.array_equal(np.union1d(draw.distinct(), draw.out_of_bag(12)), np.arange(12))
    assert len({tuple(draw.indices) for draw in first.draws}) == 5
    # Member k's draw does not depend on how many members there are.
    assert np.array_equal(bootstrap_demonstrations(12, 2, seed=4).draws[1].indices, first.draws[1].indices)
    # Two demonstrations: a draw of one of them twice is drawn again (training holds one out).
    assert all(len(draw.distinct()) == 2 for draw in bootstrap_demonstrations(2, 8, seed=0).draws)
    for bad in (1, 0, 2.5, True):
        with pytest.raises(ConfigError, match=f"--ensemble {bad!r}: expected an integer >= 2"):
            bootstrap_demonstrations(names, bad, seed=0)


@pytest.mark.parametrize("members", [2, 5])
def test_one_forward_pass_gives_each_members_logits(members):
    models = [_member(seed) for seed in range(members)]
    network = EnsembleNetwork(models)
    for batch in (1, 3):
        inputs = _inputs(batch, seed=batch)
        with torch.inference_mode():
            stacked = network(*inputs)
            separate = torch.stack([model(*inputs) for model in models])
        assert stacked.shape == (members, batch, actions.NUM_LABELS)
        torch.testing.assert_close(stacked, separate, rtol=1e-5, atol=1e-5)


def test_an_ensemble_file_round_trips_and_says_what_it_is(tmp_path):
    bootstrap = bootstrap_demonstrations(6, 3, seed=1)
    ensemble = EnsembleCheckpoint([_checkpoint(seed) for seed in range(3)], bootstrap.to_dict())
    path = save_ensemble(ensemble, tmp_path / "ensemble.pt")
    single = save_checkpoint(_checkpoint(9), tmp_path / "single.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    assert is_ensemble_checkpoint(path)
    assert not any(is_ensemble_checkpoint(other) for other in (single, tmp_path / "junk.pt", tmp_path / "none.pt"))
    loaded = load_ensemble(path)
    assert loaded.size == 3 and loaded.path == path and loaded.bootstrap == bootstrap.to_dict()
    np.testing.assert_array_equal(loaded.action_commands, actions.COMMANDS)
    inputs = _inputs(2)
    with torch.inference_mode():
        torch.testing.assert_close(loaded.build_network()(*inputs),
                                   torch.stack([member.build_model()(*inputs) for member in ensemble.members]),
                                   rtol=1e-5, atol=1e-5)
    probabilities = EnsembleInference(loaded).member_probabilities(*(value.numpy() for value in inputs))
    assert probabilities.shape == (3, 2, actions.NUM_LABELS)
    np.testing.assert_allclose(probabilities.sum(axis=-1), 1.0)
    with pytest.raises(CheckpointError, match="single.pt has schema 'ditch_drake.policy_checkpoint'"):
        load_ensemble(single)


def test_checkpoint_info_lists_an_ensembles_members_beside_a_single_clone(tmp_path, capsys):
    ensemble = save_ensemble(EnsembleCheckpoint([_checkpoint(seed) for seed in range(3)]), tmp_path / "ensemble.pt")
    single = save_checkpoint(_checkpoint(9), tmp_path / "single.pt")
    assert main(["checkpoint-info", str(ensemble), str(single)]) == 0
    rows = [line.split()[0] for line in capsys.readouterr().out.splitlines()[1:]]
    assert rows == [f"{ensemble}[0]", f"{ensemble}[1]", f"{ensemble}[2]", str(single)]


def test_bad_ensembles_are_refused_naming_the_member_and_the_key(tmp_path):
    def write(members: list[dict]) -> str:
        path = tmp_path / "bad.pt"
        save_payload({"schema": "ditch_drake.policy_ensemble", "schema_version": 1, "code_version": "x",
                      "members": members, "bootstrap": {}}, path)
        return str(path)

    good = [_checkpoint(seed).to_payload() for seed in range(3)]
    with pytest.raises(ConfigError, match="has 1 member.*expected at least 2"):
        load_ensemble(write(good[:1]))
    narrow = _checkpoint(5, ModelConfig(conv1_channels=16)).to_payload()
    with pytest.raises(CheckpointError, match="member 2's model_config.conv1_channels is 16, member 0's 64"):
        load_ensemble(write([*good[:2], narrow]))
    side = _checkpoint(5, ModelConfig(canonical_side=True)).to_payload()
    with pytest.raises(CheckpointError, match="member 1's model_config.canonical_side is True"):
        load_ensemble(write([good[0], side]))
    other_table = {**good[1], "action_commands": (actions.COMMANDS * [1.0, 2.0]).tolist()}
    with pytest.raises(CheckpointError, match="bad.pt member 1 was trained with another action table"):
        load_ensemble(write([good[0], other_table]))
    broken = {**good[1], "state_dict": {k: v for k, v in good[1]["state_dict"].items() if "head" not in k}}
    with pytest.raises(CheckpointError, match="bad.pt member 1: the weights do not fit"):
        load_ensemble(write([good[0], broken]))
    with pytest.raises(CheckpointError, match="bad.pt member 0 is 'ditch_drake.training_state'"):
        load_ensemble(write([{**good[0], "schema": "ditch_drake.training_state"}, good[1]]))


@pytest.fixture
def store_path(tmp_path, random_demonstration):
    store = DatasetStore.create(tmp_path / "store")
    for index, steps in enumerate((9, 6, 11, 5, 8)):
        store.append(random_demonstration(index, steps))
    return tmp_path / "store"


def test_train_ensemble_trains_each_member_on_its_resample_and_continues_after_an_interruption(
        store_path, tmp_path, monkeypatch):
    episodes = dataset_episodes(store_path)
    names = [f"store[{i}]" for i in range(len(episodes))]
    out = tmp_path / "ensemble.pt"
    real_train, calls = ensemble_training.train, []

    def interrupted_in_member_1(arrays, config, progress, path, resume):
        calls.append((config.seed, np.unique(arrays.demo_id)))
        if config.seed == TINY.seed + 1:
            model = FourInputClassifier()
            return TrainResult(model, make_checkpoint(model), [], -1, False, True, exit_code=130)
        return real_train(arrays, config, progress, path, resume)

    def samples_of(indices):
        return training_set([episodes[i] for i in indices])

    monkeypatch.setattr(ensemble_training, "train", interrupted_in_member_1)
    first = train_ensemble(samples_of, names, out, TINY, members=3, progress=False)
    assert first.interrupted and first.exit_code == 130 and first.output_path is None
    assert first.trained == [0, 1] and not out.exists()
    assert (members_folder(out) / "member_0.pt").exists() and not (members_folder(out) / "member_1.pt").exists()
    bootstrap = bootstrap_demonstrations(names, 3, TINY.seed)
    # The copies of a demonstration drawn twice keep its id: the split holds out all or none.
    assert np.array_equal(calls[0][1], bootstrap.draws[0].distinct())
    # Another seed would mix two ensembles in one folder.
    with pytest.raises(ConfigError, match=r"members of another ensemble \(seed, draws"):
        train_ensemble(samples_of, names, out, dataclasses.replace(TINY, seed=4), members=3, progress=False)

    monkeypatch.setattr(ensemble_training, "train", real_train)
    second = train_ensemble(samples_of, names, out, TINY, members=3, progress=False)
    assert second.skipped == [0] and second.trained == [1, 2] and not second.interrupted
    assert second.output_path == out and not members_folder(out).exists()
    ensemble = load_ensemble(out)
    assert ensemble.bootstrap == bootstrap.to_dict()
    for draw, member in zip(bootstrap.draws, ensemble.members, strict=True):
        assert member.training["train_config"]["seed"] == draw.seed
        used = set(member.training["train_demo_ids"]) | set(member.training["val_demo_ids"])
        assert used == set(draw.distinct().tolist())


def test_the_train_command_writes_one_ensemble(store_path, tmp_path, capsys):
    out = tmp_path / "e.pt"
    options = ["train", "--data", str(store_path), "--out", str(out), "--epochs", "1", "--batch-size", "8",
               "--batches-per-epoch", "1", "--threads", "1"]
    assert main([*options, "--ensemble", "1"]) == 2
    assert "--ensemble 1: expected an integer >= 2" in capsys.readouterr().err
    assert main([*options, "--ensemble", "2"]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["out"] == str(out) and printed["trained"] == [0, 1] and not printed["interrupted"]
    ensemble = load_ensemble(out)
    assert ensemble.size == 2 and ensemble.bootstrap["demonstrations"][0] == f"{store_path}[0]"
