"""Turns one stream of uniform draws into a distinct stream per key (a rollout's ditch and task)."""

import zlib

import numpy as np
from pydrake.systems.framework import BasicVector, Context, LeafSystem


class KeyedUniform(LeafSystem):
    """Outputs a uniform draw in [0, 1) made from its input draw and a key: the same input and
    key give the same output, another key an unrelated one.

    A Drake `RandomSource` draws from the episode's seed alone, so episodes of one seed in
    different ditches (a benchmark split runs every ditch at seed 0) would read the same draws.
    Seeding numpy's generator with the input draw's 64 bits and the key's CRC-32 keeps the
    output uniform and independent from step to step (as the input is) while giving each key
    its own sequence.

    .. pydrake_system::

        name: KeyedUniform
        input_ports:
        - draw
        output_ports:
        - keyed_draw

    Ports:
        draw: [u] a uniform draw in [0, 1) (a `RandomSource`'s output).
        keyed_draw: [u'] the draw for this key, uniform in [0, 1).
    """

    def __init__(self, key: str):
        """
        Args:
            key: what makes this stream distinct, e.g. "ditch_2003/task1".
        """
        super().__init__()
        self._key = key
        self._key_crc = zlib.crc32(key.encode())
        self._draw_port = self.DeclareVectorInputPort("draw", 1)
        self.DeclareVectorOutputPort("keyed_draw", 1, self._calc_keyed_draw)

    @property
    def key(self) -> str:
        return self._key

    def keyed(self, draw: float) -> float:
        """The output for an input `draw`."""
        bits = int(np.float64(draw).view(np.uint64))
        return float(np.random.default_rng([bits, self._key_crc]).random())

    def _calc_keyed_draw(self, context: Context, output: BasicVector) -> None:
        output.SetAtIndex(0, self.keyed(self._draw_port.Eval(context)[0]))
