"""The frame stacker's four stacks as one dictionary of shaped float32 arrays (a Gymnasium observation)."""

import numpy as np
from pydrake.common.value import Value
from pydrake.systems.framework import LeafSystem

from ditch_drake.spec.observation_layout import (
    BEARING_STACK_SIZE,
    DISTANCE_STACK_SIZE,
    IMAGE_STACK_SHAPE,
    IMAGE_STACK_SIZE,
    IMU_STACK_SIZE,
)

# Observation key -> (input port, size, shape).
OBSERVATION_LAYOUT = {
    "image": ("image_stack", IMAGE_STACK_SIZE, IMAGE_STACK_SHAPE),
    "imu": ("imu_stack", IMU_STACK_SIZE, (IMU_STACK_SIZE,)),
    "distance": ("distance_stack", DISTANCE_STACK_SIZE, (DISTANCE_STACK_SIZE,)),
    "bearing": ("bearing_stack", BEARING_STACK_SIZE, (BEARING_STACK_SIZE,)),
}


class ObservationDict(LeafSystem):
    """Packs the four stacked observations into one dictionary of float32 arrays.

    The keys and shapes are `OBSERVATION_LAYOUT`'s: "image" (4, 128, 128) in [0, 1],
    channel 0 newest; "imu" (8,) [roll_t, pitch_t, roll_t-1, ...] (rad); "distance" (4,)
    (m) and "bearing" (4,) (rad), newest first. float32 is what the network takes (the
    `LearnedPolicy` casts its inputs the same way), so a policy fed this dictionary sees
    the same numbers as the block. Each evaluation makes new arrays: a dictionary handed
    out earlier never changes.

    .. pydrake_system::

        name: ObservationDict
        input_ports:
        - image_stack
        - imu_stack
        - distance_stack
        - bearing_stack
        output_ports:
        - observation
    """

    def __init__(self):
        super().__init__()
        self._inputs = {key: (self.DeclareVectorInputPort(port, size), shape)
                        for key, (port, size, shape) in OBSERVATION_LAYOUT.items()}
        self.DeclareAbstractOutputPort(
            "observation", lambda: Value[object]({}), self._calc_observation,
            prerequisites_of_calc={port.ticket() for port, _ in self._inputs.values()})

    def _calc_observation(self, context, output) -> None:
        output.set_value({key: np.array(port.EvalBasicVector(context).value(), dtype=np.float32).reshape(shape)
                          for key, (port, shape) in self._inputs.items()})
