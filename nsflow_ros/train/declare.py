"""Declarations on an exported model: metadata the tracker reads (``smoothing``, ``gain_levels``), set in
place on a model file, e.g. one trained before the option existed."""

from __future__ import annotations

import os
from pathlib import Path

from nsflow_ros.optional import require
from nsflow_ros.train.errors import TrainError

__all__ = ["main", "set_metadata"]



def set_metadata(path: str | os.PathLike[str], values: dict[str, str]) -> Path:
    """Set metadata_props of an exported model in place (other keys and the graph unchanged), e.g. a
    declaration the tracker reads (``gain_levels``) added to a model trained before the option existed.

    Raises:
        TrainError: a missing or unreadable file, or a value that is not a string.
    """
    onnx = require("onnx", "editing ONNX metadata")
    target = Path(path)
    try:
        proto = onnx.load(str(target))
    except (OSError, ValueError) as err:
        raise TrainError(f"cannot read the ONNX model {target}: {err}") from err
    props = {p.key: p.value for p in proto.metadata_props}
    for key, value in values.items():
        if not isinstance(value, str):
            raise TrainError(f"metadata value for {key!r} must be a string, got {type(value).__name__}")
        props[key] = value
    del proto.metadata_props[:]
    for key, value in props.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(proto)
    onnx.save(proto, str(target))
    return target


def main(args: list[str] | None = None) -> int:
    """``python -m nsflow_ros.train.declare MODEL KEY=VALUE ...``: :func:`set_metadata` from the shell."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m nsflow_ros.train.declare", description=main.__doc__)
    parser.add_argument("model", help="the .onnx file to edit in place")
    parser.add_argument("values", nargs="+", metavar="KEY=VALUE", help="metadata entries to set")
    opts = parser.parse_args(args)
    bad = [v for v in opts.values if "=" not in v]
    if bad:
        parser.error(f"expected KEY=VALUE, got {bad[0]!r}")
    try:
        set_metadata(opts.model, dict(v.split("=", 1) for v in opts.values))
    except TrainError as err:
        print(f"nsflow_ros.train.declare: {err}")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
