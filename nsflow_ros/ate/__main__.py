"""``python -m nsflow_ros.ate``: the same CLI as ``ros2 run nsflow_ros ate``."""

from __future__ import annotations

import sys

from nsflow_ros.ate.cli import main

__all__: list[str] = []

sys.exit(main())
