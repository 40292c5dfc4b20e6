"""Shows on the Meshcat page who drives a shared rollout, so a person sees when the gate asks for help."""

from pydrake.geometry import Meshcat, Rgba, Sphere
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from ditch_drake.spec import robot, schedule

POLICY_RGBA = Rgba(0.1, 0.75, 0.2, 1.0)
FALLBACK_RGBA = Rgba(0.9, 0.1, 0.1, 1.0)
# The page's background while the fallback drives: a tint that cannot be missed.
_HELP_BACKGROUND = ([1.0, 0.75, 0.75], [1.0, 0.9, 0.9])
_CALM_BACKGROUND = ([0.5, 0.6, 0.7], [0.9, 0.92, 0.95])
HELP_BUTTON = "The policy is unsure: YOU steer"
MARKER_RADIUS_M = 0.18
MARKER_HEIGHT_M = 0.7  # Above the chassis frame's origin, clear of the robot's body.


class DriverIndicator(LeafSystem):
    """Marks the robot and the page by who drives: a sphere above the chassis (green while the
    policy drives, red while the fallback does), and, while the fallback drives, a tinted page
    background and a control named `HELP_BUTTON` in the Controls panel.

    A periodic publish at the control rate, after the gate's tick (`schedule.RECORDER_OFFSET_S`),
    sends the marker's colour and sets the background, and adds or removes the control as the
    driver changes (the page is the state: Meshcat knows its own controls).

    .. pydrake_system::

        name: DriverIndicator
        input_ports:
        - who_drives

    Ports:
        who_drives: [0] the policy drives, [1] the fallback (`SharedControl`'s output).
    """

    def __init__(self, meshcat: Meshcat, marker_parent_path: str, period_s: float = robot.CONTROL_PERIOD_S,
                 offset_s: float = schedule.RECORDER_OFFSET_S):
        """
        Args:
            meshcat: the page a person watches.
            marker_parent_path: the Meshcat path of the chassis (the marker is its child, so it
                moves with the robot), e.g. "/drake/illustration/husky/chassis".
            period_s: the control period (s).
            offset_s: when in each period it publishes (s), after the gate's tick.
        """
        super().__init__()
        self._meshcat = meshcat
        self._marker_path = f"{marker_parent_path.rstrip('/')}/driver_marker"
        self._driver_port = self.DeclareVectorInputPort("who_drives", 1)
        meshcat.SetObject(self._marker_path, Sphere(MARKER_RADIUS_M), POLICY_RGBA)
        meshcat.SetTransform(self._marker_path, RigidTransform([0.0, 0.0, MARKER_HEIGHT_M]))
        self.DeclarePeriodicPublishEvent(period_s, offset_s, self._show)

    @property
    def marker_path(self) -> str:
        """The Meshcat path of the coloured marker."""
        return self._marker_path

    def _show(self, context) -> None:
        fallback = self._driver_port.Eval(context)[0] == 1.0
        self._meshcat.SetProperty(self._marker_path, "color", _rgba_list(FALLBACK_RGBA if fallback else POLICY_RGBA))
        top, bottom = _HELP_BACKGROUND if fallback else _CALM_BACKGROUND
        self._meshcat.SetProperty("/Background", "top_color", top)
        self._meshcat.SetProperty("/Background", "bottom_color", bottom)
        shown = HELP_BUTTON in self._meshcat.GetButtonNames()
        if fallback and not shown:
            self._meshcat.AddButton(HELP_BUTTON)
        elif shown and not fallback:
            self._meshcat.DeleteButton(HELP_BUTTON)


def _rgba_list(rgba: Rgba) -> list[float]:
    return [rgba.r(), rgba.g(), rgba.b(), rgba.a()]
