"""Tests of the training loop (nsflow_ros.train.trainer): resume, workers, logs and the run record."""

from __future__ import annotations

import csv
import json
import sys
import types

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from train_sources_data import write_footage_bag  # noqa: E402

from nsflow_ros.train.data import PairConfig  # noqa: E402
from nsflow_ros.train.errors import TrainError  # noqa: E402
from nsflow_ros.train.model import EncoderSpec  # noqa: E402
from nsflow_ros.train.sources import DataSpec, MixedSource, PhotoSource  # noqa: E402
from nsflow_ros.train.trainer import TrainConfig, TrainData, make_data, train  # noqa: E402

DATA = TrainData(MixedSource([(PhotoSource(("astronaut", "camera")), 1.0)]))


def _cfg(out, **kw) -> TrainConfig:
    base = dict(
        spec=EncoderSpec(d=2, width=4),
        out=out,
        seed=1,
        val_every=0,
        threads=1,
        pair=PairConfig(96, 72, max_points=30, min_distance=5.0),
        tensorboard=False,
    )
    return TrainConfig(**{**base, **kw})


def _params(model) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in model.parameters()])


class _KilledError(Exception):
    pass


def test_a_killed_run_resumes_exactly(tmp_path):
    full = train(_cfg(tmp_path / "full", steps=5), progress=False, data=DATA)

    def kill(step, loss, model):
        if step == 4:  # after the checkpoint of step 3, before any other
            raise _KilledError

    with pytest.raises(_KilledError):
        train(_cfg(tmp_path / "part", steps=5, checkpoint_every=3), progress=False, data=DATA, on_step=kill)
    resumed = train(_cfg(tmp_path / "part", steps=5, resume=True), progress=False, data=DATA)
    assert resumed.losses == full.losses and resumed.steps == 5
    assert torch.equal(_params(resumed.model), _params(full.model))
    with (tmp_path / "part" / "train.csv").open() as f:
        steps = [int(r["step"]) for r in csv.DictReader(f)]
    assert steps == [1, 2, 3, 4, 5]  # the killed run's step 4 row is replaced, not repeated
    record = json.loads((tmp_path / "part" / "run.json").read_text())
    assert record["steps"] == 5 and "resumed_from" in record
    # another global batch would change the pair order: refused
    with pytest.raises(TrainError, match="global batch"):
        train(_cfg(tmp_path / "part", steps=6, resume=True, batch=2), progress=False, data=DATA)


def test_resume_needs_a_run_checkpoint(tmp_path):
    with pytest.raises(TrainError, match="cannot read checkpoint"):
        train(_cfg(tmp_path / "none", steps=1, resume=True), progress=False, data=DATA)


def test_dataloader_workers_give_the_same_run(tmp_path):
    a = train(_cfg(tmp_path / "a", steps=3, batch=2), progress=False, data=DATA)
    b = train(_cfg(tmp_path / "b", steps=3, batch=2, workers=1), progress=False, data=DATA)
    assert a.losses == b.losses


def test_the_run_folder_records_how_the_run_was_made(tmp_path, monkeypatch):
    calls = []

    class FakeWriter:
        def __init__(self, log_dir):
            calls.append(("dir", log_dir))

        def add_scalar(self, tag, value, step):
            calls.append((tag, step))

        def flush(self):
            pass

        def close(self):
            pass

    fake = types.ModuleType("torch.utils.tensorboard")
    fake.SummaryWriter = FakeWriter
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", fake)
    out = tmp_path / "run"
    cfg = _cfg(out, steps=2, val_every=2, val_per_image=1, tensorboard=True, command="nsflow-train --steps 2")
    train(cfg, progress=False, data=DATA)
    record = json.loads((out / "run.json").read_text())
    assert record["command"] == "nsflow-train --steps 2"
    assert record["data"]["train"]["sources"][0]["images"] == ["astronaut", "camera"]
    assert record["environment"]["torch"] == torch.__version__ and record["environment"]["world_size"] == 1
    assert "commit" in record["git"] and record["steps"] == 2 and record["steps_per_second"] > 0
    assert ("train/loss", 1) in calls and ("train/loss", 2) in calls and ("val/perturbed_within1", 2) in calls
    with (out / "train.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["step"]) for r in rows] == [1, 2] and all(float(r["loss"]) > 0 for r in rows)
    # without TensorBoard the run says how to get it and still writes the CSV
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)
    train(_cfg(tmp_path / "plain", steps=1, tensorboard=True), progress=False, data=DATA)
    plain = json.loads((tmp_path / "plain" / "run.json").read_text())
    assert "pip install tensorboard" in plain["tensorboard"]


def test_make_data_holds_out_tartanair_environments_and_footage_frames(tmp_path, tartanair):
    root, _ = tartanair
    bag = write_footage_bag(tmp_path / "bag", frames=5)
    specs = (DataSpec("tartanair", root, 0.7), DataSpec("footage", bag, 0.3))
    data = make_data(_cfg(tmp_path / "x", data=specs, footage_holdout=0.2))
    train_part = data.source.describe()["sources"]
    assert train_part[0]["environments"] == ["abandonedfactory"]
    assert train_part[0]["share"] == pytest.approx(0.7)
    assert train_part[1]["frames"] == 4 and train_part[1]["heldout_frames"] == 1
    assert data.validation["tartanair"].describe()["environments"] == ["hospital"]
    assert len(data.validation["footage"].frames) == 1
    chosen = make_data(_cfg(tmp_path / "x", data=specs[:1], tartanair_val=("abandonedfactory",)))
    assert chosen.source.describe()["sources"][0]["environments"] == ["hospital"]
    with pytest.raises(TrainError, match=r"every environment of .* is held out"):
        make_data(_cfg(tmp_path / "x", data=specs[:1], tartanair_val=("abandonedfactory", "hospital")))
    with pytest.raises(TrainError, match=r"validation environments \['moon'\] not in"):
        make_data(_cfg(tmp_path / "x", data=specs[:1], tartanair_val=("moon",)))


def test_training_on_tartanair_and_footage_with_validation(tmp_path, tartanair):
    root, _ = tartanair
    bag = write_footage_bag(tmp_path / "bag", frames=5)
    specs = (DataSpec("tartanair", root, 0.5), DataSpec("footage", bag, 0.5))
    out = tmp_path / "run"
    res = train(_cfg(out, data=specs, steps=2, batch=2, val_every=2, val_per_image=1), progress=False)
    assert res.steps == 2 and all(np.isfinite(res.losses))
    record = json.loads((out / "log.jsonl").read_text().splitlines()[-1])
    assert {"tartanair_within1", "footage_within1", "perturbed_within1"} <= set(record)
