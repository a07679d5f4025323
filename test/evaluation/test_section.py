"""The section helpers every analysis shares: its settings as JSON data and the quick-mode note."""

from __future__ import annotations

import json
from dataclasses import dataclass

from nsflow_ros.evaluation.section import QUICK_NOTE, config_data, quick_note


@dataclass(frozen=True)
class _Config:
    width: int = 320
    photos: tuple[str, ...] = ("a", "b")
    scale: float = 0.5


def test_config_data_lists_every_field_in_order_with_tuples_as_lists():
    data = config_data(_Config())
    assert data == {"width": 320, "photos": ["a", "b"], "scale": 0.5}
    assert list(data) == ["width", "photos", "scale"]
    assert json.loads(json.dumps(data)) == data


def test_quick_note_only_in_a_quick_run():
    assert quick_note(True) == QUICK_NOTE and "Quick mode" in QUICK_NOTE
    assert quick_note(False) == ""
