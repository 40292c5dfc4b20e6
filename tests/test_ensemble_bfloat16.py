"""The ensemble network's image branch in bfloat16 (`precision: bfloat16_image`): its labels and
probabilities against float32's on observations of closed-loop drives, the float32 default
unchanged, and the refusal on a CPU without native bfloat16."""

import numpy as np
import pytest
import torch

from ditch_drake.cli.main import main
from ditch_drake.common.config_yaml import config_to_yaml
from ditch_drake.common.errors import ConfigError
from ditch_drake.learning import ensemble_network
from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path
from ditch_drake.learning.ensemble import EnsembleCheckpoint, EnsembleInference, save_ensemble
from ditch_drake.learning.ensemble_network import EnsembleNetwork, native_bfloat16_flags
from ditch_drake.learning.inference import load_policy

# Five shipped clones of one model config: an ensemble of trained weights.
MEMBERS = ("wide", "narrow", "crater", "sine", "wide_bc40")
# The fixed batch: each environment's shipped model driving task 1 from seed 3 for DRIVE_S,
# its inputs read at every control step (244 observations).
DRIVE_S = 6.0
MIN_LABEL_AGREEMENT = 0.99
# Softmax probabilities, bfloat16 image branch against float32 (largest difference measured on
# the fixed batch: 0.0027).
PROBABILITY_ATOL = 0.01

needs_native_bfloat16 = pytest.mark.skipif(
    not native_bfloat16_flags(),
    reason=f"this CPU has none of {list(ensemble_network.NATIVE_BFLOAT16_FLAGS)}: no native bfloat16 to run")


@pytest.fixture(scope="module")
def observations() -> tuple[torch.Tensor, ...]:
    """The learned policy's four inputs on a short drive of each environment's shipped model:
    (batch, 4, 128, 128), (batch, 8), (batch, 4), (batch, 4)."""
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode

    names = ("image_stack", "imu_stack", "distance_stack", "bearing_stack")
    rows = []
    for environment in ("wide", "narrow", "crater", "sine"):
        diagram, scene = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment=environment, task=1),
                                                          controller=LearnedPolicyConfig()))
        policy = diagram.GetSubsystemByName("learned_policy")

        def watch(context, policy=policy):
            policy_context = policy.GetMyContextFromRoot(context)
            rows.append([policy.GetInputPort(name).Eval(policy_context).astype(np.float32) for name in names])

        RunEpisode(Simulator(diagram), diagram, scene, 3, watch=watch, watch_period_s=0.1, end_time_s=DRIVE_S)
    image, imu, distance, bearing = (torch.from_numpy(np.stack(column)) for column in zip(*rows, strict=True))
    return image.reshape(len(rows), 4, 128, 128), imu, distance, bearing


@pytest.fixture(scope="module")
def members() -> list:
    return [load_checkpoint(resolve_checkpoint_path(name)).build_model() for name in MEMBERS]


def _logits(network: EnsembleNetwork, observations, chunk: int = 16) -> torch.Tensor:
    """(K, batch, labels): `network` on `observations` a chunk at a time (faster than all at once)."""
    with torch.inference_mode():
        return torch.cat([network(*(value[start:start + chunk] for value in observations))
                          for start in range(0, len(observations[0]), chunk)], dim=1)


def _float32_forward_as_before(network: EnsembleNetwork, image, imu, distance, bearing) -> torch.Tensor:
    """`EnsembleNetwork.forward` as it was before it had a precision."""
    features = [network.image_branch(image.contiguous(memory_format=torch.channels_last))]
    for name, value in zip(("imu", "distance", "bearing"), (imu, distance, bearing), strict=True):
        standardized = (value.unsqueeze(0) - getattr(network, f"{name}_mean")) / getattr(network, f"{name}_std")
        features.append(getattr(network, f"{name}_branch")(standardized))
    return network.head(torch.cat(features, dim=2))


def test_float32_is_the_default_and_its_numbers_are_unchanged(members, observations):
    default = EnsembleNetwork(members)
    assert default.precision == "float32"
    explicit = EnsembleNetwork(members, precision="float32")
    batch = [value[:16] for value in observations]
    with torch.inference_mode():
        logits = default(*batch)
        assert torch.equal(logits, _float32_forward_as_before(default, *batch))
        assert torch.equal(logits, explicit(*batch))
        assert logits.dtype == torch.float32
        torch.testing.assert_close(logits, torch.stack([member(*batch) for member in members]), rtol=1e-5, atol=1e-5)


@needs_native_bfloat16
def test_the_bfloat16_image_branch_agrees_with_float32(members, observations):
    float32 = EnsembleNetwork(members)
    bfloat16 = EnsembleNetwork(members, precision="bfloat16_image")
    reference, approximate = _logits(float32, observations), _logits(bfloat16, observations)
    assert approximate.dtype == torch.float32 and approximate.shape == reference.shape
    assert reference.shape[1] >= 240
    agreement = (reference.argmax(-1) == approximate.argmax(-1)).double().mean(dim=1).numpy()
    probabilities = [torch.softmax(logits.double(), dim=-1) for logits in (reference, approximate)]
    largest = float((probabilities[0] - probabilities[1]).abs().max())
    print(f"bfloat16_image against float32 on {reference.shape[1]} observations: each member's label agrees on "
          f"{', '.join(f'{100 * share:.2f} %' for share in agreement)}; probabilities differ by at most {largest:.4f}")
    assert agreement.min() >= MIN_LABEL_AGREEMENT
    assert largest <= PROBABILITY_ATOL
    mean_labels = [p.mean(dim=0).argmax(-1) for p in probabilities]
    assert (mean_labels[0] == mean_labels[1]).double().mean() >= MIN_LABEL_AGREEMENT


