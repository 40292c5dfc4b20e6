"""The picture of a search: walls by slope, windows, the path and the search's targets."""

import numpy as np
from PIL import Image

from ditch_drake.docs_tools.search_figure import SearchEpisode, _slope_image, save_search_figure
from ditch_drake.systems.episode_monitor import EpisodeOutcome
from ditch_drake.world.environments import get_environment
from ditch_drake.world.terrain import DitchTerrain
from ditch_drake.world.windows import windows_by_side


def _outcome() -> EpisodeOutcome:
    return EpisodeOutcome(status="reached_goal", time_s=50.0, path_length_m=40.0, peak_abs_roll_deg=40.0,
                          peak_abs_pitch_deg=30.0, peak_tilt_deg=50.0, min_stability_margin_deg=10.0,
                          final_xy=(0.0, 11.0))


def test_the_walls_are_green_in_the_windows_and_red_elsewhere():
    terrain = DitchTerrain(get_environment("wide_search").terrain)
    window = windows_by_side(terrain)["right"][0]
    lower, upper = np.array([-40.0, -10.0]), np.array([40.0, 10.0])
    rgba = _slope_image(terrain, lower, upper, 0.5)
    wall_y = -(terrain.toe_distance_m + 1.0)
    row = int((wall_y - lower[1]) / 0.5)
    inside = int((np.mean([window.from_xy[0], window.to_xy[0]]) - lower[0]) / 0.5)
    outside = int((20.0 - lower[0]) / 0.5)
    assert rgba[row, inside, 1] > rgba[row, inside, 0]
    assert rgba[row, outside, 0] > rgba[row, outside, 1]
    assert rgba[int((0.0 - lower[1]) / 0.5), inside, 3] == 0.0


def test_a_figure_of_two_episodes_has_two_panels(tmp_path):
    track = np.column_stack([np.linspace(0.0, -15.0, 20), np.linspace(-11.0, 11.0, 20)])
    with_search = SearchEpisode("searching", "wide_search", 0, 0, _outcome(), track, track[::2] + 1.0,
                                np.arange(10) % 6)
    without = SearchEpisode("expert", "wide_search_offset", 0, 0, _outcome(), track)
    path = save_search_figure([with_search, without], tmp_path / "search.png")
    width, height = Image.open(path).size
    assert height > width / 2
