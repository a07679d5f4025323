"""``python -m nsflow_ros.train``: ``nsflow-train``, in the form ``torchrun ... -m nsflow_ros.train`` uses."""

from __future__ import annotations

import sys

from nsflow_ros.train.cli import main

if __name__ == "__main__":
    sys.exit(main())
