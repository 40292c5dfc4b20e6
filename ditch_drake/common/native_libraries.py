"""Two native libraries whose load order in one process matters: triton's and Mesa's LLVM.

triton (which PyPI's CUDA builds of torch install) links its own LLVM into `libtriton.so` and
exports its symbols. Drake's `RenderEngineVtk` renders headless through EGL, and Mesa loads its
driver (`swrast_dri.so`, with the system's `libLLVM-15.so.1`) RTLD_GLOBAL. A `libtriton.so`
loaded after that binds about 12,000 of its LLVM references to Mesa's LLVM 15 (`LD_DEBUG=bindings`)
and dies in its static initializers (SIGSEGV in `llvm::DebugCounter`). torch imports triton
whenever it is installed and an optimizer is made (`torch.optim.Adam` imports `torch._dynamo`,
which imports triton), so training after a lidar rendered in the same process (`ditch-drake
experiment`, `train-generalist`, the test suite) crashed. Loaded first, `libtriton.so` (RTLD_LOCAL)
binds to itself, Mesa's LLVM to itself, and both work. The CPU torch has no triton: nothing to do.
"""

import importlib.util
import sys


def _shared_llvm_loaded() -> bool:
    """Whether a shared libLLVM (Mesa's) is mapped into this process (False where /proc is not there)."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            return any("/libLLVM" in line for line in maps)
    except OSError:
        return False


def load_triton_before_mesa() -> None:
    """Imports triton, where it is installed and not imported yet: call before Drake's first renderer.

    Costs about 0.3 s, once per process. Where Mesa's LLVM is already loaded (something rendered
    first), triton could no longer load without crashing: it is marked missing instead
    (`sys.modules["triton"] = None`), so torch runs without it as with its CPU builds.
    """
    if "triton" in sys.modules or importlib.util.find_spec("triton") is None:
        return
    if _shared_llvm_loaded():
        sys.modules["triton"] = None
        return
    try:
        import triton  # noqa: F401
    except Exception:  # noqa: BLE001 - a triton that does not import is torch's to report, not the renderer's.
        pass
