"""What a run leaves in its folder besides the model: ``train.csv`` (one row per step), TensorBoard
events under ``tensorboard/`` when the optional ``tensorboard`` package is installed, and ``run.json``
(:func:`run_record`); and the progress shown meanwhile.
"""

from __future__ import annotations

import csv
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any

__all__ = ["CSV_FIELDS", "Progress", "StepLog", "git_state", "run_record", "tensorboard_writer"]

CSV_FIELDS = ("step", "seconds", "loss", "pairs", "points")
TENSORBOARD_HINT = "TensorBoard event files are not written: pip install tensorboard"


def tensorboard_writer(folder: Path) -> Any | None:
    """A ``SummaryWriter`` logging into ``folder``, or None when TensorBoard is not installed."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(log_dir=str(folder))


class StepLog:
    """The per-step CSV log and, when available, TensorBoard scalars.

    Args:
        folder: the run folder.
        resume: continue an existing ``train.csv`` at step ``first``, dropping the rows a killed run
            wrote after its last checkpoint.
        first: the step the run starts at.
        tensorboard: try TensorBoard (:attr:`tensorboard` is None when it is not installed).
    """

    def __init__(self, folder: Path, resume: bool = False, first: int = 0, tensorboard: bool = True) -> None:
        path = Path(folder) / "train.csv"
        rows: list[list[str]] = []
        if resume and path.is_file():
            with path.open(newline="") as f:
                rows = [r for r in list(csv.reader(f))[1:] if r and r[0].isdigit() and int(r[0]) <= first]
        self._file = path.open("w", newline="")
        self._csv = csv.writer(self._file)
        self._csv.writerow(CSV_FIELDS)
        self._csv.writerows(rows)
        self.tensorboard = tensorboard_writer(Path(folder) / "tensorboard") if tensorboard else None

    def step(self, step: int, seconds: float, loss: float, pairs: int, points: int) -> None:
        self._csv.writerow([step, f"{seconds:.3f}", f"{loss:.6g}", pairs, points])
        if self.tensorboard is not None:
            self.tensorboard.add_scalar("train/loss", loss, step)

    def scalars(self, step: int, values: dict[str, float]) -> None:
        """Validation figures (TensorBoard only; the JSON log holds them too)."""
        if self.tensorboard is not None:
            for key, value in values.items():
                self.tensorboard.add_scalar(f"val/{key}", value, step)

    def flush(self) -> None:
        self._file.flush()
        if self.tensorboard is not None:
            self.tensorboard.flush()

    def close(self) -> None:
        self._file.close()
        if self.tensorboard is not None:
            self.tensorboard.close()


class Progress:
    """The run's progress with the time to the end (:func:`nsflow_ros.progress.progress_bar`), when
    ``enabled``, from step ``first`` to ``steps`` (None = only the time limit) or the ``time.monotonic()``
    ``deadline``."""

    def __init__(self, enabled: bool, first: int, steps: int | None, deadline: float) -> None:
        self.bar = None
        self.deadline = deadline
        if enabled:
            from nsflow_ros.progress import progress_bar

            self.bar = progress_bar(total=steps, initial=first, unit="step", dynamic_ncols=True)

    def update(self, loss: float) -> None:
        if self.bar is None:
            return
        self.bar.update(1)
        if self.bar.n % 20 == 0:
            left = max(0.0, self.deadline - time.monotonic())
            self.bar.set_description(f"loss {loss:.4f}, time limit in {left / 60:.1f} min")

    def note(self, **values: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix(**values)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def git_state(path: Path | None = None) -> dict[str, object]:
    """Commit and dirty flag of the git checkout holding ``path`` (the package), or why there is none."""
    where = str(path or Path(__file__).resolve().parent)
    try:
        commit = subprocess.run(
            ["git", "-C", where, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        status = subprocess.run(
            ["git", "-C", where, "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=10, check=True,
        ).stdout
    except (OSError, subprocess.SubprocessError) as err:
        return {"commit": None, "note": f"not a git checkout ({type(err).__name__})"}
    return {"commit": commit, "dirty": bool(status.strip())}


def _version(module: str) -> str | None:
    try:
        return str(__import__(module).__version__)
    except (ImportError, AttributeError):
        return None


def run_record(
    *, command: str, data: dict[str, object], device: str, world_size: int, config: dict[str, str]
) -> dict[str, object]:
    """What ``run.json`` records about how a run was made: command, data, git state, environment and
    settings (the caller adds its results)."""
    import torch

    env: dict[str, object] = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "numpy": _version("numpy"),
        "opencv": _version("cv2"),
        "onnxruntime": _version("onnxruntime"),
        "tensorboard": _version("tensorboard"),
        "device": device,
        "gpu": torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else None,
        "cpu_count": os.cpu_count(),
        "world_size": world_size,
    }
    return {"command": command, "data": data, "git": git_state(), "environment": env, "config": config}
