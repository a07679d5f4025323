"""CI smoke test of training: a few steps lower the loss; the ONNX export loads and matches torch."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nsflow_ros import Smoothing, load_encoder  # noqa: E402
from nsflow_ros.train.card import CARD_NAME, write_model_card  # noqa: E402
from nsflow_ros.train.cli import main  # noqa: E402
from nsflow_ros.train.data import PairConfig, load_image, make_pair  # noqa: E402
from nsflow_ros.train.export import export_onnx  # noqa: E402
from nsflow_ros.train.model import Encoder, EncoderSpec, count_parameters  # noqa: E402
from nsflow_ros.train.trainer import TrainConfig, train_step  # noqa: E402


def test_import_nsflow_ros_does_not_import_torch():
    code = "import sys, nsflow_ros; sys.exit(1 if 'torch' in sys.modules else 0)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def test_missing_torch_gives_a_clear_error():
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "try:\n    import nsflow_ros.train\n"
        "except Exception as err:\n    print(type(err).__name__, err)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False).stdout
    assert out.startswith("TrainError") and "pip install 'nsflow_ros[train]'" in out


def test_loss_decreases_on_a_repeated_pair():
    torch.manual_seed(0)
    torch.set_num_threads(2)
    pair_cfg = PairConfig(width=128, height=96, max_points=60, init_sigma=1.5)
    pair = make_pair(load_image("astronaut"), np.random.default_rng(1), pair_cfg, strength=0.5)
    assert len(pair.points) > 20
    cfg = TrainConfig(spec=EncoderSpec(d=2), pair=pair_cfg, rho="cauchy")
    model = Encoder(cfg.spec)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    losses = [train_step(model, opt, pair, cfg) for _ in range(60)]
    assert all(v is not None for v in losses)
    first, last = np.mean(losses[:5]), np.mean(losses[-10:])
    assert last < 0.9 * first, f"loss did not decrease: first {first:.4f}, last {last:.4f}"


def test_coarse_to_fine_step_trains_the_coarse_levels_only_through_their_loss():
    from dataclasses import replace

    torch.manual_seed(0)
    pair_cfg = PairConfig(width=160, height=120, max_points=60, init_mode="uniform", init_sigma=12.0)
    pair = make_pair(load_image("astronaut"), np.random.default_rng(1), pair_cfg, strength=0.5)
    grads = {}
    for weight in (0.0, 1.0):
        cfg = TrainConfig(lm=replace(TrainConfig().lm, levels=3), coarse_weight=weight, pair=pair_cfg)
        torch.manual_seed(0)
        model = Encoder(cfg.spec)
        opt = torch.optim.SGD(model.parameters(), lr=0.0)  # lr 0: keep the weights, read the gradients
        value = train_step(model, opt, pair, cfg)
        assert value is not None and np.isfinite(value)
        grads[weight] = torch.cat([p.grad.flatten() for p in model.parameters()])
    assert float(grads[0.0].abs().sum()) > 0
    # The coarse levels' loss adds a gradient of its own (the starts are detached: nothing else reaches them).
    rel = float(torch.linalg.vector_norm(grads[1.0] - grads[0.0]) / torch.linalg.vector_norm(grads[0.0]))
    assert rel > 0.05


@pytest.mark.parametrize("spec", [EncoderSpec(d=4), EncoderSpec(d=3, in_channels=3, head="relu")])
def test_export_loads_and_matches_torch(tmp_path, spec):
    torch.manual_seed(0)
    model = Encoder(spec).eval()
    path = export_onnx(model, tmp_path / "enc.onnx")
    enc = load_encoder(path)
    assert enc.channels == spec.d and enc.input_channels == spec.in_channels
    assert enc.name == f"nsflow-d{spec.d}"
    img = np.random.default_rng(0).integers(0, 256, (37, 53, 3), dtype=np.uint8)  # BGR, odd size
    got = enc(img)
    if spec.in_channels == 1:
        import cv2

        x = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)[None, None]
    else:
        x = img[..., ::-1].transpose(2, 0, 1)[None]
    with torch.no_grad():
        ref = model(torch.from_numpy(x.astype(np.float32) / 255.0))[0].permute(1, 2, 0).numpy()
    assert got.shape == (37, 53, spec.d)
    assert np.abs(got - ref).max() < 1e-5


def test_parameter_count_matches_the_paper():
    # The paper's 1.01e-3 M parameters: RGB input, d = 3, with biases.
    assert count_parameters(Encoder(EncoderSpec(d=3, in_channels=3, head="relu"))) == 1003


def test_cli_runs_end_to_end(tmp_path, capsys):
    out, models = tmp_path / "run", tmp_path / "models"
    models.mkdir()
    # the hand-written card of the other models (no markers of any kind): the install leaves it alone
    shipped = "# Model card\n\n## `default`\n\nhand-written\n\n## `d4`: `nsflow_encoder.onnx`\n\nfigures\n"
    (models / "README.md").write_text(shipped)
    args = "--steps 3 --d 2 --val-every 3 --eval-per-image 1 --val-per-image 1 --no-progress --install"
    code = main([*args.split(), "--out", str(out), "--models-dir", str(models)])
    assert code == 0
    assert (models / "README.md").read_text() == shipped
    for name in (
        "nsflow_encoder.onnx",
        "loss.png",
        "val_epoch00.png",
        "eval.md",
        "encoder.pt",
        "eval_heldout.png",
    ):
        assert (out / name).is_file(), name
    assert "ONNX vs torch" in capsys.readouterr().out
    card = (models / CARD_NAME).read_text()
    assert "| perturbed | levels=3 | NSFlow |" in card and "| clean | levels=1 | classical |" in card
    assert "--steps 3" in card and len(card.splitlines()) <= 150
    assert load_encoder(models / "nsflow_encoder.onnx").channels == 2
    for png in ("train_loss.png", "train_validation.png", "eval_heldout.png"):
        assert (models / png).stat().st_size < 200_000


def test_cli_without_validation_installs_without_its_figure(tmp_path):
    out, models = tmp_path / "run", tmp_path / "models"
    args = "--steps 2 --d 2 --val-every 0 --eval-per-image 1 --no-progress --install"
    assert main([*args.split(), "--out", str(out), "--models-dir", str(models)]) == 0
    assert not list(out.glob("val_epoch*.png"))
    assert (models / "train_loss.png").is_file() and not (models / "train_validation.png").exists()
    assert "train_validation.png" not in (models / CARD_NAME).read_text()


def test_cli_reports_known_errors(tmp_path, capsys):
    assert main(["--steps", "1", "--d", "0", "--out", str(tmp_path / "x")]) == 1
    assert "EncoderSpec.d" in capsys.readouterr().err
    assert main(["--steps", "1", "--coarse-loss", "-1", "--out", str(tmp_path / "x")]) == 1
    assert "coarse_weight must be >= 0" in capsys.readouterr().err
    assert main(["--steps", "1", "--scene-share", "1.5", "--out", str(tmp_path / "x")]) == 1
    assert "scene_share must be in [0, 1], got 1.5" in capsys.readouterr().err
    assert main(["--steps", "1", "--basin-loss", "-1", "--out", str(tmp_path / "x")]) == 1
    assert "basin weight and radius must be >= 0" in capsys.readouterr().err
    for bad in ("gauss:2", "uniform", "normal:-1"):
        with pytest.raises(SystemExit) as exc:
            main(["--init-error", bad])
        assert exc.value.code == 2
        assert "expected normal:S, uniform:R or zero" in capsys.readouterr().err
    for bad in ("1", "1,-0.5", "a,b", "nan,1"):
        with pytest.raises(SystemExit) as exc:
            main(["--smoothing", bad])
        assert exc.value.code == 2
        assert "expected FINE,COARSE" in capsys.readouterr().err


def test_cli_trains_coarse_to_fine(tmp_path):
    out, models = tmp_path / "run", tmp_path / "models"
    args = "--steps 2 --d 2 --levels 3 --coarse-loss 0.5 --init-error uniform:20 --translation 12"
    args += " --basin-loss 1 --jacobian esm --zero-mean --gain-levels 1"
    args += " --val-every 2 --eval-per-image 1 --val-per-image 1 --no-progress --threads 1 --install"
    assert main([*args.split(), "--out", str(out), "--models-dir", str(models)]) == 0
    enc = load_encoder(out / "nsflow_encoder.onnx")
    assert enc.channels == 2 and enc.gain_levels == 1  # the export declares the tracker's gain
    config = json.loads((out / "run.json").read_text())["config"]
    assert "'levels': 3" in config["lm"] and config["coarse_weight"] == "0.5"
    assert "Jacobian.ESM" in config["lm"] and "'zero_mean': True" in config["lm"]
    assert config["basin_weight"] == "1.0"
    assert "'init_mode': 'uniform'" in config["pair"] and "'init_sigma': 20.0" in config["pair"]
    card = (models / CARD_NAME).read_text()
    assert "3-level coarse-to-fine LM" in card and "0.5 x the same penalty of each coarse level" in card
    assert "uniform in [0, 20] px" in card and "1 x the basin loss" in card


@pytest.mark.parametrize("levels", [1, 3])
def test_cli_trains_through_the_smoothing_and_the_export_declares_it(tmp_path, capsys, levels):
    out = tmp_path / "run"
    args = f"--steps 2 --d 2 --levels {levels} --smoothing 1,0.5 --basin-loss 1"
    args += " --val-every 2 --eval-per-image 1 --val-per-image 1 --no-progress --threads 1"
    assert main([*args.split(), "--out", str(out)]) == 0
    enc = load_encoder(out / "nsflow_encoder.onnx")
    assert enc.smoothing == Smoothing(1.0, 0.5) and enc.metadata["smoothing"] == "1,0.5"
    # the export check compares the unsmoothed maps with torch's
    diff = float(capsys.readouterr().out.split("ONNX vs torch max abs difference: ")[1].split()[0])
    assert diff < 1e-4
    config = json.loads((out / "run.json").read_text())["config"]
    assert config["smoothing"] == "{'fine': 1.0, 'coarse': 0.5}"


def test_smoothing_changes_the_training_step(tmp_path):
    # same seed, same pair: the loss differs only through the smoothing in the solver's maps
    pair = make_pair(load_image("camera"), np.random.default_rng(0), PairConfig(), strength=0.0)
    losses = []
    for smoothing in (None, Smoothing(1.0, 0.5)):
        torch.manual_seed(0)
        model = Encoder(EncoderSpec(d=2))
        opt = torch.optim.SGD(model.parameters(), lr=0.0)
        losses.append(train_step(model, opt, pair, TrainConfig(smoothing=smoothing)))
    assert None not in losses and abs(losses[0] - losses[1]) > 1e-4


def test_cli_trains_on_tartanair_and_footage_and_compares_on_held_out_footage(tmp_path, tartanair):
    from train_sources_data import write_footage_bag

    root, _ = tartanair
    bag = write_footage_bag(tmp_path / "bag", frames=5)
    out, models = tmp_path / "run", tmp_path / "models"
    args = "--steps 2 --d 2 --size 96x72 --points 30 --batch 2 --val-every 2 --eval-per-image 1"
    args += " --val-per-image 1 --footage-eval-per-frame 1 --no-progress --install"
    data = ["--data", f"tartanair:{root}:0.6", "--data", f"footage:{bag}:0.4"]
    assert main([*args.split(), *data, "--out", str(out), "--models-dir", str(models)]) == 0
    table = (out / "eval_footage.md").read_text()
    for row in ("lighting change | this run", "lighting change | shipped", "same lighting | classical"):
        assert f"| {row} |" in table
    assert (out / "eval_footage.png").is_file()
    card = (models / CARD_NAME).read_text()
    assert "60%: TartanAir" in card and "environments abandonedfactory" in card
    assert "40%: footage" in card and "1 later frames held out" in card
    record = json.loads((out / "run.json").read_text())
    assert record["data"]["validation"]["tartanair"]["environments"] == ["hospital"]


def test_recipe_paper_sets_the_papers_values_and_explicit_options_win(tmp_path, capsys):
    from nsflow_ros.train.cli import parse

    opts = parse(["--recipe", "paper", "--data", "tartanair:/x"])
    assert (opts.size, opts.points, opts.iterations, opts.window, opts.lr, opts.batch) == (
        (640, 480), 200, 50, 11, 1e-3, 1
    )
    assert (opts.rgb, opts.d, opts.width, opts.head) == (True, 3, 8, "relu")
    mine = parse(["--recipe", "paper", "--size", "128x96", "--iterations", "20"])
    assert mine.size == (128, 96) and mine.iterations == 20 and mine.points == 200
    assert parse([]).size == (320, 240) and parse([]).iterations == 30
    assert main(["--recipe", "paper", "--steps", "1", "--out", str(tmp_path / "x")]) == 1
    assert "--recipe paper trains on TartanAir: give --data tartanair:DIR" in capsys.readouterr().err
    missing = tmp_path / "none"
    assert main(["--steps", "1", "--data", f"footage:{missing}", "--out", str(tmp_path / "x")]) == 1
    assert f"nsflow-train: error: footage {missing}: data set not found" in capsys.readouterr().err


def test_the_card_states_what_the_paper_leaves_open(tmp_path):
    from nsflow_ros.train.recipes import PAPER_OPEN

    sources = [{"kind": "tartanair", "path": "/d/ta", "environments": ["a", "b"], "pairs": 10, "share": 1.0}]
    spec = EncoderSpec(d=3, in_channels=3, head="relu")
    cfg = TrainConfig(spec=spec, command="nsflow-train --recipe paper")
    card = write_model_card(
        tmp_path / CARD_NAME, cfg, parameters=1003, flops=1, steps=1, seconds=1.0, tables="", figures={},
        data=sources, recipe=("paper", PAPER_OPEN),
    ).read_text()
    assert "100%: TartanAir `/d/ta`, environments a, b (10 pairs)" in card
    assert "Recipe `paper`" in card and "perturbation std sigma of the initial flow" in card


def test_init_from_the_shipped_onnx_encoder(tmp_path):
    from nsflow_ros.core.encoder import DEFAULT_MODEL
    from nsflow_ros.resources import share_file
    from nsflow_ros.train.errors import TrainError
    from nsflow_ros.train.trainer import load_checkpoint

    shipped = share_file(DEFAULT_MODEL)
    spec = json.loads(load_encoder(shipped).metadata["spec"])
    model = Encoder(EncoderSpec(**spec)).eval()
    load_checkpoint(model, shipped)
    img = np.random.default_rng(0).integers(0, 256, (40, 52), dtype=np.uint8)
    with torch.no_grad():
        ours = model(torch.from_numpy(img.astype(np.float32) / 255.0)[None, None])[0].permute(1, 2, 0).numpy()
    assert np.abs(ours - load_encoder(shipped, smoothing=Smoothing())(img)).max() < 1e-5
    with pytest.raises(TrainError, match="holds an encoder of spec"):
        load_checkpoint(Encoder(EncoderSpec(d=2)), shipped)
