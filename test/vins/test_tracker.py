"""A tracker built from a VINS config: the config's settings, body_T_cam0 and VINS-Mono's fisheye mask."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from nsflow_ros.core.tracker import FeatureTracker
from nsflow_ros.vins.config import load_vins_config
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.tracker import FISHEYE_MASK_NAME, find_fisheye_mask, tracker_from_config

ROOT = Path(__file__).resolve().parents[2]


def _circle_mask(cam, radius):
    mask = np.zeros((cam.height, cam.width), np.uint8)
    cv2.circle(mask, (cam.width // 2, cam.height // 2), radius, 255, -1)
    return mask


def test_tracker_from_config_takes_the_vins_settings():
    cfg = load_vins_config(ROOT / "config/euroc/euroc_stereo_imu_config.yaml")
    tracker = tracker_from_config(cfg, {"method": "classical", "max_cnt": 99})
    assert isinstance(tracker, FeatureTracker)
    s = tracker.settings
    assert s.stereo and s.flow_back and s.max_cnt == 99 and s.min_dist == cfg.min_dist
    assert isinstance(s.min_dist, float) and s.F_threshold == cfg.F_threshold and not s.reject_with_f
    np.testing.assert_allclose(tracker.body_R_cam0, cfg.body_T_cam[0][:3, :3])
    frame = np.zeros((cfg.image_height, cfg.image_width), np.uint8)
    out = tracker.process(0.0, frame, frame)
    assert out.num_cameras == 2 and len(out.cameras[0]) == 0  # black image: nothing to detect


def test_fisheye_config_finds_the_mask_where_vins_mono_keeps_it(tmp_path):
    folder = tmp_path / "euroc"
    folder.mkdir()
    src = ROOT / "config/euroc"
    for name in ("cam0_pinhole.yaml", "cam1_pinhole.yaml"):
        (folder / name).write_text((src / name).read_text())
    text = (src / "euroc_mono_imu_config.yaml").read_text() + "\nfisheye: 1\n"
    (folder / "cfg.yaml").write_text(text)
    cfg = load_vins_config(folder / "cfg.yaml")
    assert cfg.fisheye
    with pytest.raises(ConfigError, match=r"fisheye is 1 but no fisheye mask was found \(looked at .*euroc"):
        tracker_from_config(cfg, {"method": "classical"})
    # VINS-Mono keeps config/fisheye_mask.jpg beside config/<dataset>/; JPEG noise is thresholded away
    mask = _circle_mask(cfg.cameras[0], 200)
    cv2.imwrite(str(tmp_path / FISHEYE_MASK_NAME), mask)
    assert find_fisheye_mask(cfg.path) == tmp_path / FISHEYE_MASK_NAME
    tracker = tracker_from_config(cfg, {"method": "classical"})
    assert tracker.mask is not None and set(np.unique(tracker.mask)) == {0, 255}
    assert (tracker.mask == mask).mean() > 0.999
    # an explicit path wins; a missing one is named
    with pytest.raises(ConfigError, match=r"mask image not found: .*nope\.png"):
        tracker_from_config(cfg, {"method": "classical"}, fisheye_mask=tmp_path / "nope.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(ConfigError, match="cannot read mask image"):
        tracker_from_config(cfg, {"method": "classical"}, fisheye_mask=bad)
