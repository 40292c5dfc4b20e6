"""The Gymnasium environment `DitchDrake-v0` (`ditch_drake.gym.env.DitchDrakeEnv`); docs/tutorials/gym.md.

Needs the `gym` extra (`pip install -e '.[gym]'`). Importing this module registers the id;
so does `import ditch_drake` when Gymnasium is imported already (importing Gymnasium costs
0.15 s, which the command line does not pay). So after `import gymnasium, ditch_drake` or
`import ditch_drake.gym`, `gymnasium.make("DitchDrake-v0", env="wide")` works, and
`gymnasium.make("ditch_drake:DitchDrake-v0", ...)` imports the package itself (the form for a
fresh process, such as a spawned vector-env worker).
"""

ENV_ID = "DitchDrake-v0"
ENTRY_POINT = "ditch_drake.gym.env:DitchDrakeEnv"


def register() -> None:
    """Registers `DitchDrake-v0` with Gymnasium (once; later calls do nothing)."""
    import gymnasium

    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point=ENTRY_POINT)


register()
