"""The front-end's settings: one typed table that every other view of them is derived from.

From :data:`SETTINGS` come the node's parameters, ``--help`` and ``config/tracker_params.yaml``
(:mod:`nsflow_ros.ros.tracker_params`), the VINS-config overrides
(:func:`nsflow_ros.vins.config.apply_overrides`), the tracker's settings and what
:class:`~nsflow_ros.vins.session.FrontEndSession` does with a change at run time. A setting with a VINS key
takes :data:`KEEP` (-1) for "the VINS config's value", which is why switches are integers (-1 / 0 / 1).
Imports neither rclpy nor torch, so ``--help`` needs no middleware.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any

from nsflow_ros.resources import DEFAULT_CONFIG
from nsflow_ros.vins.errors import ConfigError
from nsflow_ros.vins.pairing import STEREO_SYNC_TOLERANCE

__all__ = [
    "KEEP",
    "KINDS",
    "SESSION_SETTINGS",
    "SETTINGS",
    "TRACKER_SETTINGS",
    "VINS_KEYS",
    "Mode",
    "Setting",
    "Value",
    "is_unset",
    "session_tracker_fields",
    "setting",
]

Value = bool | int | float | str

KEEP = -1
"""A setting's value meaning "the default": the VINS config's value for a setting with a VINS key."""

KINDS = {bool: "boolean", int: "integer", float: "number", str: "string"}
"""A value type in words, as help texts and error messages name it."""


class Mode(Enum):
    """When a setting may change."""

    LIVE = "live"
    """A change at run time applies to the running tracker."""
    REBUILD = "rebuild"
    """A change at run time builds a new tracker (its encoder or image preparation changes)."""
    READ_ONLY = "read-only"
    """Set at start-up; a change at run time is refused."""


@dataclass(frozen=True)
class Setting:
    """One setting.

    Attributes:
        name: the ROS parameter name (and the TrackerSettings field for a tracker setting).
        default: the default value; its Python type is the setting's type.
        mode: when it may change.
        description: what it does and what special values mean (its mode and unit are added).
        unit: the unit of its value ("" = none).
        vins_key: the VINS config key it overrides (:data:`KEEP` = the file's value); None = none.
        tracker: a field of :class:`~nsflow_ros.core.tracker.TrackerSettings` of the same name.
        session: taken by :class:`~nsflow_ros.vins.session.FrontEndSession` (else the node's alone).
        minimum: the smallest value allowed (numbers; :data:`KEEP` aside); None = any.
        maximum: the largest value allowed (numbers); None = any.
        positive: the value must be > ``minimum`` rather than >= it.
        choices: the only values allowed (numbers); None = any in the range.
        switch: an integer 0/1 (or true/false) switch.
        none_value: the value that stands for None in TrackerSettings ("" = shipped model, 0 = all cores).
        tracker_type: the TrackerSettings field's type where it differs from the setting's (None = same).
        example: a typical value for error messages (None = the default).
    """

    name: str
    default: Value
    mode: Mode
    description: str
    unit: str = ""
    vins_key: str | None = None
    tracker: bool = False
    session: bool = False
    minimum: float | None = None
    maximum: float | None = None
    positive: bool = False
    choices: tuple[int, ...] | None = None
    switch: bool = False
    none_value: Value | None = None
    tracker_type: type | None = None
    example: Value | None = None

    @property
    def type(self) -> type:
        """The Python type of the setting's values."""
        return type(self.default)

    @property
    def kind(self) -> str:
        """The type in words: boolean, integer, number or string."""
        return KINDS[self.type]

    @property
    def full_description(self) -> str:
        """The description plus the VINS key's default and when it may change."""
        text = self.description
        if self.vins_key is not None:
            text += f" {KEEP} = from the VINS config."
        when = {
            Mode.LIVE: "Can change at run time.",
            Mode.REBUILD: "Can change at run time; a change restarts the tracks (ids keep counting up).",
            Mode.READ_ONLY: "Read-only: set at start-up.",
        }[self.mode]
        return f"{text} {when}"

    def check(self, value: Any) -> Value:
        """The value that overrides the VINS config (not :data:`KEEP`) as int, bool (switch) or float.

        A switch takes true/false or 0/1, a number an integer too.

        Raises:
            ConfigError: naming the setting, the value and what is expected.
        """
        name = self.name
        if self.switch:
            if isinstance(value, bool):
                return value
            if isinstance(value, numbers.Integral) and int(value) in (0, 1):
                return bool(value)
            got = _describe(value)
            raise ConfigError(
                f"tracker setting '{name}' must be true/false or 0/1 (or {KEEP} to keep), got {got}"
            )
        if self.type is int:
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ConfigError(f"tracker setting '{name}' must be an integer, got {_describe(value)}")
            if self.minimum is not None and int(value) < self.minimum:
                raise ConfigError(
                    f"tracker setting '{name}' must be >= {self.minimum:g} (or {KEEP} to keep), got {value}"
                )
            return int(value)
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ConfigError(f"tracker setting '{name}' must be a number, got {_describe(value)}")
        out = float(value)
        low = self.minimum
        if not math.isfinite(out) or (low is not None and (out <= low if self.positive else out < low)):
            bound = "" if low is None else f" {'>' if self.positive else '>='} {low:g}"
            raise ConfigError(
                f"tracker setting '{name}' must be a finite number{bound} (or {KEEP} to keep), got {out}"
            )
        return out

    @property
    def bound(self) -> str:
        """The range in words, e.g. ">= 1" or "in [0, 1]"; "" when any value of the type is allowed."""
        low, high = self.minimum, self.maximum
        if low is not None and high is not None and not self.positive:
            return f"in [{low:g}, {high:g}]"
        words = [f"{'>' if self.positive else '>='} {low:g}"] if low is not None else []
        words += [f"<= {high:g}"] if high is not None else []
        return " and ".join(words)

    @property
    def keeps(self) -> bool:
        """Whether :data:`KEEP` (-1) is a value of this setting: its default ("the VINS config's value" or
        the layout's choice). Anywhere else -1 is out of range like any other value."""
        return not isinstance(self.default, bool) and isinstance(self.default, int | float) \
            and self.default == KEEP

    def problem(self, value: Value) -> str | None:
        """What is wrong with a value of the right type ("expected ..."); None when it is allowed.

        The one range rule of the node's parameters, at start-up and at run time: :data:`KEEP` only where it
        is the default (:attr:`keeps`), a switch 0 or 1, :attr:`choices`, then :attr:`minimum` and
        :attr:`maximum`.
        """
        if isinstance(value, bool) or not isinstance(value, int | float):
            return None  # strings and booleans: their type is their range
        keep = f" (or {KEEP}: the default)" if self.keeps else ""
        if self.keeps and value == KEEP:
            return None
        if self.switch:
            return None if value in (0, 1) else f"0 or 1{keep}"
        if self.choices is not None:
            return None if value in self.choices else f"one of {', '.join(map(str, self.choices))}"
        low, high = self.minimum, self.maximum
        below = low is not None and (value <= low if self.positive else value < low)
        above = high is not None and value > high
        if below or above:
            return f"{'an' if self.kind[0] in 'aeiou' else 'a'} {self.kind} {self.bound}{keep}"
        return None


def _describe(value: Any) -> str:
    return "no value" if value is None else f"{type(value).__name__} {value!r}"


def is_unset(value: Any) -> bool:
    """True for the values that mean "the default": None, "" and :data:`KEEP` (not a bool)."""
    if value is None or (isinstance(value, str) and value == ""):
        return True
    return not isinstance(value, bool) and isinstance(value, int | float) and value == KEEP


SETTINGS: tuple[Setting, ...] = (
    Setting(
        "config_file", DEFAULT_CONFIG, Mode.READ_ONLY,
        "VINS-Fusion or VINS-Mono config file (OpenCV YAML). A relative path is looked up in the package's "
        "share directory (where config/ is installed), then in the working directory."),
    Setting(
        "method", "nsflow", Mode.REBUILD,
        "Tracking method: 'nsflow' (learned descriptors + Levenberg-Marquardt LK, the paper's tracker), "
        "'nsflow_lk' (the same descriptors as uint8 through OpenCV's pyramidal LK, faster), 'classical' "
        "(the image intensity through the LM solver) or 'klt' (OpenCV calcOpticalFlowPyrLK as VINS-Fusion "
        "calls it: 21x21 window, maxLevel 3, 30 iterations / eps 0.01).",
        tracker=True, session=True),
    Setting(
        "model_path", "", Mode.REBUILD,
        "ONNX encoder of the learned methods ('nsflow', 'nsflow_lk'): a file, or a model shipped in the "
        "package's models/ folder by name: '' or 'default' (also 'fast': one descriptor channel, compared "
        "up to a gain on the finest level; keeps up beside an estimator on two cores; 'nsflow_lk' takes "
        "'d4' instead) or 'd4' (the paper's four-channel descriptors: about 1.6x the CPU per frame, for a "
        "GPU provider or many cores). Its maps are smoothed as its metadata 'smoothing' declares.",
        tracker=True, session=True, none_value=""),
    Setting(
        "max_cnt", KEEP, Mode.LIVE, "Most features kept per image (VINS max_cnt, >= 1).", unit="features",
        vins_key="max_cnt", tracker=True, session=True, minimum=1, example=150),
    Setting(
        "min_dist", KEEP, Mode.LIVE, "Minimum distance between features in pixels (VINS min_dist, >= 0).",
        unit="px", vins_key="min_dist", tracker=True, session=True, minimum=0, tracker_type=float,
        example=30),
    Setting(
        "F_threshold", float(KEEP), Mode.LIVE,
        "RANSAC threshold in pixels of the fundamental-matrix check (VINS F_threshold, > 0; an integer "
        "is accepted).",
        unit="px", vins_key="F_threshold", tracker=True, session=True, minimum=0, positive=True, example=1.0),
    Setting(
        "flow_back", KEEP, Mode.LIVE,
        "Check every track and drop the bad ones (VINS flow_back), 0/1: VINS's reverse solve (back within "
        "0.5 px), or for an LM method its covariance check (see reverse_checks).",
        vins_key="flow_back", tracker=True, session=True, switch=True, example=1),
    Setting(
        "reverse_checks", 0, Mode.LIVE,
        "With flow_back, check an LM method's tracks by VINS's reverse solves (back within 0.5 px) instead "
        "of its covariance check (sigma and, for stereo, the epipolar distance; docs/benchmarks.md has the "
        "cost and catch of each), 0/1. 'klt' and 'nsflow_lk' always solve in reverse.",
        tracker=True, session=True, switch=True),
    Setting(
        "show_track", KEEP, Mode.LIVE, "Publish the image_track debug image (VINS show_track), 0/1.",
        vins_key="show_track", session=True, switch=True),
    Setting(
        "freq", KEEP, Mode.LIVE,
        "Feature publishing rate in Hz of the 'mono' layout (VINS-Mono freq; 0 = 100 Hz, in effect every "
        "image, as in VINS-Mono); frames in between are tracked but not published. The 'fusion' layout "
        "ignores it (publish_rate sets its rate).",
        unit="Hz", vins_key="freq", session=True, minimum=0, example=10),
    Setting(
        "publish_rate", float(KEEP), Mode.LIVE,
        "Feature messages per second at most, for an estimator that cannot take every frame (e.g. 10 on a "
        "small computer, as VINS-Fusion's own front-end feeds its estimator every 2nd frame with "
        "multiple_thread: 1): every frame is still tracked, a frame is published when VINS-Mono's rate "
        "control lets it through, and the published velocities are taken over the interval since the "
        "previous published frame. 0 = every frame. -1 = the layout's default: every frame for 'fusion' "
        "(VINS-Fusion ignores freq), the config's freq for 'mono'. Given for the 'mono' layout it replaces "
        "freq.",
        unit="Hz", session=True, minimum=0, example=10.0),
    Setting(
        "downsample", 1, Mode.REBUILD,
        "Track on images decimated by this factor, 1, 2 or 4 (cv2.resize INTER_AREA; for cameras larger "
        "than 752x480, e.g. 1280x800 with 2): the calibration is scaled inside (pixel centres: x_small = "
        "(x + 0.5) / factor - 0.5), min_dist is divided by the factor so the features keep the layout they "
        "have at full resolution, and the published pixels, undistorted points and velocities are in the "
        "config's full-resolution calibration, so the estimator's config stays as it is. The image size "
        "must be divisible by the factor.",
        tracker=True, session=True, minimum=1, choices=(1, 2, 4), example=2),
    Setting(
        "equalize", KEEP, Mode.REBUILD,
        "Equalise the image (CLAHE) before tracking (VINS-Mono equalize), 0/1.",
        vins_key="equalize", tracker=True, session=True, switch=True),
    Setting(
        "reject_with_f", KEEP, Mode.LIVE,
        "Fundamental-matrix RANSAC on tracked points, 0/1. -1 = on for the 'mono' layout (VINS-Mono does "
        "it), off for 'fusion' (VINS-Fusion does not).",
        tracker=True, session=True, switch=True),
    Setting(
        "publish_covariance", KEEP, Mode.LIVE,
        "Publish each feature's calibrated pixel covariance (sigma_uu, sigma_uv, sigma_vv in px^2, from the "
        "final solve's J^T J and residual, scaled as fitted for the method and model) as three channels "
        "after the layout's own: 9-11 of 'fusion', 5-7 of 'mono'; the stock estimators ignore them "
        "(docs/vins_fusion.md: a patch that uses them), 0/1. -1 = on for the 'fusion' layout with an LM "
        "method ('nsflow', 'classical': the solver's own J^T J, no measurable cost), off for the OpenCV LK "
        "methods ('klt', 'nsflow_lk': read again from the windows, 3-8 % of their frame's CPU) and for "
        "'mono'.",
        tracker=True, session=True, switch=True),
    Setting(
        "max_sigma", 0.0, Mode.LIVE,
        "Drop a tracked feature whose predicted standard deviation along its covariance's major axis "
        "exceeds this, as the flow-back check drops one (counted as gated on /diagnostics); 0 = off.",
        unit="px", tracker=True, session=True, minimum=0),
    Setting(
        "output_layout", "", Mode.READ_ONLY,
        "Feature message layout: 'fusion' (VINS-Fusion channels: id, camera, u, v, vx, vy + 3 zeros, then "
        "the covariance's 3 with publish_covariance) or 'mono' (VINS-Mono channels: id * NUM_OF_CAM + "
        "camera, u, v, vx, vy; first frame dropped, freq throttling, restart on stamp gaps). '' = the "
        "dialect of the config file."),
    Setting(
        "feature_topic", "/feature_tracker/feature", Mode.READ_ONLY,
        "Topic of the features (sensor_msgs/PointCloud, reliable, keep-last 2000); the VINS estimators "
        "listen here."),
    Setting(
        "restart_topic", "/feature_tracker/restart", Mode.READ_ONLY,
        "Topic of the std_msgs/Bool restart signal of the 'mono' layout (stamp gap > 1 s or time going "
        "backwards)."),
    Setting(
        "image_track_topic", "image_track", Mode.READ_ONLY,
        "Topic of the debug image (sensor_msgs/Image, bgr8)."),
    Setting(
        "use_imu_prediction", False, Mode.READ_ONLY,
        "Predict feature positions from the gyroscope (needs imu_topic and body_T_cam0 in the VINS config).",
        tracker=True, session=True),
    Setting(
        "num_threads", 1, Mode.REBUILD,
        "CPU threads of the encoder (one spends the least CPU per frame, more cut its wall time); 0 = all "
        "usable cores.",
        tracker=True, session=True, minimum=0, none_value=0),
    Setting(
        "fisheye_mask", "", Mode.READ_ONLY,
        "Mask image (255 = usable) for a VINS config with fisheye: 1 (VINS-Mono's fisheye mask): tracked "
        "points on its zeros are dropped and no corners are detected there. '' = fisheye_mask.jpg in the "
        "config's folder or its parent, where VINS-Mono keeps it. Unused when the config's fisheye is 0."),
    Setting(
        "mask0", "", Mode.READ_ONLY,
        "Static mask image of camera 0 (8-bit, the camera's image size, any camera model; read as "
        "mask_convention says): no corner is detected and no track is kept on its masked pixels, e.g. the "
        "robot's own body. With fisheye: 1 both masks apply. '' = the VINS config's mask0 key (OpenVINS's, "
        "relative to the config's folder), else none.",
        example="mask_cam0.png"),
    Setting(
        "mask1", "", Mode.READ_ONLY,
        "Static mask image of camera 1 (stereo), as mask0: right-camera matches on its masked pixels are "
        "dropped. '' = the VINS config's mask1 key, else none.",
        example="mask_cam1.png"),
    Setting(
        "mask_convention", "vins", Mode.READ_ONLY,
        "How mask0, mask1 and the mask topics are read: 'vins' = 255 where features may be, 0 where none "
        "may be (VINS-Mono's fisheye_mask); 'openvins' = 255 where none may be (OpenVINS's mask0 / mask1, a "
        "segmentation's object pixels). A pixel > 127 counts as 255. The fisheye_mask is always 'vins'.",
        example="openvins"),
    Setting(
        "mask_min_usable", 0.25, Mode.READ_ONLY,
        "A static mask (mask0, mask1, the fisheye mask) that leaves less than this share of its image "
        "usable is warned about at start-up with its share; one with no usable pixel stops the node (and "
        "nsflow-replay --offline / --features-bag) with one line. Masks below it are named as the likely "
        "cause when the tracking state drops. 0.25: EuRoC's max_cnt 150 features at min_dist 30 px need "
        "about a third of a 752x480 image, so below a quarter they crowd or fall short.",
        unit="share", minimum=0, maximum=1),
    Setting(
        "mask_topic", "", Mode.READ_ONLY,
        "Topic of per-frame masks of camera 0 (sensor_msgs/Image mono8, the camera's size, stamped like its "
        "images, e.g. moving objects from a segmentation node; read as mask_convention says): a frame takes "
        "the mask within stereo_sync_tolerance of its stamp and publishes no feature on its masked pixels, "
        "besides the static masks. A frame whose mask has not come by the time it is tracked (see "
        "mask_wait_ms) is tracked with the static masks only; masks missing, late (after their frame was "
        "tracked) or refused (wrong size or encoding) are counted on /diagnostics. '' = none.",
        example="/segmentation/mask"),
    Setting(
        "mask1_topic", "", Mode.READ_ONLY,
        "Topic of per-frame masks of camera 1 (stereo), as mask_topic; '' = camera 1 has none (with "
        "mask_topic alone only the left features are masked: a right point is kept or dropped with its "
        "left one, and by the static mask1).",
        example="/segmentation/mask_right"),
    Setting(
        "mask_wait_ms", 0.0, Mode.LIVE,
        "How long a frame may wait for its per-frame mask before it is tracked without it (from the "
        "arrival of its image; the node goes on receiving meanwhile). 0 = no wait: only a mask that came "
        "before its frame's turn is used. Raise it to the segmentation's latency behind the camera when "
        "/diagnostics counts masks as late. A wait also ends when the next frame arrives, and after a wait "
        "that ran out the node stops waiting for that topic until a mask comes again (it says so once), so "
        "a silent mask publisher costs no frame: a wait lasts at most one frame period. At most 1000 (a mask "
        "a second behind its camera is of no use at camera rate).",
        unit="ms", minimum=0, maximum=1000),
    Setting(
        "queue_size", 1, Mode.READ_ONLY,
        "Frames waiting for the tracker at most (>= 1). When the tracker falls behind, a new frame "
        "supersedes the oldest waiting one (counted as superseded on /diagnostics): with 1 the tracker "
        "always works on the newest frame, which waits at most for the one being tracked.",
        unit="frames", minimum=1),
    Setting(
        "late_frame_ms", 20.0, Mode.LIVE,
        "A frame that waited longer than this for the tracker (which was still on an earlier one) is "
        "tracked without the reverse checks of flow_back, which are a large share of a learned frame's "
        "cost, so the node catches up instead of superseding frames; counted as unchecked on /diagnostics "
        "(cost and quality: docs/benchmarks.md). 0 = always check.",
        unit="ms", minimum=0),
    Setting(
        "status_period", 5.0, Mode.LIVE,
        "Seconds between status lines in the log and on /diagnostics (frames received / processed / "
        "dropped, features, latency); 0 = none.",
        unit="s", minimum=0),
    # -- the tracking state (OK / DEGRADED / LOST) of each status period: what reaches the estimator --
    Setting(
        "degraded_features", 0.3, Mode.LIVE,
        "Tracking state DEGRADED (status line, /diagnostics, summary) when the features published per frame "
        "in a status period average below this share of max_cnt: VINS-Fusion weights every feature alike, "
        "and on less than about a third of its max_cnt its solve rests on few points, often in one part of "
        "the image. A state improves only once its thresholds are cleared by 20 %.",
        unit="x max_cnt", minimum=0, maximum=1),
    Setting(
        "lost_features", 0.15, Mode.LIVE,
        "Tracking state LOST when the features published per frame average below this share of max_cnt "
        "(22 of EuRoC's 150: about what VINS-Fusion's initialisation needs, its relative pose takes more "
        "than 20 correspondences). At most degraded_features.",
        unit="x max_cnt", minimum=0, maximum=1),
    Setting(
        "degraded_carried", 0.5, Mode.LIVE,
        "Tracking state DEGRADED when, over a status period, the median published frame carries on less "
        "than this share of the previous published frame's feature ids: the estimator constrains the pose "
        "with features seen in several frames; a camera tracked well carries 80-95 % (tracks of 5-20 "
        "frames), at a half tracks last about two frames.",
        unit="share", minimum=0, maximum=1),
    Setting(
        "lost_carried", 0.1, Mode.LIVE,
        "Tracking state LOST when the median published frame carries on less than this share of the "
        "previous frame's ids: tracks last barely one frame and the estimator has nothing to triangulate "
        "(e.g. every feature gated by max_sigma). At most degraded_carried.",
        unit="share", minimum=0, maximum=1),
    Setting(
        "summary_file", "", Mode.READ_ONLY,
        "Write the run's counters as JSON to this file when the node stops ('' = no file)."),
    # accelerators: where the encoder runs
    Setting(
        "providers", "cpu", Mode.REBUILD,
        "onnxruntime execution providers of the encoder, best first, comma-separated: cpu, cuda, tensorrt, "
        "openvino, coreml, rocm, migraphx, directml, dnnl, qnn, xnnpack or onnxruntime's full names (e.g. "
        "'tensorrt,cuda,cpu'). Providers this onnxruntime lacks are skipped with a warning; the one in "
        "use is logged and shown on /diagnostics. On a provider other than the CPU the whole image is "
        "encoded in one call.",
        tracker=True, session=True, example="cuda,cpu"),
    Setting(
        "tensorrt_fp16", False, Mode.REBUILD,
        "Let the TensorRT provider build half-precision engines.",
        tracker=True, session=True),
    Setting(
        "tensorrt_cache", "", Mode.REBUILD,
        "Folder where the TensorRT provider keeps the engines it builds, so a restart does not build them "
        "again ('' = no cache).",
        tracker=True, session=True, none_value=""),
    # -- inputs and the debug image on a robot: compressed topics, stereo stamp tolerance, image_track rate
    Setting(
        "image_transport", "raw", Mode.READ_ONLY,
        "How the images arrive: 'raw' (sensor_msgs/Image on the config's image topics) or 'compressed' "
        "(sensor_msgs/CompressedImage, JPEG or PNG, on '<image topic>/compressed' as image_transport names "
        "it; a remap of the image topic applies before '/compressed' is added).",
        example="compressed"),
    Setting(
        "stereo_sync_tolerance", STEREO_SYNC_TOLERANCE, Mode.LIVE,
        "Largest stamp difference of a stereo pair (as VINS-Fusion's 3 ms): each image pairs with the "
        "nearest image of the other camera within it, and the frame takes the left image's stamp; "
        "0 = equal stamps only. Images left without a partner are counted as unpaired. At half the frame "
        "period measured from the stamps or more, a change is refused (a start-up value is warned about).",
        unit="s", minimum=0),
    Setting(
        "track_image_rate", 10.0, Mode.LIVE,
        "Most image_track debug images per second (wall time), drawn only while something subscribes to "
        "it; 0 = every tracked frame.",
        unit="Hz", minimum=0),
    # -- threads of the node process, beside the estimator --
    Setting(
        "opencv_threads", 1, Mode.READ_ONLY,
        "OpenCV's threads in the node process (corner detection, image warps and filters); 0 = OpenCV's "
        "default pool of all the cores. 1 leaves the other cores to the estimator: the pool costs CPU "
        "time for little wall time.",
        unit="threads", minimum=0),
)
"""Every setting of the ``tracker`` node, in the order of the params file."""

_BY_NAME = {s.name: s for s in SETTINGS}

SESSION_SETTINGS: tuple[str, ...] = tuple(s.name for s in SETTINGS if s.session)
"""Settings :class:`~nsflow_ros.vins.session.FrontEndSession` takes, at construction and at run time."""

VINS_KEYS: tuple[str, ...] = tuple(s.vins_key for s in SETTINGS if s.vins_key is not None)
"""The VINS config keys a setting overrides (:func:`nsflow_ros.vins.config.apply_overrides`)."""

TRACKER_SETTINGS: tuple[str, ...] = tuple(s.name for s in SETTINGS if s.tracker)
"""Settings that are fields of :class:`~nsflow_ros.core.tracker.TrackerSettings`."""


def setting(name: str) -> Setting:
    """The :class:`Setting` of a name.

    Raises:
        ConfigError: for an unknown name, listing the known ones.
    """
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ConfigError(f"unknown setting {name!r}; known: {', '.join(_BY_NAME)}") from None


def session_tracker_fields(values: Mapping[str, Any], layout: str) -> dict[str, Any]:
    """The TrackerSettings fields of the settings without a VINS key, from setting values by name.

    An unset value (:func:`is_unset`) takes the default and :attr:`Setting.none_value` becomes None;
    ``reject_with_f`` unset is on for the ``mono`` layout (VINS-Mono runs it), off for ``fusion``;
    ``publish_covariance`` unset is on for ``fusion`` (channels 9 and up, which its estimator never reads)
    with an LM method, whose solver hands the covariance over at no cost, off for the OpenCV LK methods
    (it would cost them 3-8 % of their frame) and for ``mono`` (its five channels unchanged).
    """
    out: dict[str, Any] = {}
    for s in SETTINGS:
        if not s.tracker or s.vins_key is not None:
            continue
        value = values.get(s.name)
        if is_unset(value):
            value = s.default
        if s.name == "reject_with_f" and is_unset(value):
            out[s.name] = layout == "mono"
        elif s.name == "publish_covariance" and is_unset(value):
            from nsflow_ros.core.methods import METHODS  # not at import: --help needs no OpenCV

            spec = METHODS.get(str(out.get("method")))
            out[s.name] = layout == "fusion" and spec is not None and spec.is_lm
        elif s.none_value is not None and value == s.none_value:
            out[s.name] = None
        else:
            out[s.name] = bool(value) if s.switch or s.type is bool else value
    return out
