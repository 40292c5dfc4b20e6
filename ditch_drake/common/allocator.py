"""glibc's malloc keeps large freed blocks for reuse instead of returning them to the system.

A training step on a batch of 64 allocates tensors of 64 x 64 x 128 x 128 values (the first
convolution's output and, in the backward pass, max pooling's gradient buffer: 134 MB in
bfloat16, 268 MB in float32) and frees them before the next step. glibc serves blocks above its
mmap threshold with fresh mappings and unmaps them on free, so every step touches new pages:
about 111,000 page faults a step, half of a bfloat16 step's time on a 2-core CPU with AMX
(torch's profiler: the fills of those tensors took 18 ms with the blocks kept, 77 ms without).
Kept on the heap, the same blocks are reused from the second step on. The numbers computed
do not change, only where the memory comes from; the process holds on to its peak instead of
returning it.
"""

import ctypes
import sys

# glibc's mallopt parameters (malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
# Free memory at the heap's top beyond this is given back to the system: more than a step's
# largest blocks (two of 268 MB in float32), so they stay, while what a larger dataset's reading
# frees does not pile up.
TRIM_THRESHOLD_BYTES = 1 << 30


def keep_freed_memory() -> bool:
    """Asks glibc to serve every block from the heap and to keep up to `TRIM_THRESHOLD_BYTES` of
    free memory at its top (process-wide, from now on).

    Returns:
        Whether glibc took both settings; False on another platform or C library, where
        nothing changes.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
