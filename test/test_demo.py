"""The main job end to end: a replay over real ROS 2 topics reaches the tracker node and features return."""

from __future__ import annotations

import json

from nsflow_ros.demo import format_summary, run_demo


def test_replay_reaches_tracker_node_and_features_come_back(tmp_path):
    summary = run_demo(tmp_path, duration=1.0, seed=1, rate=1.0, levels=("none",), methods=("classical",))
    fig = summary["results"]["none"]["classical"]
    assert fig["frames_sent"] == 20
    assert fig["tracker_received"] == 20  # the publisher matched the tracker before the first frame
    assert fig["features_per_frame"] > 50
    assert fig["error_count"] > 200 and fig["error_median_px"] < 0.3
    assert (tmp_path / "tracks.png").stat().st_size > 10_000
    assert json.loads((tmp_path / "summary.json").read_text())["results"]["none"]["classical"]["frames"] > 0
    # the tracker node's own counts, from its summary file
    assert fig["frames"] <= fig["tracker_processed"] <= fig["tracker_received"] <= fig["frames_sent"]
    assert fig["tracker_dropped"] == fig["tracker_received"] - fig["tracker_processed"]
    table = format_summary(summary)
    assert "classical" in table and "recv" in table and "proc" in table
    row = next(line for line in table.splitlines() if line.startswith("none") and "classical" in line)
    counts = [fig["frames_sent"], fig["tracker_received"], fig["tracker_processed"]]
    assert row.split()[2:5] == [str(n) for n in counts]


def test_contact_sheet_has_a_legend_and_labels_on_dark_boxes():
    import numpy as np

    from nsflow_ros.vins.sheet import contact_sheet

    white = np.full((480, 752, 3), 255, np.uint8)
    sheet = contact_sheet([white, white], cols=2, labels=["nsflow", "klt"], legend=True)
    assert sheet.shape[1] == 2 * 376
    assert sheet.shape[0] == round(480 * 376 / 752) + 30  # the tiles, then the legend strip
    # the label box is dark even on a white image, its text white
    box = sheet[2:20, 2:40]
    assert box.min() < 60 and box.max() > 200
    # the legend strip shows the track-length colours: blue (new) to red (20+ frames)
    strip = sheet[-30:]
    assert (strip[..., 0] > 200).any() and (strip[..., 2] > 200).any()
