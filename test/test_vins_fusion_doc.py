"""docs/vins_fusion.md: every nsflow-* command line parses with the tool's own parser, and the names it
gives (parameters, config keys, topic) are the ones the code uses."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from nsflow_ros.ate.cli import build_parser as ate_parser
from nsflow_ros.resources import share_file
from nsflow_ros.ros.replay_node import _parser as replay_parser
from nsflow_ros.ros.tracker_params import PARAMETERS
from nsflow_ros.vins.feature_bag import FEATURE_TOPIC

DOC = Path(__file__).resolve().parent.parent / "docs" / "vins_fusion.md"


def _commands(tool: str) -> list[list[str]]:
    text = DOC.read_text(encoding="utf-8")
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    lines = [line.strip() for block in blocks for line in block.replace("\\\n", " ").splitlines()]
    # shell loop variables take their first value: `for level in none small large` -> $level = none
    loops = dict(re.findall(r"for (\w+) in (\S+)", "\n".join(lines)))
    out = []
    for line in lines:
        if line.startswith(f"{tool} "):
            for var, value in loops.items():
                line = line.replace(f"${var}", value)
            out.append(shlex.split(line)[1:])
    return out


def test_the_doc_shows_each_tool():
    assert len(_commands("nsflow-replay")) >= 3
    assert len(_commands("nsflow-ate")) >= 2
    assert len(_commands("nsflow-tracker")) >= 1


@pytest.mark.parametrize("argv", _commands("nsflow-replay"), ids=lambda a: " ".join(a)[:60])
def test_replay_lines_parse(argv):
    opts = replay_parser().parse_args(argv)
    assert opts.path.name


@pytest.mark.parametrize("argv", _commands("nsflow-ate"), ids=lambda a: " ".join(a)[:60])
def test_ate_lines_parse(argv):
    if argv[0] not in ("ape", "drift", "batch"):
        argv = ["ape", *argv]
    assert ate_parser().parse_args(argv).command in ("ape", "batch")


@pytest.mark.parametrize("argv", _commands("nsflow-tracker"), ids=lambda a: " ".join(a)[:60])
def test_tracker_lines_set_known_parameters(argv):
    assert argv[0] == "--ros-args"
    names = {p.name for p in PARAMETERS}
    given = [argv[k + 1].split(":=")[0] for k, a in enumerate(argv) if a == "-p"]
    assert given and set(given) <= names, set(given) - names


def test_names_in_the_doc_are_the_code_s():
    text = DOC.read_text(encoding="utf-8")
    assert FEATURE_TOPIC in text
    config = share_file("config/euroc/euroc_stereo_imu_config.yaml").read_text()
    table = text.split("**Config keys that matter**", 1)[1].split("\n\n**", 1)[0]
    first_cells = re.findall(r"^\| (`[^|]*) \|", table, flags=re.M)
    named = {k for cell in first_cells for k in re.findall(r"`(\w+)`", cell)}
    assert {"num_of_cam", "cam0_calib", "image0_topic", "imu_topic", "max_cnt", "output_path"} <= named
    missing = [k for k in named if not re.search(rf"^{k}:", config, flags=re.M)]
    assert missing == [], f"config keys in the doc that the shipped config lacks: {missing}"
