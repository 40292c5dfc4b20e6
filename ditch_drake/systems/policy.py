"""The learned policy (paper 3.4): the trained classifier as a Drake system at the control rate."""

from typing import NamedTuple

import numpy as np
import torch
from pydrake.systems.framework import DiscreteValues, LeafSystem

from ditch_drake.common.errors import ConfigError
from ditch_drake.learning import uncertainty
from ditch_drake.learning.checkpoint import PolicyCheckpoint
from ditch_drake.learning.inference import EnsemblePolicyInference, PolicyInference, TorchInference
from ditch_drake.learning.mirror import mirror_left_right
from ditch_drake.spec import robot

# The uncertainty the block reports unless told another (the one a single clone has too).
DEFAULT_UNCERTAINTY_SIGNAL = "mean_softmax_entropy"


class PolicyDecision(NamedTuple):
    """What the policy makes of one observation.

    Attributes:
        label: the chosen label (the most probable one of `probabilities`).
        probabilities: (num_labels,) the members' mean softmax probabilities (one clone's own).
        member_probabilities: (members, num_labels) each member's (one row for a single clone).
        uncertainty: the configured signal of the members' probabilities.
    """

    label: int
    probabilities: np.ndarray
    member_probabilities: np.ndarray
    uncertainty: float


class LearnedPolicy(LeafSystem):
    """Runs the behavioural clone on the stacked observations and commands the chosen label.

    A periodic discrete update every `period_s` (at t_k = offset_s + k * period_s) reads
    the four stacks, runs the network once (eval mode: dropout off, BatchNorm on its
    running statistics), and stores the most probable label, its [v, w] command from the
    checkpoint's action table and the softmax probabilities in the discrete state, which the
    outputs read. The network runs in the runtime of the inference object it is given
    (`ditch_drake.learning.inference`: PyTorch under `torch.inference_mode`, or ONNX Runtime);
    the softmax, the mirror and the argmax here are the same for every runtime. The same
    update is declared as a forced discrete update, so `CalcForcedDiscreteVariableUpdate`
    runs one step too. Until the first update the command is [0, 0] (stand still), the
    label -1 and the probabilities 0.

    With the FrameStacker updating at the same ticks and `offset_s = 0`, the update at t_k
    sees the stacks pushed at t_{k-1} (see `FrameStacker`); a small positive `offset_s`
    makes it see those pushed at t_k, one period fresher.

    A checkpoint trained in one side's frame (`ModelConfig.canonical_side`) adds the input
    `crossing_side` (`PerceivedCrossingSide` or `OracleCrossingSide`; 0 before the edge is seen
    reflects nothing): where it is -1 (cross turned left along the edge) the
    policy runs the network on the left-right reflection of the stacks
    (`ditch_drake.learning.mirror`) and reflects the chosen label and the probabilities back.

    An ensemble (`ditch_drake.learning.ensemble.EnsembleInference`, K clones in one forward
    pass) chooses by the members' mean probabilities (ThriftyDAgger's ensemble mean), each
    member's reflected back first where the view was reflected. Every update also stores the
    uncertainty signal chosen at construction (`ditch_drake.learning.uncertainty`) of the
    members' probabilities, which the `uncertainty` output reads: "mean_softmax_entropy" (the
    default) works for a single clone too (its own softmax entropy); a disagreement signal
    needs K >= 2. The signals are symmetric under the left-right reflection, so a reflected
    view reports the uncertainty of the view as it is. A single clone's label, probabilities
    and command are computed as before the port existed.

    The network's weights (the inference object) are fixed configuration, so they live on
    the system, not in the Context; everything that changes is discrete state.

    .. pydrake_system::

        name: LearnedPolicy
        input_ports:
        - image_stack
        - imu_stack
        - distance_stack
        - bearing_stack
        - crossing_side (canonical_side checkpoints only)
        output_ports:
        - command
        - label
        - probabilities
        - uncertainty

    Ports:
        image_stack: 4 * 128 * 128 values in [0, 1], channel-major, channel 0 newest (the
            FrameStacker's `image_stack`).
        imu_stack: 8 (rad), [roll_t, pitch_t, roll_t-1, ...].
        distance_stack: 4 (m), newest first.
        bearing_stack: 4 (rad), newest first.
        crossing_side: [+1] or [-1], the side along the edge to cross on (canonical_side only).
        command: [v m/s, w rad/s] of the chosen label.
        label: [the chosen label in 0..16] (a float, -1 before the first update).
        probabilities: 17 softmax probabilities, one per label (an ensemble's: the members' mean).
        uncertainty: [the configured signal] in its unit (nats for the entropies, rad/s for
            "angular_rate_spread"); 0 before the first update.
    """

    def __init__(
        self,
        policy: PolicyCheckpoint | PolicyInference | EnsemblePolicyInference,
        offset_s: float = 0.0,
        period_s: float = robot.CONTROL_PERIOD_S,
        num_threads: int | None = 1,
        uncertainty_signal: str = DEFAULT_UNCERTAINTY_SIGNAL,
    ):
        """Declares the ports, the state and the periodic update.

        Args:
            policy: a trained policy (`ditch_drake.learning.checkpoint.load_checkpoint`), run
                in PyTorch, or an inference object of any runtime
                (`ditch_drake.learning.inference.load_policy`; an ensemble's has `members`
                and `member_logits`); its model config fixes the input sizes, its action table
                the commands.
            offset_s: time of the first update (s).
            period_s: update period (s), the control rate.
            num_threads: with a checkpoint, torch's intra-op threads, set once here for the
                whole process (`torch.set_num_threads` is process-wide); None leaves torch's
                setting. Default 1: one forward pass of one sample gains little from more
                threads, and rollouts run one process per core. An inference object comes
                with its own.
            uncertainty_signal: the `uncertainty` output's signal, a name of
                `ditch_drake.learning.uncertainty.UNCERTAINTY_SIGNALS`.

        Raises:
            ValueError: a non-positive period, a negative offset or a thread count < 1.
            ConfigError: an unknown signal, or a disagreement signal with a single clone,
                naming the signal and K.
        """
        super().__init__()
        if not (period_s > 0 and offset_s >= 0):
            raise ValueError(f"period_s={period_s} must be positive and offset_s={offset_s} non-negative")
        self._signal = uncertainty.uncertainty_signal(uncertainty_signal)
        self._inference = TorchInference(policy, num_threads) if isinstance(policy, PolicyCheckpoint) else policy
        self._members = int(getattr(self._inference, "members", 1))
        if uncertainty_signal in uncertainty.DISAGREEMENT_SIGNALS and self._members < 2:
            raise ConfigError(f"uncertainty signal {uncertainty_signal!r} with K = {self._members} member: it is the "
                              "members' disagreement; expected an ensemble of K >= 2 (ditch-drake train --ensemble) "
                              "or signal 'mean_softmax_entropy'")
        self._signal_name = uncertainty_signal
        config = self._inference.model_config
        self._image_shape = (1, config.image_channels, config.image_size, config.image_size)
        self._commands = np.asarray(self._inference.action_commands, dtype=float)
        self._image_port = self.DeclareVectorInputPort("image_stack", int(np.prod(self._image_shape)))
        self._imu_port = self.DeclareVectorInputPort("imu_stack", config.imu_size)
        self._distance_port = self.DeclareVectorInputPort("distance_stack", config.distance_size)
        self._bearing_port = self.DeclareVectorInputPort("bearing_stack", config.bearing_size)
        self._side_port = self.DeclareVectorInputPort("crossing_side", 1) if config.canonical_side else None
        self._command_index = self.DeclareDiscreteState(2)
        self._label_index = self.DeclareDiscreteState(np.array([-1.0]))
        self._probabilities_index = self.DeclareDiscreteState(config.num_labels)
        self._command_port = self.DeclareStateOutputPort("command", self._command_index)
        self._label_port = self.DeclareStateOutputPort("label", self._label_index)
        self._probabilities_port = self.DeclareStateOutputPort("probabilities", self._probabilities_index)
        self._uncertainty_index = self.DeclareDiscreteState(1)
        self._uncertainty_port = self.DeclareStateOutputPort("uncertainty", self._uncertainty_index)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)
        self.DeclareForcedDiscreteUpdateEvent(self._update)

    @property
    def runtime(self) -> str:
        """The runtime the network runs in (`ditch_drake.learning.inference.RUNTIMES`)."""
        return self._inference.runtime

    @property
    def action_commands(self) -> np.ndarray:
        """(num_labels, 2) [v m/s, w rad/s] per label (a copy)."""
        return self._commands.copy()

    @property
    def members(self) -> int:
        """K, the clones it runs (1 for a single checkpoint)."""
        return self._members

    @property
    def uncertainty_signal(self) -> str:
        """The name of the signal its `uncertainty` output reports."""
        return self._signal_name

    def infer(
        self, image_stack: np.ndarray, imu_stack: np.ndarray, distance_stack: np.ndarray, bearing_stack: np.ndarray,
        crossing_side: float = 1.0,
    ) -> tuple[int, np.ndarray]:
        """The chosen label and the (num_labels,) probabilities for one observation (port
        layouts); `crossing_side` -1 reflects both (canonical_side checkpoints)."""
        decision = self.decide(image_stack, imu_stack, distance_stack, bearing_stack, crossing_side)
        return decision.label, decision.probabilities

    def decide(
        self, image_stack: np.ndarray, imu_stack: np.ndarray, distance_stack: np.ndarray, bearing_stack: np.ndarray,
        crossing_side: float = 1.0,
    ) -> PolicyDecision:
        """The label, the probabilities (each member's and their mean) and the uncertainty for one
        observation (port layouts); `crossing_side` -1 reflects them (canonical_side checkpoints)."""
        batch = {
            "image": np.asarray(image_stack, dtype=np.float32).reshape(self._image_shape),
            **{name: np.asarray(x, dtype=np.float32).reshape(1, -1)
               for name, x in (("imu", imu_stack), ("distance", distance_stack), ("bearing", bearing_stack))},
        }
        reflect = self._side_port is not None and crossing_side < 0.0
        if reflect:
            batch = {name: value.copy() for name, value in batch.items()}
            mirror_left_right(batch)
        inputs = (batch[name] for name in ("image", "imu", "distance", "bearing"))
        if self._members > 1:
            logits = self._inference.member_logits(*inputs)[:, 0, :]  # (K, labels) of the one sample.
        else:
            logits = self._inference.logits(*inputs)  # (1, labels): the one member's.
        members = torch.softmax(torch.from_numpy(logits).double(), dim=-1).numpy()
        if reflect:
            # Label k turns as fast the other way as label num_labels - 1 - k (`mirror`).
            members = members[:, ::-1].copy()
        # One clone's probabilities are its own: no mean, so its numbers stay as they were.
        probabilities = members.mean(axis=0) if self._members > 1 else members[0]
        value = float(self._signal(members, self._commands[:, 1]))
        return PolicyDecision(int(np.argmax(probabilities)), probabilities, members, value)

    def _update(self, context, discrete_state: DiscreteValues) -> None:
        # Read-only views of the stacks (`Eval` would copy each first); `decide` casts them to float32.
        side = 1.0 if self._side_port is None else float(self._side_port.Eval(context)[0])
        decision = self.decide(
            *(port.EvalBasicVector(context).value()
              for port in (self._image_port, self._imu_port, self._distance_port, self._bearing_port)),
            crossing_side=side,
        )
        discrete_state.set_value(self._command_index, self._commands[decision.label])
        discrete_state.set_value(self._label_index, [float(decision.label)])
        discrete_state.set_value(self._probabilities_index, decision.probabilities)
        discrete_state.set_value(self._uncertainty_index, [decision.uncertainty])
