"""The settings table against the tracker it configures."""

from __future__ import annotations

from dataclasses import fields

from nsflow_ros.core.tracker import REBUILD_FIELDS, TrackerSettings
from nsflow_ros.vins.settings import SETTINGS, TRACKER_SETTINGS, Mode


def test_tracker_rows_are_tracker_settings_fields():
    names = {f.name for f in fields(TrackerSettings)}
    assert set(TRACKER_SETTINGS) <= names
    # stereo comes from the config's num_of_cam, not from a node parameter
    assert names - set(TRACKER_SETTINGS) == {"stereo"}


def test_rebuild_rows_are_what_the_tracker_cannot_change_live():
    rebuild = {s.name for s in SETTINGS if s.tracker and s.mode is Mode.REBUILD}
    live = {s.name for s in SETTINGS if s.tracker and s.mode is Mode.LIVE}
    assert rebuild == REBUILD_FIELDS - {"stereo"}
    assert not live & REBUILD_FIELDS
