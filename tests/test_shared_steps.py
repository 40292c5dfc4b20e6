"""Learning only the supervisor's steps of shared episodes (`TrainConfig.shared_steps`
"interventions", HG-DAgger's and ThriftyDAgger's data): which steps are kept, that the kept
samples are those steps of the whole set, and the train command with it."""


import numpy as np
import pytest

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.demos.interventions import episode_interventions, kept_steps
from ditch_drake.demos.store import DatasetStore
from ditch_drake.demos.training_set import dataset_episodes, training_set
from ditch_drake.learning.checkpoint import load_checkpoint
from ditch_drake.learning.config import TrainConfig

STEPS = (9, 6, 11, 5, 8)


@pytest.fixture
def mixed_store(tmp_path, random_demonstration):
    """Five random episodes: the even ones demonstrations, the odd ones shared episodes with
    the middle third of their steps taken over (a demonstration's flags are all false)."""
    store = DatasetStore.create(tmp_path / "store")
    for index, steps in enumerate(STEPS):
        demonstration = random_demonstration(index, steps)
        flags = np.zeros(steps, bool)
        if index % 2:
            demonstration.metadata["shared_gate"] = {"signal": "tip_risk_ahead", "fallback": "expert"}
            flags[steps // 3: 2 * steps // 3] = True
        store.append(demonstration, intervention=flags)
    return tmp_path / "store"


def test_only_the_supervisors_steps_of_shared_episodes_are_kept(mixed_store):
    episodes = dataset_episodes(mixed_store)
    assert kept_steps(episodes) is None and kept_steps(episodes, "all") is None
    steps = kept_steps(episodes, "interventions")
    assert steps[0] is None and steps[2] is None and steps[4] is None
    assert steps[1].tolist() == [2, 3] and steps[3].tolist() == [1, 2]
    whole, kept = training_set(episodes), training_set(episodes, steps=steps)
    rows = np.concatenate([np.arange(9), 9 + np.array([2, 3]), 15 + np.arange(11), 26 + np.array([1, 2]),
                           31 + np.arange(8)])
    assert len(kept.label) == len(rows) == 9 + 2 + 11 + 2 + 8
    for name in ("label", "imu", "distance", "bearing", "demo_id"):
        assert np.array_equal(getattr(kept, name), getattr(whole, name)[rows]), name
    assert np.array_equal(np.asarray(kept.image[np.arange(len(rows))]), np.asarray(whole.image[rows]))
    flags = episode_interventions(episodes, steps)
    assert flags.shape == rows.shape and flags.tolist() == [False] * 9 + [True] * 2 + [False] * 11 + [True] * 2 + [
        False] * 8


def test_a_bad_choice_is_refused_naming_the_option():
    with pytest.raises(ConfigError, match=r"shared_steps='some': expected one of \('all', 'interventions'\) "
                                          r"\(--shared-steps\)"):
        TrainConfig(shared_steps="some")


def test_the_train_command_learns_the_interventions_only(mixed_store, tmp_path, capsys):
    options = ["train", "--data", str(mixed_store), "--epochs", "1", "--batch-size", "8", "--batches-per-epoch", "1",
               "--threads", "1", "--balancing", "none", "--seed", "3"]
    assert main([*options, "--out", str(tmp_path / "all.pt")]) == 0
    assert main([*options, "--out", str(tmp_path / "hg.pt"), "--shared-steps", "interventions"]) == 0
    capsys.readouterr()
    every, interventions = (load_checkpoint(tmp_path / name).training for name in ("all.pt", "hg.pt"))
    assert "shared_steps" not in every["train_config"] and interventions["train_config"]["shared_steps"] == (
        "interventions")
    samples = [t["num_train_samples"] + t["num_val_samples"] for t in (every, interventions)]
    assert samples == [sum(STEPS), sum(STEPS) - (6 - 2) - (5 - 2)]
    with pytest.raises(SystemExit) as exit_:
        main([*options, "--out", str(tmp_path / "x.pt"), "--shared-steps", "some"])
    assert exit_.value.code == 2 and "--shared-steps: invalid choice: 'some'" in capsys.readouterr().err


def test_an_ensembles_members_learn_the_interventions_only(mixed_store, tmp_path):
    from ditch_drake.learning.ensemble import load_ensemble

    out = tmp_path / "e.pt"
    assert main(["train", "--data", str(mixed_store), "--out", str(out), "--epochs", "1", "--batch-size", "8",
                 "--batches-per-epoch", "1", "--threads", "1", "--balancing", "none", "--ensemble", "2",
                 "--shared-steps", "interventions", "--intervention-weight", "2"]) == 0
    ensemble = load_ensemble(out)
    kept = {0: 9, 1: 2, 2: 11, 3: 2, 4: 8}  # Per episode: every step of a demonstration, a shared one's interventions.
    for member, draw in zip(ensemble.members, ensemble.bootstrap["draws"], strict=True):
        training = member.training
        assert training["train_config"]["shared_steps"] == "interventions"
        assert training["num_train_samples"] + training["num_val_samples"] == sum(kept[i] for i in draw["indices"])
