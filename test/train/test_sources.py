"""Tests of the training data sources (nsflow_ros.train.sources)."""

from __future__ import annotations

import ast
from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from train_sources_data import write_footage_bag, write_tartanair  # noqa: E402

from nsflow_ros.train.data import PairConfig  # noqa: E402
from nsflow_ros.train.errors import TrainError  # noqa: E402
from nsflow_ros.train.sources import (  # noqa: E402
    DATA_KINDS,
    SOURCES,
    DataSpec,
    FootageSource,
    MixedSource,
    PairSource,
    PairStream,
    PhotoSource,
    SourceOptions,
    TartanAirSource,
    parse_data_spec,
    read_footage,
    tartanair_environments,
)

SMALL = PairConfig(width=128, height=96, max_points=80, min_distance=5.0)


def test_tartanair_points_are_valid_and_their_flow_exact(tartanair):
    root, truth = tartanair
    src = TartanAirSource(root)
    assert src.environments == ["abandonedfactory", "hospital"] and len(src.pairs) == 4
    seen = 0
    for i in range(12):
        rng = np.random.default_rng(i)
        pair = src.sample(rng, SMALL, strength=0.0)
        assert pair.image1.shape == (96, 128) and pair.image1.dtype == np.uint8
        assert len(pair.points) > 5
        # which crop / pair: find the stored flow whose values match at the points
        matches = []
        for (env, k), (flow, mask) in truth.items():
            for y0 in range(0, 120 - 96 + 1):
                for x0 in range(0, 160 - 128 + 1):
                    ij = pair.points.astype(int) + np.array([x0, y0])
                    if np.array_equal(flow[ij[:, 1], ij[:, 0]].astype(np.float64), pair.flow_gt):
                        matches.append((env, k, x0, y0, mask[ij[:, 1], ij[:, 0]]))
                        break
        assert matches, "flow at the points is not the file's"
        env, k, x0, y0, m = matches[0]
        assert (m == 0).all()  # never an occluded / out-of-frame pixel
        target = pair.points + pair.flow_gt
        assert (target >= 5).all() and (target[:, 0] <= 127 - 5).all() and (target[:, 1] <= 95 - 5).all()
        seen += 1
    assert seen == 12


def test_tartanair_colour_and_environment_split(tartanair):
    root, _ = tartanair
    assert tartanair_environments(root) == ["abandonedfactory", "hospital"]
    train = TartanAirSource(root, ["abandonedfactory"], color=True)
    val = TartanAirSource(root, ["hospital"])
    assert {p.environment for p in train.pairs} == {"abandonedfactory"}
    assert {p.environment for p in val.pairs} == {"hospital"}
    pair = train.sample(np.random.default_rng(0), SMALL, 0.5)
    assert pair.image1.shape == (96, 128, 3)
    with pytest.raises(TrainError, match=r"environments \['desert'\] not in"):
        TartanAirSource(root, ["desert"])


def test_tartanair_errors_name_the_file(tmp_path):
    write_tartanair(tmp_path / "a", envs=("env",))
    missing = tmp_path / "a/env/Easy/P000/flow/000001_000002_mask.npy"
    missing.unlink()
    with pytest.raises(TrainError, match=r"missing TartanAir file .*000001_000002_mask\.npy"):
        TartanAirSource(tmp_path / "a")
    write_tartanair(tmp_path / "b", envs=("env",), frames=2)
    bad = tmp_path / "b/env/Easy/P000/flow/000000_000001_mask.npy"
    np.save(bad, np.zeros((10, 10), np.uint8))
    with pytest.raises(TrainError, match=r"000001_mask\.npy has shape \(10, 10\), expected \(120, 160\)"):
        TartanAirSource(tmp_path / "b").sample(np.random.default_rng(0), SMALL, 0.0)
    (tmp_path / "c").mkdir()
    with pytest.raises(TrainError, match="holds no TartanAir environment"):
        TartanAirSource(tmp_path / "c")
    with pytest.raises(TrainError, match="TartanAir folder not found"):
        TartanAirSource(tmp_path / "nothing")


def test_footage_from_a_bag_and_an_image_folder(tmp_path):
    bag = write_footage_bag(tmp_path / "bag", frames=6)
    frames = read_footage(bag)
    assert len(frames) == 6 and frames[0].shape == (150, 200)
    src = FootageSource(bag, holdout=0.34)
    assert len(src.frames) == 4 and len(src.held) == 2
    held = src.heldout()
    assert held is not None and np.array_equal(held.frames[0], frames[4])
    pair = src.sample(np.random.default_rng(0), SMALL, 1.0)
    assert len(pair.points) > 5
    # exact flow: the homography maps the points to their targets
    target = cv2.perspectiveTransform(pair.points[None], pair.homography)[0]
    np.testing.assert_allclose(pair.points + pair.flow_gt, target)
    folder = tmp_path / "pngs"
    folder.mkdir()
    for k, f in enumerate(frames):
        cv2.imwrite(str(folder / f"{k:03d}.png"), f)
    assert all(np.array_equal(a, b) for a, b in zip(read_footage(folder), frames, strict=True))
    assert len(read_footage(folder, max_frames=3)) == 3


def test_footage_errors(tmp_path):
    bag = write_footage_bag(tmp_path / "bag", frames=3)
    with pytest.raises(TrainError, match=r"footage .*bag: .*/cam2/image_raw"):
        read_footage(bag, topics=["/cam2/image_raw"])
    with pytest.raises(TrainError, match=r"footage .*nowhere"):
        read_footage(tmp_path / "nowhere")
    with pytest.raises(TrainError, match="holdout must be in"):
        FootageSource(bag, holdout=1.0)


