"""The observation's numbers (docs/design.md, "The observation"), in one place.

One control step observes a surface-normal image, the chassis roll and pitch, and the
distance and bearing to the goal; the policy sees the last `STACK_DEPTH` steps of each,
newest first, zeros before the first step. Every other module imports these.

Layouts (all flat float vectors on Drake ports):
- image: `IMAGE_SIZE` x `IMAGE_SIZE`, row-major (index r * IMAGE_SIZE + c), values in [0, 1].
- image stack: `IMAGE_STACK_SHAPE` = (channels, rows, cols), channel-major, channel 0
  newest; `stack.reshape(IMAGE_STACK_SHAPE)` gives the network's input layout.
- IMU stack: [roll_t, pitch_t, roll_t-1, pitch_t-1, ...] (rad), newest first.
- distance and bearing stacks: [value_t, value_t-1, ...], newest first.
"""

# The paper's image is N x M = 128 x 128 (section 3.1).
IMAGE_SIZE = 128
IMAGE_SHAPE = (IMAGE_SIZE, IMAGE_SIZE)
IMAGE_PIXELS = IMAGE_SIZE * IMAGE_SIZE

# The paper stacks every input over 4 control steps (section 3.2).
STACK_DEPTH = 4

# One step's scalar observations.
IMU_SIZE = 2  # roll, pitch (rad)
DISTANCE_SIZE = 1  # planar distance to the goal (m)
BEARING_SIZE = 1  # goal direction minus robot yaw (rad), wrapped to (-pi, pi]

# Stacked sizes.
IMAGE_STACK_SHAPE = (STACK_DEPTH, IMAGE_SIZE, IMAGE_SIZE)
IMAGE_STACK_SIZE = STACK_DEPTH * IMAGE_PIXELS
IMU_STACK_SIZE = STACK_DEPTH * IMU_SIZE
DISTANCE_STACK_SIZE = STACK_DEPTH * DISTANCE_SIZE
BEARING_STACK_SIZE = STACK_DEPTH * BEARING_SIZE
