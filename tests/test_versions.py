"""What differs between the supported Drake, torch and Python versions.

- pydrake 1.58's nanobind `Value[object]` refuses None (1.51's pybind11 one held it): the Gym
  action block's "no action" is `NO_ACTION`, with None still taken where Drake takes it.
- triton (in PyPI's CUDA torch; torch imports it when training makes its optimizer) crashes
  (SIGSEGV) when loaded after Drake's RenderEngineVtk has rendered in the process: Mesa's EGL
  driver puts its libLLVM-15 in the global symbol scope and triton's own LLVM binds to it
  (`ditch_drake.common.native_libraries`). The lidar loads triton before its renderer. CI's CPU
  torch has no triton: there a stand-in package checks the order; with PyPI's torch,
  `test_training_after_a_lidar_rendered_does_not_crash` is the crash check itself.
"""

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from pydrake.common.value import Value

from ditch_drake.spec import actions
from ditch_drake.systems.action_label_input import NO_ACTION, ActionLabelInput


def _stands_still(block, context) -> bool:
    return (list(block.GetOutputPort("command").Eval(context)) == [0.0, 0.0]
            and list(block.GetOutputPort("label").Eval(context)) == [-1.0])


def test_the_action_block_stands_still_without_an_action_on_this_drake():
    block = ActionLabelInput()  # Its model value held None before: a TypeError on pydrake 1.58.
    context = block.CreateDefaultContext()
    assert _stands_still(block, context)  # Nothing fixed on the port.
    block.GetInputPort("action").FixValue(context, 3)
    np.testing.assert_array_equal(block.GetOutputPort("command").Eval(context), actions.COMMANDS[3])
    for none in (NO_ACTION, np.int64(NO_ACTION)):
        block.GetInputPort("action").FixValue(context, none)
        assert _stands_still(block, context)


def test_none_still_means_no_action_where_drake_holds_none():
    try:
        Value[object](None)
    except TypeError:
        pytest.skip("this pydrake's Value[object] refuses None (nanobind bindings): NO_ACTION is the only way")
    block = ActionLabelInput()
    context = block.CreateDefaultContext()
    block.GetInputPort("action").FixValue(context, 5)
    block.GetInputPort("action").FixValue(context, None)
    assert _stands_still(block, context)



# A lidar scan in the wide ditch (Drake's RenderEngineVtk through EGL: Mesa and its LLVM), then,
# with "train", a tiny training run in the same process. Prints what was loaded.
LIDAR_THEN_TRAIN = """
import json, sys
import numpy as np
from pydrake.systems.framework import DiagramBuilder
from ditch_drake.diagrams.ditch_scene import AddDitchScene, SceneConfig
from ditch_drake.diagrams.lidar_rig import AddLidar

def mapped(name):
    return any(name in line for line in open("/proc/self/maps"))

builder = DiagramBuilder()
scene = AddDitchScene(builder, SceneConfig(environment="wide"))
lidar = AddLidar(builder, scene)
diagram = builder.Build()
context = diagram.CreateDefaultContext()
converter_context = lidar.converter.GetMyMutableContextFromRoot(context)
lidar.converter.ExecuteForcedEvents(converter_context)
points = lidar.converter.GetOutputPort("point_cloud").Eval(converter_context).size()
result = {"points": points, "llvm_after_render": mapped("/libLLVM")}
if "train" in sys.argv:
    from ditch_drake.learning.data import ArraySet
    from ditch_drake.learning.train import TrainConfig, train
    rng = np.random.default_rng(0)
    n = 24
    arrays = ArraySet(image=rng.integers(0, 256, (n, 4, 128, 128), dtype=np.uint8), imu=rng.normal(0, 0.2, (n, 8)),
                      distance=rng.uniform(0, 20, (n, 4)), bearing=rng.uniform(-3, 3, (n, 4)),
                      label=rng.integers(0, 17, n), demo_id=np.arange(n) * 4 // n)
    train(arrays, TrainConfig(epochs=1, batch_size=8, max_batches_per_epoch=1, num_threads=1, val_fraction=0.25,
                              seed=1), progress=False)
result["triton_imported"] = sys.modules.get("triton") is not None
result["triton_mapped"] = mapped("libtriton")
print(json.dumps(result))
"""


def _run(code: str, *args: str, env: dict | None = None) -> dict:
    result = subprocess.run([sys.executable, "-X", "faulthandler", "-c", code, *args], capture_output=True,
                            text=True, timeout=300, check=False, env=env)
    assert result.returncode == 0, f"exit code {result.returncode}\n{result.stderr[-3000:]}"
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_training_after_a_lidar_rendered_does_not_crash():
    """With PyPI's CUDA torch (triton installed) this crashed with SIGSEGV (exit code -11) before
    the lidar loaded triton first; with the CPU torch it checks render-then-train runs."""
    loaded = _run(LIDAR_THEN_TRAIN, "train")
    assert loaded["points"] > 1000, loaded
    assert loaded["triton_mapped"] == (importlib.util.find_spec("triton") is not None), loaded


STAND_IN_TRITON = """
import os
with open(os.environ["TRITON_LOG"], "w") as log:
    log.write(str(any("/libLLVM" in line for line in open("/proc/self/maps"))))
"""


def test_the_lidar_imports_triton_before_its_renderer_loads_mesa(tmp_path):
    """On any torch: a stand-in `triton` package, first on the path, notes whether Mesa's LLVM
    was already loaded when it was imported."""
    (tmp_path / "triton").mkdir()
    (tmp_path / "triton" / "__init__.py").write_text(STAND_IN_TRITON)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]),
           "TRITON_LOG": str(tmp_path / "log")}
    loaded = _run(LIDAR_THEN_TRAIN, env=env)
    assert loaded["triton_imported"], loaded
    assert (tmp_path / "log").read_text() == "False", "triton was imported after Mesa's LLVM"
    if not loaded["llvm_after_render"]:
        pytest.skip("this machine's EGL renders without a shared libLLVM: the order cannot matter here")


def test_triton_is_marked_missing_when_mesa_was_first(tmp_path):
    """Where something rendered before the lidar, triton can no longer load: torch must not try."""
    (tmp_path / "triton").mkdir()
    (tmp_path / "triton" / "__init__.py").write_text("raise SystemExit('the stand-in triton was imported')")
    code = ("import sys; from ditch_drake.common import native_libraries as n; n._shared_llvm_loaded = lambda: True; "
            "n.load_triton_before_mesa(); import json; print(json.dumps({'missing': sys.modules['triton'] is None}))")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    assert _run(code, env=env) == {"missing": True}
