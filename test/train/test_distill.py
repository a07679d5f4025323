"""Distillation (nsflow_ros.train.distill): the loss, the teacher guard, steps that learn, the CLI."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nsflow_ros import load_encoder  # noqa: E402
from nsflow_ros.train.card import CARD_NAME  # noqa: E402
from nsflow_ros.train.cli import main  # noqa: E402
from nsflow_ros.train.data import PairConfig, load_image, make_pair  # noqa: E402
from nsflow_ros.train.distill import Teacher, distill_loss, principal_components  # noqa: E402
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


def test_principal_components_find_the_direction_of_most_variation():
    rng = np.random.default_rng(0)
    direction = np.array([0.6, -0.8, 0.0])
    # pixels spread mostly along `direction`, a little along z, about a mean of (1, 2, 3)
    spread = np.array([0.0, 0.0, 0.5])
    pixels = rng.normal(size=(5000, 1)) * 3.0 * direction + rng.normal(size=(5000, 3)) * spread
    maps = [(pixels + np.array([1.0, 2.0, 3.0])).reshape(50, 100, 3)]
    top, mean = principal_components(maps, 2)
    assert top.shape == (2, 3) and mean == pytest.approx([1.0, 2.0, 3.0], abs=0.1)
    np.testing.assert_allclose(top @ top.T, np.eye(2), atol=1e-9)
    # the largest weight of each direction is positive: -0.8 -> the sign flips to (-0.6, 0.8, 0)
    np.testing.assert_allclose(top[0], [-0.6, 0.8, 0.0], atol=0.01)
    np.testing.assert_allclose(np.abs(top[1]), [0.0, 0.0, 1.0], atol=0.01)
    with pytest.raises(TrainError, match=r"k must be in \[1, 3\], got 4"):
        principal_components(maps, 4)


def test_a_narrower_student_learns_the_teachers_leading_component(teacher_path):
    photos = [load_image("astronaut"), load_image("camera")]
    with pytest.raises(TrainError, match=r"principal components .* images to fit them are needed"):
        Teacher(teacher_path, 1, 1)
    teacher = Teacher(teacher_path, 1, 1, photos)
    full = Teacher(teacher_path, 2, 1)
    assert teacher.projection is not None and full.projection is None
    image = load_image("coins")
    top, mean = teacher.projection
    expected = np.einsum("dhw,d->hw", full(image).numpy() - mean[:, None, None], top[0])
    got = teacher(image)
    assert got.shape == (1, *image.shape)
    np.testing.assert_allclose(got[0].numpy(), expected, atol=1e-5)


def test_the_teacher_gives_its_maps_without_its_declared_smoothing(tmp_path, teacher_path):
    import onnx

    model = onnx.load(teacher_path)
    onnx.helper.set_model_props(model, {"smoothing": "1.0,1.0"})
    smoothed = tmp_path / "smoothed.onnx"
    onnx.save(model, smoothed)
    image = load_image("coins")
    raw = load_encoder(teacher_path)(image)
    assert load_encoder(smoothed).smoothing.fine == 1.0
    np.testing.assert_array_equal(Teacher(smoothed, 2, 1)(image).permute(1, 2, 0).numpy(), raw)


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
    card = (models / CARD_NAME).read_text()
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


def test_distill_weight_adds_the_teachers_loss_to_the_lk_layers(teacher_path):
    from nsflow_ros.train.trainer import batch_loss

    pair = make_pair(load_image("astronaut"), np.random.default_rng(3), PairConfig(128, 96, max_points=30))
    teacher = Teacher(teacher_path, 2, 1)
    torch.manual_seed(0)
    model = Encoder(EncoderSpec(d=2, width=2))
    lk, used = batch_loss(model, [pair], TrainConfig())
    alone, _ = batch_loss(model, [pair], TrainConfig(), teacher)  # distillation alone (weight 0)
    both, used_both = batch_loss(model, [pair], TrainConfig(distill_weight=2.5), teacher)
    assert used > 5 and used_both == used and float(lk) != float(alone)
    assert float(both) == pytest.approx(float(lk) + 2.5 * float(alone), rel=1e-6)


def test_light_min_draws_only_strong_lighting_changes():
    from nsflow_ros.train.sources import PairStream

    with pytest.raises(TrainError, match=r"light_min must be in \[0, 1\], got 1.5"):
        PairConfig(64, 48, light_min=1.5)
    strengths: list[float] = []

    class Recorder:
        def sample(self, rng, cfg, strength):
            strengths.append(strength)
            return make_pair(load_image("camera"), rng, cfg)

        def describe(self) -> str:
            return "recorder"

    data = PairStream(Recorder(), PairConfig(96, 64, max_points=10, light_min=0.8), seed=1)
    for i in range(20):
        data[i]
    assert min(strengths) >= 0.8 and max(strengths) <= 1.0
