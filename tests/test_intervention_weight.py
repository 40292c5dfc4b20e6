"""Sirius-style weighting: the loss of intervention samples weighs `intervention_weight`, and weight
1 trains bit for bit as before."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.demos.interventions import episode_interventions
from ditch_drake.demos.store import DatasetStore
from ditch_drake.demos.training_set import dataset_episodes, training_set
from ditch_drake.learning.checkpoint import load_checkpoint
from ditch_drake.learning.config import TrainConfig
from ditch_drake.learning.train import intervention_weighted_loss, train

TINY = TrainConfig(epochs=1, batch_size=8, max_batches_per_epoch=2, num_threads=1, val_fraction=0.25, seed=3,
                   eval_batch_size=16, balancing="none")


def _log_softmax(logits: np.ndarray) -> np.ndarray:
    shifted = logits - logits.max(axis=1, keepdims=True)
    return shifted - np.log(np.exp(shifted).sum(axis=1, keepdims=True))


def test_the_weighted_loss_is_the_hand_computed_one():
    logits = np.array([[2.0, 0.5, -1.0], [0.0, 1.0, 0.0], [-0.5, 0.2, 1.5], [1.0, 1.0, 1.0]])
    labels = np.array([0, 2, 2, 1])
    flags = np.array([False, True, False, True])
    weight = 3.0
    w = np.where(flags, weight, 1.0)
    nll = -_log_softmax(logits)[np.arange(4), labels]
    expected = (w * nll).sum() / w.sum()
    got = intervention_weighted_loss(torch.tensor(logits), torch.tensor(labels), torch.tensor(w))
    assert float(got) == pytest.approx(expected, rel=1e-12)
    # With class weights c: sum(w c l) / sum(w c), as torch's weighted cross-entropy.
    c = np.array([0.5, 2.0, 1.5])
    expected = (w * c[labels] * nll).sum() / (w * c[labels]).sum()
    got = intervention_weighted_loss(torch.tensor(logits), torch.tensor(labels), torch.tensor(w), torch.tensor(c))
    assert float(got) == pytest.approx(expected, rel=1e-12)
    # With soft targets: each sample's cross-entropy against its label's row.
    soft = np.array([[0.8, 0.2, 0.0], [0.1, 0.8, 0.1], [0.0, 0.2, 0.8]])
    nll_soft = -(soft[labels] * _log_softmax(logits)).sum(axis=1)
    got = intervention_weighted_loss(torch.tensor(logits), torch.tensor(labels), torch.tensor(w),
                                     soft_targets=torch.tensor(soft))
    assert float(got) == pytest.approx((w * nll_soft).sum() / w.sum(), rel=1e-12)
    # Unit weights: the unweighted mean.
    ones = torch.ones(4, dtype=torch.float64)
    unweighted = torch.nn.functional.cross_entropy(torch.tensor(logits), torch.tensor(labels))
    assert float(intervention_weighted_loss(torch.tensor(logits), torch.tensor(labels), ones)) == pytest.approx(
        float(unweighted), rel=1e-12)


@pytest.fixture
def intervened_store(tmp_path, random_demonstration):
    """Five random episodes, the middle third of each step range taken over."""
    store = DatasetStore.create(tmp_path / "store")
    for index, steps in enumerate((9, 6, 11, 5, 8)):
        flags = np.zeros(steps, bool)
        flags[steps // 3: 2 * steps // 3] = True
        store.append(random_demonstration(index, steps), intervention=flags)
    return tmp_path / "store"


def _state(result) -> dict:
    return {key: value.clone() for key, value in result.model.state_dict().items()}


def test_weight_1_trains_bit_for_bit_as_before_and_another_weight_does_not(intervened_store):
    episodes = dataset_episodes(intervened_store)
    flags = episode_interventions(episodes)
    assert flags.shape == (39,) and flags.sum() == 3 + 2 + 4 + 2 + 3
    before = train(training_set(episodes), TINY, progress=False)
    uniform = train(training_set(episodes), dataclasses.replace(TINY, intervention_weight=1.0), progress=False,
                    intervention=flags)
    for key, value in _state(before).items():
        assert torch.equal(value, _state(uniform)[key]), key
    assert before.history[0]["train_loss"] == uniform.history[0]["train_loss"]
    assert "intervention_weight" not in uniform.checkpoint.training["train_config"]
    timings = ("balancing_seconds", "smote_seconds")
    assert ({k: v for k, v in uniform.checkpoint.training.items() if k not in timings}
            == {k: v for k, v in before.checkpoint.training.items() if k not in timings})
    weighted = train(training_set(episodes), dataclasses.replace(TINY, intervention_weight=4.0), progress=False,
                     intervention=flags)
    assert weighted.checkpoint.training["train_config"]["intervention_weight"] == 4.0
    assert weighted.checkpoint.training["intervention_train_samples"] > 0
    assert any(not torch.equal(value, _state(weighted)[key]) for key, value in _state(before).items())
    with pytest.raises(ConfigError, match=r"intervention has shape \(3,\); expected \(39,\)"):
        train(training_set(episodes), dataclasses.replace(TINY, intervention_weight=4.0), progress=False,
              intervention=np.zeros(3, bool))


@pytest.mark.parametrize("weight", [0.0, -1.0, float("nan"), float("inf")])
def test_a_bad_weight_is_refused_naming_the_option(weight):
    with pytest.raises(ConfigError, match=r"intervention_weight=.*\(--intervention-weight\)"):
        TrainConfig(intervention_weight=weight)


def test_the_train_command_weighs_interventions(intervened_store, tmp_path, capsys):
    out = tmp_path / "w.pt"
    options = ["train", "--data", str(intervened_store), "--out", str(out), "--epochs", "1", "--batch-size", "8",
               "--batches-per-epoch", "1", "--threads", "1", "--balancing", "none"]
    assert main([*options, "--intervention-weight", "0"]) == 2
    assert "intervention_weight=0.0: expected a finite number > 0" in capsys.readouterr().err
    assert main([*options, "--intervention-weight", "5"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["out"] == str(out)
    training = load_checkpoint(out).training
    assert training["train_config"]["intervention_weight"] == 5.0 and training["intervention_train_samples"] > 0


def test_an_ensemble_weighs_each_members_interventions(intervened_store, tmp_path, capsys):
    from ditch_drake.learning.ensemble import load_ensemble

    out = tmp_path / "e.pt"
    assert main(["train", "--data", str(intervened_store), "--out", str(out), "--epochs", "1", "--batch-size", "8",
                 "--batches-per-epoch", "1", "--threads", "1", "--balancing", "none", "--ensemble", "2",
                 "--intervention-weight", "3"]) == 0
    for member in load_ensemble(out).members:
        assert member.training["train_config"]["intervention_weight"] == 3.0
        assert member.training["intervention_train_samples"] > 0
