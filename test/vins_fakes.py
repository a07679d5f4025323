"""Fake ``rosmaster`` / ``vins_node`` / ``rosbag`` programs and a workspace that puts them first on PATH,
so that the estimator runner's orchestration is tested without a ROS 1 build."""

from __future__ import annotations

import sys
from pathlib import Path

from nsflow_ros.evaluation.estimator import VinsBuild

__all__ = ["FAKE_BAG", "FAKE_MASTER", "FAKE_NODE", "fake_build"]

FAKE_MASTER = """
import os, signal, sys
from xmlrpc.server import SimpleXMLRPCServer
port = int(sys.argv[sys.argv.index("-p") + 1])
subs = {}
server = SimpleXMLRPCServer(("127.0.0.1", port), logRequests=False)
def registerSubscriber(caller, topic, msgtype, api):
    subs.setdefault(topic, []).append(caller)
    return [1, "", []]
def getSystemState(caller):
    return [1, "", [[], [[t, n] for t, n in subs.items()], []]]
def getPid(caller):
    return [1, "", os.getpid()]
server.register_function(getPid)
server.register_function(registerSubscriber)
server.register_function(getSystemState)
signal.signal(signal.SIGINT, lambda *a: sys.exit(0))
server.serve_forever()
"""

# MODE: ok | die | crash_at_start | no_output | ignore_sigint | endless
FAKE_NODE = """
import json, os, signal, sys, time, xmlrpc.client
from pathlib import Path
MODE = {mode!r}
cfg = Path(sys.argv[1])
if MODE == "crash_at_start":
    print("config_file: cannot parse", cfg, file=sys.stderr)
    sys.exit(1)
values = {{}}
for line in cfg.read_text().splitlines():
    if ":" in line and not line.startswith((" ", "#", "%")):
        key, _, rest = line.partition(":")
        values[key.strip()] = rest.split("#")[0].strip().strip('"')
out = Path(values["output_path"])
(out / "node.json").write_text(json.dumps({{"argv": sys.argv, "pid": os.getpid(), "values": values,
    "master": os.environ["ROS_MASTER_URI"], "path_has_fakes": os.environ["PATH"].split(":")[0]}}))
master = xmlrpc.client.ServerProxy(os.environ["ROS_MASTER_URI"])
master.registerSubscriber("/vins_estimator", "/imu0", "sensor_msgs/Imu", "http://x")
master.registerSubscriber("/vins_estimator", "/feature_tracker/feature", "sensor_msgs/PointCloud", "http://x")
if MODE == "ignore_sigint":
    signal.signal(signal.SIGINT, signal.SIG_IGN)
elif MODE == "die":
    time.sleep(0.05)
    print("segmentation fault in the estimator", file=sys.stderr)
    sys.exit(3)
t = 1.0
while True:
    if MODE == "endless" or (MODE != "no_output" and not (out / "play_done").exists()):
        with open(out / "vio.csv", "a") as f:
            f.write(f"{{int(t * 1e9)}},{{t}},0,0,1,0,0,0,0,0,0,\\n")
        t += 0.05
    time.sleep(0.02)
"""

# MODE: ok | fail | slow
FAKE_BAG = """
import json, sys, time
from pathlib import Path
MODE = {mode!r}
Path("rosbag.json").write_text(json.dumps(sys.argv[1:]))
time.sleep(10 if MODE == "slow" else 0.1)
Path("play_done").touch()
if MODE == "fail":
    print("ROSBAG ERROR: bag unindexed", file=sys.stderr)
    sys.exit(1)
"""


def _script(path: Path, body: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"#!{sys.executable} -IS\n{body}")  # no site: starts in a tenth of the time
    path.chmod(0o755)


def fake_build(root: Path, node: str = "ok", bag: str = "ok") -> VinsBuild:
    """A workspace whose setup.bash puts fake rosmaster / rosbag first on PATH, and a fake vins_node."""
    ws = root / "ws"
    bin_dir = ws / "fake_bin"
    _script(bin_dir / "rosmaster", FAKE_MASTER)
    _script(bin_dir / "rosbag", FAKE_BAG.format(mode=bag))
    _script(ws / "devel" / "lib" / "vins" / "vins_node", FAKE_NODE.format(mode=node))
    (ws / "devel" / "setup.bash").write_text(f'export PATH="{bin_dir}:$PATH"\n')
    return VinsBuild.locate(ws)
