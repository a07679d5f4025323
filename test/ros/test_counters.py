"""The node's table of causes: one counter per cause, each named once, summed as documented."""

from __future__ import annotations

import pytest

from nsflow_ros.ros.counters import CAUSES, Kind, NodeCounters, image_cause


def test_every_cause_has_one_counter_name_and_label():
    names = [c.name for c in CAUSES]
    assert len(set(names)) == len(names) == len({(c.unit, c.label) for c in CAUSES})
    assert all(c.unit in ("image", "frame") and c.meaning for c in CAUSES)
    totals = NodeCounters().totals()
    assert set(names) <= set(totals) and all(v == 0 for v in totals.values())


def test_dropped_is_every_frame_cause_but_events_and_held_frames_and_refused_is_bad_input_only():
    c = NodeCounters()
    for cause in CAUSES:
        c.count(cause.key, 2)
    frame_causes = [x for x in CAUSES if x.unit == "frame"]
    # an event (tracks reset) or a frame held back by publish_rate was tracked: not dropped
    assert c.frames_dropped == 2 * sum(x.kind not in (Kind.EVENT, Kind.HELD) for x in frame_causes)
    assert c.totals()["frames_throttled"] == 2 and c.totals()["frames_mask_wait"] == 2
    assert c.frames_refused == 2 * sum(x.kind is Kind.REFUSED for x in frame_causes)
    assert c.totals()["images_unpaired"] == c.images_unpaired == 2
    before = c.totals()
    c.count("superseded", detail="superseded")
    assert {k: v for k, v in c.since(before).items() if v} == {"frames_superseded": 1, "frames_dropped": 1}
    with pytest.raises(KeyError, match="unknown counter cause 'late_mask'; known: undecodable"):
        c.count("late_mask")


@pytest.mark.parametrize(("detail", "key"), [
    ("format:webp", "wrong_encoding"), ("encoding:bayer_rggb8", "wrong_encoding"), ("size", "wrong_size"),
    ("truncated:png", "undecodable"), ("step", "undecodable"), ("corrupt:jpeg", "undecodable"),
])
def test_decoder_causes_map_to_one_counter(detail, key):
    assert image_cause(detail) == key
