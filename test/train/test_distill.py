"""Distillation (nsflow_ros.train.distill): the loss, the teacher guard, steps that learn, the CLI."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nsflow_ros import load_encoder  # noqa: E402
from nsflow_ros.train.cli import main  # noqa: E402
from nsflow_ros.train.data import PairConfig, load_image, make_pair  # noqa: E402
from nsflow_ros.train.distill import Teacher, distill_loss  # noqa: E402
from nsflow_ros.train.errors import TrainError  # noqa: E402
from nsflow_ros.train.export import export_onnx  # noqa: E402
from nsflow_ros.train.model import Encoder, EncoderSpec  # noqa: E402
from nsflow_ros.train.trainer import TrainConfig, train_step  # noqa: E402


@pytest.fixture(scope="module")
def teacher_path(tmp_path_factory):
    torch.manual_seed(1)
    return export_onnx(Encoder(EncoderSpec(d=2, width=4)), tmp_path_factory.mktemp("t") / "teacher.onnx")


def test_loss_is_zero_for_equal_maps_and_counts_values_and_differences():
    a = torch.rand(2, 3, 8, 9)
    assert float(distill_loss(a, a.clone())) == 0.0
    # a constant offset changes values only: the difference terms stay 0
    assert float(distill_loss(a + 0.5, a)) == pytest.approx(0.25, rel=1e-6)
    # a checkerboard of +-e: value term e^2, each difference term (2e)^2 over its own count
    e = 0.1
    board = torch.from_numpy(np.indices((8, 9)).sum(0) % 2 * 2.0 - 1.0).float() * e
    assert float(distill_loss(a + board, a)) == pytest.approx(e**2 + 2 * (2 * e) ** 2, rel=1e-5)


def test_loss_shape_guard():
    with pytest.raises(TrainError, match=r"\(2, 3, 8, 9\) and \(2, 3, 8, 8\)"):
        distill_loss(torch.zeros(2, 3, 8, 9), torch.zeros(2, 3, 8, 8))


def test_teacher_guards(tmp_path, teacher_path):
    with pytest.raises(TrainError, match=r"missing\.onnx"):
        Teacher(tmp_path / "missing.onnx", 2, 1)
    with pytest.raises(TrainError, match="maps 1 -> 2 channels, the student 1 -> 4"):
        Teacher(teacher_path, 4, 1)


def test_steps_bring_the_student_to_the_teacher(teacher_path):
    torch.manual_seed(0)
    torch.set_num_threads(2)
    teacher = Teacher(teacher_path, 2, 1)
    pair = make_pair(load_image("astronaut"), np.random.default_rng(0), PairConfig(width=96, height=72))
    student = Encoder(EncoderSpec(d=2, width=2))
    opt = torch.optim.Adam(student.parameters(), lr=3e-3)
    cfg = TrainConfig(spec=student.spec)
    losses = [train_step(student, opt, pair, cfg, teacher) for _ in range(60)]
    assert np.mean(losses[-10:]) < 0.5 * np.mean(losses[:3])


def test_cli_distils_and_writes_the_card(tmp_path, teacher_path):
    out, models = tmp_path / "run", tmp_path / "models"
    args = "--steps 3 --d 2 --width 2 --lr 0.003 --val-every 3 --eval-per-image 1 --val-per-image 1"
    args += " --no-progress --threads 1 --install"
    args += f" --teacher {teacher_path} --out {out} --models-dir {models}"
    assert main(args.split()) == 0
    assert load_encoder(out / "nsflow_encoder.onnx").channels == 2
    card = (models / "README.md").read_text()
    assert f"Distilled from `{teacher_path.as_posix()}`" in card and "lr 0.003" in card
    assert "3x3 conv 1->2, ReLU; 3x3 conv 2->2, ReLU; 1x1 conv 2->4, ReLU; 1x1 conv 4->2" in card


def test_cli_rejects_a_teacher_of_other_channels(tmp_path, teacher_path, capsys):
    args = ["--steps", "1", "--d", "4", "--teacher", str(teacher_path), "--out", str(tmp_path / "x")]
    assert main(args) == 1
    assert "the student 1 -> 4" in capsys.readouterr().err


def test_init_starts_from_a_checkpoint_and_refuses_another_shape(tmp_path, teacher_path, capsys):
    first = tmp_path / "first"
    args = "--steps 2 --d 2 --width 2 --val-every 2 --eval-per-image 1 --val-per-image 1"
    args += " --no-progress --threads 1"
    assert main([*args.split(), "--teacher", str(teacher_path), "--out", str(first)]) == 0
    ckpt = torch.load(first / "encoder.pt", weights_only=True)
    # zero steps from the checkpoint: the exported model is the checkpoint's encoder
    again = tmp_path / "again"
    assert main([*args.replace("--steps 2", "--steps 0").split(), "--init", str(first / "encoder.pt"),
                 "--out", str(again)]) == 0
    restored = Encoder(EncoderSpec(d=2, width=2))
    restored.load_state_dict(ckpt["state"])
    img = np.random.default_rng(0).integers(0, 256, (40, 50), dtype=np.uint8)
    with torch.no_grad():
        x = torch.from_numpy(img.astype(np.float32) / 255.0)[None, None]
        ref = restored(x)[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(load_encoder(again / "nsflow_encoder.onnx")(img), ref, atol=1e-5)
    assert main(["--steps", "1", "--d", "2", "--width", "3", "--init", str(first / "encoder.pt"),
                 "--out", str(tmp_path / "x")]) == 1
    assert "holds an encoder of spec" in capsys.readouterr().err
    assert main(["--steps", "1", "--init", str(tmp_path / "none.pt"), "--out", str(tmp_path / "y")]) == 1
    assert "none.pt" in capsys.readouterr().err
