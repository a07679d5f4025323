"""A tracker built from a VINS config: the config's settings, body_T_cam0 and VINS-Mono's fisheye mask."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from nsflow_ros.core.tracker import FeatureTracker
from nsflow_ros.vins.config import load_vins_config
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.tracker import (
    FISHEYE_MASK_NAME,
    find_fisheye_mask,
    load_static_masks,
    tracker_from_config,
)

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


def _euroc_copy(folder: Path, extra: str = "", stereo: bool = False) -> Path:
    folder.mkdir(exist_ok=True)
    src = ROOT / "config/euroc"
    for name in ("cam0_pinhole.yaml", "cam1_pinhole.yaml"):
        (folder / name).write_text((src / name).read_text())
    name = "euroc_stereo_imu_config.yaml" if stereo else "euroc_mono_imu_config.yaml"
    (folder / "cfg.yaml").write_text((src / name).read_text() + "\n" + extra)
    return folder / "cfg.yaml"


def test_static_masks_from_parameters_or_the_openvins_config_keys(tmp_path):
    cfg = load_vins_config(_euroc_copy(tmp_path / "a", stereo=True))
    w, h = cfg.image_width, cfg.image_height
    body = np.zeros((h, w), np.uint8)
    body[h - 100 :, :] = 255  # OpenVINS convention: 255 = masked out (the robot's body at the bottom)
    cv2.imwrite(str(tmp_path / "a" / "body0.png"), body)
    cv2.imwrite(str(tmp_path / "a" / "body1.png"), body[:, ::-1])
    m0, m1 = load_static_masks(cfg, tmp_path / "a" / "body0.png", None, "openvins")
    assert m1 is None and m0[h - 1, 0] == 0 and m0[0, 0] == 255  # the tracker's form: 255 = usable
    # OpenVINS's keys, relative to the config's folder; use_mask: 0 turns them off
    keyed = _euroc_copy(tmp_path / "a", 'mask0: "body0.png"\nmask1: "body1.png"\n', stereo=True)
    cfg = load_vins_config(keyed)
    assert cfg.mask0 == str(tmp_path / "a" / "body0.png") and cfg.mask1.endswith("body1.png")
    m0, m1 = load_static_masks(cfg, convention="openvins")
    tracker = tracker_from_config(cfg, {"method": "classical"}, masks=(m0, m1))
    np.testing.assert_array_equal(tracker.mask, m0)
    np.testing.assert_array_equal(tracker.mask1, m1)
    mono = tracker_from_config(cfg, {"method": "classical", "stereo": False}, masks=(m0, m1))
    assert mono.mask1 is None  # camera 0 of a stereo config: camera 1's mask has no use
    off = load_vins_config(_euroc_copy(tmp_path / "a", 'use_mask: 0\nmask0: "body0.png"\n', stereo=True))
    assert off.mask0 == "" and load_static_masks(off) == (None, None)


def test_static_mask_and_fisheye_mask_apply_together(tmp_path):
    path = _euroc_copy(tmp_path / "b", "fisheye: 1\n")
    cfg = load_vins_config(path)
    circle = _circle_mask(cfg.cameras[0], 200)
    cv2.imwrite(str(tmp_path / FISHEYE_MASK_NAME), circle)
    left = np.full_like(circle, 255)
    left[:, cfg.image_width // 2 :] = 0
    tracker = tracker_from_config(cfg, {"method": "classical"}, masks=(left, None))
    np.testing.assert_array_equal(tracker.mask, np.minimum(circle, left))
    # without a fisheye mask, mask0 alone applies: any camera model, independent of fisheye
    plain = load_vins_config(_euroc_copy(tmp_path / "c"))
    alone = tracker_from_config(plain, {"method": "classical"}, masks=(left,))
    np.testing.assert_array_equal(alone.mask, left)


def test_bad_static_masks_get_one_line_naming_the_file(tmp_path):
    cfg = load_vins_config(_euroc_copy(tmp_path / "d"))
    with pytest.raises(ConfigError, match=r"mask image not found: .*nope\.png"):
        load_static_masks(cfg, tmp_path / "nope.png")
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((20, 10), np.uint8))
    with pytest.raises(ConfigError, match=r"mask0 .*small\.png is 10x20 but the image size of .* is 752x480"):
        load_static_masks(cfg, small)
    with pytest.raises(ConfigError, match=r"mask1 .*small\.png given, but .*cfg\.yaml has one camera"):
        load_static_masks(cfg, None, small)
    with pytest.raises(ConfigError, match=r"mask convention must be one of"):
        load_static_masks(cfg, small, convention="upside-down")
    with pytest.raises(ConfigError, match=r"key 'mask0' names mask image .*gone\.png, which does not exist"):
        load_vins_config(_euroc_copy(tmp_path / "d", 'mask0: "gone.png"\n'))
    with pytest.raises(ConfigError, match=r"key 'mask1' names a mask of camera 1, but the config has 1 cam"):
        load_vins_config(_euroc_copy(tmp_path / "d", 'mask1: "small.png"\n'))