def test_mixing_follows_the_weights(tartanair):
    root, _ = tartanair
    photos, tartan = PhotoSource(("camera",)), TartanAirSource(root)
    mix = MixedSource([(tartan, 0.7), (photos, 0.3)])
    assert mix.describe()["sources"][0]["share"] == pytest.approx(0.7)
    from_tartan = [
        bool(np.isnan(mix.sample(np.random.default_rng(i), SMALL, 0.0).homography).all()) for i in range(60)
    ]
    assert 0.5 < np.mean(from_tartan) < 0.9
    with pytest.raises(TrainError, match="weights must be finite and > 0"):
        MixedSource([(photos, 0.0)])
    with pytest.raises(TrainError, match="no training data source"):
        MixedSource([])


def test_a_single_source_mix_draws_nothing_extra():
    photos = PhotoSource(("camera", "astronaut"))
    a = MixedSource([(photos, 1.0)]).sample(np.random.default_rng(3), SMALL, 0.5)
    b = photos.sample(np.random.default_rng(3), SMALL, 0.5)
    assert np.array_equal(a.image1, b.image1) and np.array_equal(a.points, b.points)


def test_pair_stream_is_indexed():
    stream = PairStream(PhotoSource(("camera",)), SMALL, seed=5)
    a, b, c = stream[3], stream[3], stream[4]
    assert np.array_equal(a.image2, b.image2) and not np.array_equal(a.image2, c.image2)
    assert len(a.points) >= 4
    empty = PairStream(PhotoSource(("camera",)), SMALL, attempts=3, min_points=1000)
    with pytest.raises(TrainError, match=r"3 pairs in a row .* had fewer than 1000 keypoints"):
        empty[0]


def test_data_spec_parsing(tmp_path):
    assert parse_data_spec("photos") == DataSpec("photos", None, 1.0)
    assert parse_data_spec("photos:0.3") == DataSpec("photos", None, 0.3)
    assert parse_data_spec("tartanair:/d/TA:0.7") == DataSpec("tartanair", tmp_path.__class__("/d/TA"), 0.7)
    assert parse_data_spec("footage:C:/x.bag") == DataSpec("footage", tmp_path.__class__("C:/x.bag"), 1.0)
    assert parse_data_spec("scenes:0.5").path is None
    for bad, msg in (
        ("kitti:/x", "kind must be one of"),
        ("tartanair", "tartanair needs a path"),
        ("footage:/x:-1", "weight must be finite and > 0"),
        ("photos:/x:1", "photos takes no path"),
    ):
        with pytest.raises(TrainError, match=msg):
            parse_data_spec(bad)


def test_every_kind_builds_and_splits_through_one_call(tmp_path, tartanair, monkeypatch):
    from nsflow_ros.train import scenes

    small_pool = scenes.ScenePool
    monkeypatch.setattr(
        scenes, "ScenePool", lambda root, seeds, seed: small_pool(root, (1,), 2, 1.0, points=300, seed=seed)
    )
    paths = {"tartanair": tartanair[0], "footage": write_footage_bag(tmp_path / "bag", frames=5)}
    assert DATA_KINDS == tuple(SOURCES) == ("photos", "scenes", "tartanair", "footage")
    opts = SourceOptions(cache=tmp_path / "cache", holdout=0.2)
    held_kinds = []
    for kind, cls in SOURCES.items():
        assert cls.kind == kind and cls.split is not PairSource.split and cls.words is not PairSource.words
        spec = parse_data_spec(f"{kind}:{paths[kind]}" if kind in paths else kind)
        train, held = spec.split(opts)
        assert type(train) is cls and train.describe()["kind"] == kind
        assert len(PairStream(train, SMALL)[0].points) >= 4
        assert isinstance(cls.words({**train.describe(), "share": 1.0}), str)
        if held is not None:
            assert type(held) is cls
            held_kinds.append((kind, len(held.evaluation_frames())))
    # TartanAir holds its last environment out (validated during training only); footage its last frame
    assert held_kinds == [("tartanair", 0), ("footage", 1)]


def _names(node: ast.AST) -> set[str]:
    """Every name and attribute name inside ``node``."""
    found = set()
    for n in ast.walk(node):
        if isinstance(n, ast.Name | ast.Attribute):
            found.add(n.id if isinstance(n, ast.Name) else n.attr)
    return found


def test_no_module_outside_the_registry_branches_on_a_source_type_or_kind():
    import nsflow_ros

    classes = {c.__name__ for c in (*SOURCES.values(), MixedSource, PairSource)}
    root = Path(nsflow_ros.__file__).parent
    found = []
    for path in sorted(root.rglob("*.py")):
        if path == root / "train" / "sources.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            where = f"{path.relative_to(root)}:{getattr(node, 'lineno', 0)}"
            if isinstance(node, ast.Call) and _names(node.func) & {"isinstance", "issubclass", "type"}:
                checked = set().union(*(_names(a) for a in node.args))
            else:
                checked = set()
            if classes & checked:
                found.append(where)
            if isinstance(node, ast.Compare):
                sides = [node.left, *node.comparators]
                consts = {s.value for side in sides for s in ast.walk(side) if isinstance(s, ast.Constant)}
                if consts & set(DATA_KINDS) or classes & set().union(*(_names(s) for s in sides)):
                    found.append(where)
    assert not found, f"branches on a data source's type or kind outside train/sources.py: {found}"
