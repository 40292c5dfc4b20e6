"""The action table and the teleop quantizer block."""

import numpy as np
import pytest

from ditch_drake.spec import actions
from ditch_drake.systems.teleop import ActionQuantizer


def test_table_matches_the_paper_examples():
    assert actions.NUM_LABELS == 17
    assert np.allclose(actions.COMMANDS[:, 0], 1.0)
    for label, rate in {8: 0.0, 10: 0.25, 11: 0.35, 12: 0.45, 16: 0.85, 0: -0.85, 7: -0.15}.items():
        assert actions.label_to_command(label)[1] == pytest.approx(rate)


@pytest.mark.parametrize("label", range(17))
def test_every_label_follows_the_spec_formula(label):
    # docs/design.md, "The action table": w(8) = 0; w(l) = sign(l - 8) * (0.05 + 0.1 |l - 8|); v = 1.0 for every label.
    expected = 0.0 if label == 8 else np.sign(label - 8) * (0.05 + 0.1 * abs(label - 8))
    assert actions.label_to_command(label) == pytest.approx([1.0, expected])
    assert actions.quantize([1.0, expected]) == label


@pytest.mark.parametrize("w, label", [(0.0, 8), (0.07, 8), (0.08, 9), (0.3, 10), (-0.3, 6), (5.0, 16), (-5.0, 0)])
def test_quantize_to_nearest_rate(w, label):
    assert actions.quantize([0.4, w]) == label


def test_quantize_inverts_the_table():
    for label in range(actions.NUM_LABELS):
        assert actions.quantize(actions.label_to_command(label)) == label


def test_bad_commands_and_labels():
    with pytest.raises(ValueError, match="must be a finite"):
        actions.quantize([1.0, float("nan")])
    with pytest.raises(ValueError, match="must be a finite"):
        actions.quantize([1.0, 0.0, 2.0])
    with pytest.raises(ValueError, match="out of range"):
        actions.label_to_command(17)


def test_quantizer_block_outputs_the_snapped_command_and_label():
    quantizer = ActionQuantizer()
    context = quantizer.CreateDefaultContext()
    quantizer.GetInputPort("raw_command").FixValue(context, [0.7, -0.62])
    assert np.allclose(quantizer.GetOutputPort("command").Eval(context), [1.0, -0.65])
    assert quantizer.GetOutputPort("label").Eval(context)[0] == 2


def test_keyboard_and_gamepad_steering():
    from ditch_drake.systems.meshcat_teleop import steer

    assert steer(0.0, 2, 0, 0, None) == pytest.approx(0.2)
    assert steer(0.3, 0, 1, 0, None) == pytest.approx(0.2)
    assert steer(0.5, 1, 0, 1, None) == pytest.approx(0.1)  # Up straightens, then one more left.
    assert steer(0.8, 5, 0, 0, None) == pytest.approx(0.85)
    assert steer(0.0, 0, 0, 0, 1.0) == pytest.approx(-0.85)  # Stick full right.


def test_meshcat_teleop_drives_straight_until_a_key_is_pressed():
    from pydrake.geometry import Meshcat
    from pydrake.systems.analysis import Simulator

    from ditch_drake.systems.meshcat_teleop import MeshcatTeleop

    teleop = MeshcatTeleop(Meshcat())
    simulator = Simulator(teleop)
    simulator.AdvanceTo(0.25)
    command = teleop.GetOutputPort("raw_command").Eval(simulator.get_context())
    assert np.allclose(command, [1.0, 0.0])
