"""Declarations on an exported model: metadata set in place, read back by the encoder."""

from __future__ import annotations

import pytest
from onnx_models import conv_encoder

from nsflow_ros.core.encoder import load_encoder
from nsflow_ros.train.declare import main, set_metadata
from nsflow_ros.train.errors import TrainError


def test_set_metadata_adds_and_replaces_keys_and_keeps_the_rest(tmp_path):
    path = conv_encoder(tmp_path / "m.onnx", c_in=1, d=3)
    set_metadata(path, {"gain_levels": "2", "note": "a"})
    set_metadata(path, {"note": "b"})
    enc = load_encoder(path)
    assert enc.gain_levels == 2 and enc.metadata["note"] == "b" and enc.channels == 3
    with pytest.raises(TrainError, match="must be a string"):
        set_metadata(path, {"gain_levels": 1})  # type: ignore[dict-item]
    with pytest.raises(TrainError, match=r"cannot read the ONNX model .*none\.onnx"):
        set_metadata(tmp_path / "none.onnx", {"a": "b"})


def test_command_line(tmp_path, capsys):
    path = conv_encoder(tmp_path / "m.onnx", c_in=1, d=3)
    assert main([str(path), "gain_levels=1"]) == 0
    assert load_encoder(path).gain_levels == 1
    assert main([str(tmp_path / "none.onnx"), "a=b"]) == 1
    assert "none.onnx" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main([str(path), "no-equals-sign"])