@needs_native_bfloat16
def test_the_inference_object_and_the_policy_loader_take_the_precision(members, observations, tmp_path):
    checkpoints = [load_checkpoint(resolve_checkpoint_path(name)) for name in MEMBERS[:2]]
    path = save_ensemble(EnsembleCheckpoint(checkpoints), tmp_path / "ensemble.pt")
    inference = load_policy(path, precision="bfloat16_image")
    assert isinstance(inference, EnsembleInference) and inference.precision == "bfloat16_image"
    assert load_policy(path).precision == "float32"
    batch = [value[:4].numpy() for value in observations]
    np.testing.assert_allclose(inference.member_probabilities(*batch), load_policy(path).member_probabilities(*batch),
                               atol=PROBABILITY_ATOL)


def test_native_bfloat16_is_read_from_the_cpu_flags(tmp_path):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nflags\t\t: fpu sse avx512f amx_bf16 amx_tile\n\n"
                       "processor\t: 1\nflags\t\t: fpu sse avx512f amx_bf16 amx_tile\n")
    assert native_bfloat16_flags(cpuinfo) == ("amx_bf16",)
    cpuinfo.write_text("processor\t: 0\nflags\t\t: fpu sse avx512f avx512_bf16 amx_bf16\n")
    assert native_bfloat16_flags(cpuinfo) == ("avx512_bf16", "amx_bf16")
    cpuinfo.write_text("processor\t: 0\nflags\t\t: fpu sse avx2 avx512f\n")
    assert native_bfloat16_flags(cpuinfo) == ()
    assert native_bfloat16_flags(tmp_path / "none") == ()


def test_bfloat16_is_refused_where_the_cpu_lacks_it(members, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(ensemble_network, "native_bfloat16_flags", lambda: ())
    lacks = r"precision='bfloat16_image' needs a CPU that runs bfloat16 natively; this one has none of the CPU flags " \
            r"\['avx512_bf16', 'amx_bf16'\]"
    with pytest.raises(ConfigError, match=lacks):
        EnsembleNetwork(members[:2], precision="bfloat16_image")
    assert EnsembleNetwork(members[:2]).precision == "float32"  # float32 needs nothing.
    with pytest.raises(ConfigError, match=r"precision='float16': expected one of \['float32', 'bfloat16_image'\]"):
        EnsembleNetwork(members[:2], precision="float16")
    path = save_ensemble(EnsembleCheckpoint([load_checkpoint(resolve_checkpoint_path(n)) for n in MEMBERS[:2]]),
                         tmp_path / "ensemble.pt")
    override = f"{{controller: !SharedControlControllerConfig {{policy: {{checkpoint: {path}, precision: bfloat16_image}}}}}}"
    code = main(["evaluate", "--override", override, "--env", "wide", "--task", "1", "--rollouts", "1",
                 "--workers", "0", "--out", str(tmp_path / "refused.jsonl")])
    assert code == 2 and "this one has none of the CPU flags" in capsys.readouterr().err
    assert not (tmp_path / "refused.jsonl").exists()


def test_the_precision_is_written_only_when_set_and_only_for_an_ensemble(monkeypatch, tmp_path):
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig

    monkeypatch.setattr(ensemble_network, "native_bfloat16_flags", lambda: ("amx_bf16",))
    assert "precision" not in config_to_yaml(LearnedPolicyConfig())
    path = save_ensemble(EnsembleCheckpoint([load_checkpoint(resolve_checkpoint_path(n)) for n in MEMBERS[:2]]),
                         tmp_path / "ensemble.pt")
    config = LearnedPolicyConfig(checkpoint=str(path), precision="bfloat16_image")
    config.validate()
    assert "precision: bfloat16_image" in config_to_yaml(config)
    with pytest.raises(ConfigError, match="precision='bfloat16_image' with checkpoint 'wide', a single clone"):
        LearnedPolicyConfig(checkpoint="wide", precision="bfloat16_image").validate()


def test_the_bench_times_both_precisions_or_says_why_not(monkeypatch, capsys):
    from ditch_drake.perf.bench_training import measure_ensemble_policy_step_ms

    keys = ["ensemble_policy_step_ms", "ensemble_policy_step_max_ms", "ensemble_policy_step_bfloat16_ms",
            "ensemble_policy_step_bfloat16_max_ms", "ensemble_member_policy_step_ms", "ensemble_members_in_turn_ms"]
    if native_bfloat16_flags():
        figures = measure_ensemble_policy_step_ms(members=2, repeats=2)
        assert list(figures) == keys and all(value > 0 for value in figures.values())
    monkeypatch.setattr(ensemble_network, "native_bfloat16_flags", lambda: ())
    figures = measure_ensemble_policy_step_ms(members=2, repeats=2)
    assert list(figures) == keys and figures["ensemble_policy_step_ms"] > 0
    assert figures["ensemble_member_policy_step_ms"] > 0 and figures["ensemble_members_in_turn_ms"] > 0
    assert figures["ensemble_policy_step_bfloat16_ms"] is None and figures["ensemble_policy_step_bfloat16_max_ms"] is None
    assert "bench: no ensemble_policy_step_bfloat16_ms" in capsys.readouterr().err
