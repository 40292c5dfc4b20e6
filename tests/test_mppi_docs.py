"""The MPPI baseline's documentation tools: the picture at the hinge and the attitude validation."""

import numpy as np

from ditch_drake.diagrams.rollout import MppiBaselineConfig
from ditch_drake.planning.mppi import MppiPlannerConfig


def test_mppi_picture_repeats_the_blocks_update_and_writes_a_png(tmp_path):
    from ditch_drake.docs_tools.mppi_figure import draw_mppi_picture, run_mppi_to_hinge

    config = MppiBaselineConfig(planner=MppiPlannerConfig(samples=64))
    picture = run_mppi_to_hinge("wide_walled", task=1, seed=0, config=config, end_time_s=0.8)
    assert picture.command_matches and picture.result.admissible  # The block's own update, repeated.
    assert picture.result.sample_poses.shape[0] == 64 and picture.edge_distance_m > 1.0  # Still on the flat.
    path = draw_mppi_picture(picture, tmp_path / "mppi.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_figure_command_knows_mppi():
    from ditch_drake.cli import build_parser

    assert build_parser().parse_args(["figure", "mppi", "--env", "wide_walled"]).kind == "mppi"


def test_attitude_validation_traces_an_expert_drive_and_summarizes(tmp_path):
    from ditch_drake.validation.mppi_validation import draw_traces, markdown_table, summarize, trace_expert_drive

    trace = trace_expert_drive("wide_walled", 0, 0, end_time_s=1.0)
    arrays = trace.arrays()
    assert len(arrays["time_s"]) == 10 and arrays["true_rpy"].shape == (10, 2)
    # On the flat start the prediction on the block's map is level, as the simulator's chassis.
    assert np.all(np.abs(np.degrees(arrays["controller"] - arrays["true_rpy"])) < 1.0)
    rows = summarize([trace])
    assert rows["wide_walled"]["steps"] == 10 and rows["wide_walled"]["roll_p95_deg"] < 1.0
    assert "wide_walled" in markdown_table(rows)
    assert draw_traces([trace], tmp_path / "v.png").read_bytes()[:4] == b"\x89PNG"
