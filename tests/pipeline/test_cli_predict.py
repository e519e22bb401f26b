"""`cnnps predict` end to end: the summary line, DiLiGenT BALL, one-line errors."""

import json

import numpy as np
import pytest

from tests.support.bad_captures import BAD_INPUTS, make_bad_capture
from tests.support.cli import run_cli
from tests.support.synthetic import write_capture


def test_predict_lambertian_synthetic(tmp_path, capsys):
    write_capture(tmp_path / "cap", fmt="png16", m=16, max_tilt_deg=45)
    out = tmp_path / "out"
    code, stdout, stderr = run_cli(
        ["predict", str(tmp_path / "cap"), "--out", str(out), "--method", "lambertian",
         "--shadow-threshold", "0.01", "--no-progress"], capsys)
    assert code == 0, stderr
    lines = stdout.strip().splitlines()
    assert len(lines) == 1 and "cap (lambertian, 16 images" in lines[0] and "mean" in lines[0]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["mean_deg"] < 0.2  # 16-bit quantisation only
    assert f"mean {metrics['mean_deg']:.2f} deg" in lines[0]


def test_predict_drop_option_and_no_rule_by_folder_name(tmp_path, capsys):
    write_capture(tmp_path / "bearPNG", fmt="png8", size=12, m=24, gt=None)
    code, stdout, stderr = run_cli(["predict", str(tmp_path / "bearPNG"), "--out", str(tmp_path / "o"),
                                    "--method", "lambertian", "--no-progress"], capsys)
    assert code == 0, stderr
    assert "24 images" in stdout and "note" not in stdout  # every image: a folder's name is no rule
    assert json.loads((tmp_path / "o" / "prediction.json").read_text())["n_images"] == 24
    code, stdout, _ = run_cli(["predict", str(tmp_path / "bearPNG"), "--out", str(tmp_path / "o"),
                               "--method", "lambertian", "--drop", "0-19", "--no-progress"], capsys)
    assert code == 0 and "4 images" in stdout  # DiLiGenT's rule for BEAR, asked for
    code, stdout, _ = run_cli(["predict", str(tmp_path / "bearPNG"), "--out", str(tmp_path / "o"),
                               "--method", "lambertian", "--drop", "0-2,5", "--no-progress"], capsys)
    assert code == 0 and "20 images" in stdout and "note" not in stdout
    info = json.loads((tmp_path / "o" / "prediction.json").read_text())
    assert info["dropped"] == [0, 1, 2, 5]
    code, _, _ = run_cli(["predict", str(tmp_path / "bearPNG"), "--out", str(tmp_path / "o"),
                          "--method", "lambertian", "--drop", "none", "--no-progress"], capsys)
    assert code == 0
    assert json.loads((tmp_path / "o" / "prediction.json").read_text())["n_images"] == 24


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--method", "svm"], "--method"),
        (["--method", "lambertian", "--rotations", "ten"], "--rotations"),
        (["--method", "lambertian", "--batch-size", "-4"], "--batch-size"),
        (["--method", "lambertian", "--device", "gpu"], "--device"),
        (["--method", "lambertian", "--precision", "int8"], "--precision"),
        (["--method", "lambertian", "--drop", "1,x"], "--drop"),
        (["--method", "lambertian", "--drop", "9"], "out of range"),
        (["--method", "lambertian", "--grey", "green"], "--grey"),
        (["--method", "lambertian", "--shadow-threshold", "2"], "--shadow-threshold"),
        (["--method", "lambertian", "--shadow-threshold", "dark"], "--shadow-threshold"),
        (["--model", "/nonexistent/model.pt"], "model.pt: model file not found"),
        (["--method", "lambertian", "--linearize", "gamma"], "--linearize"),
        (["--method", "lambertian", "--tile-pixels", "0"], "--tile-pixels"),
        (["--method", "lambertian", "--tile-pixels", "many"], "--tile-pixels"),
        (["--method", "lambertian", "--saturated", "clip"], "--saturated"),
    ],
)
def test_bad_options_are_one_line(tmp_path, capsys, extra, words):
    write_capture(tmp_path / "cap", fmt="exr", size=8, m=6)
    out = tmp_path / "out"
    code, stdout, stderr = run_cli(["predict", str(tmp_path / "cap"), "--out", str(out), *extra], capsys)
    assert code == 2
    assert stderr.count("\n") == 1 and stderr.startswith("cnnps: error: ") and words in stderr
    assert not out.exists()


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_every_bad_input_exits_2_naming_the_file(tmp_path, capsys, case):
    cap, name, words = make_bad_capture(tmp_path, case)
    out = tmp_path / "out"
    code, stdout, stderr = run_cli(["predict", str(cap), "--out", str(out), "--method", "lambertian",
                                    "--no-progress", "--mask", "file", "--intensities", "file"], capsys)  # missing: errors
    assert code == 2
    assert stderr.count("\n") == 1 and stderr.startswith("cnnps: error: ")
    assert f"{name}: " in stderr and words in stderr
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["cap"]  # no temporary leftovers


def test_missing_capture_folder(tmp_path, capsys):
    code, _, stderr = run_cli(["predict", str(tmp_path / "nope"), "--out", str(tmp_path / "o"),
                               "--method", "lambertian"], capsys)
    assert code == 2 and "nope: capture folder not found" in stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.shared
@pytest.mark.slow
@pytest.mark.parametrize("grey, saturated, low, high", [("mean", "exclude", 3.7, 4.1), ("luminance", "exclude", 3.6, 4.0),
                                                        ("mean", "keep", 3.9, 4.4), ("luminance", "keep", 3.9, 4.4)])
def test_ball_lambertian(ball_dir, tmp_path, capsys, grey, saturated, low, high):
    """Plain least squares on DiLiGenT BALL, every mask pixel.

    Measured: saturated observations (676 of BALL's, in 671 pixels: the highlight) left
    out, mean grey 3.88 deg, luminance grey 3.78 deg; kept, as published methods do,
    4.29 and 4.17 deg (published: 4.10 deg).
    """
    out = tmp_path / "ball"
    code, stdout, stderr = run_cli(["predict", str(ball_dir), "--method", "lambertian", "--out", str(out),
                                    "--grey", grey, "--saturated", saturated, "--no-progress"], capsys)
    assert code == 0, stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert low < metrics["mean_deg"] < high
    assert metrics["pixels"] == 15791 and metrics["n_images"] == 96
    normal = np.load(out / "normal.npy")
    assert normal.shape == (512, 612, 3) and normal.dtype == np.float32
    assert f"mean {metrics['mean_deg']:.2f} deg" in stdout
    info = json.loads((out / "prediction.json").read_text())
    assert info["saturated_observations"] == (676 if saturated == "exclude" else 0)
    assert info["image_types"] == {"uint16": 96} and info["linearize"] == "none" and stderr == ""


def test_cuda_requested_without_cuda(tmp_path, capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    write_capture(tmp_path / "cap", fmt="exr", size=8, m=6)
    model = tmp_path / "m.pt"
    model.write_bytes(b"x")
    code, _, stderr = run_cli(["predict", str(tmp_path / "cap"), "--out", str(tmp_path / "o"),
                               "--model", str(model), "--device", "cuda"], capsys)
    assert code == 2 and stderr.count("\n") == 1 and "--device cuda" in stderr
    assert not (tmp_path / "o").exists()


def test_predict_warns_in_one_line_when_images_are_fewer_than_the_model_trained_on(tmp_path, capsys):
    # the shipped model's record says the fewest lights its training maps had: one image fewer warns
    from cnnps.models.shipped import trained_min_lights, weights_path

    fewest = trained_min_lights(weights_path(), {})
    m = max(3, fewest - 1)
    write_capture(tmp_path / "cap", fmt="exr", size=12, m=m, max_tilt_deg=45)
    code, stdout, stderr = run_cli(["predict", str(tmp_path / "cap"), "--out", str(tmp_path / "o"),
                                    "--rotations", "1", "--no-progress"], capsys)
    assert code == 0, stderr
    warnings = [line for line in stderr.splitlines() if line.startswith("cnnps: warning:")]
    assert warnings == [line for line in stderr.splitlines() if "warning" in line] and len(warnings) == 1
    assert f"{m} images, but this model was trained on maps of {fewest} or more lights" in warnings[0]
    # lambertian has no such limit
    code, _, stderr = run_cli(["predict", str(tmp_path / "cap"), "--out", str(tmp_path / "o2"),
                               "--method", "lambertian", "--no-progress"], capsys)
    assert code == 0 and "warning" not in stderr


def test_8bit_images_without_a_linearize_choice_get_one_note_on_stderr(tmp_path, capsys):
    write_capture(tmp_path / "cap", fmt="png8", size=16, m=8, gt=None)
    argv = ["predict", str(tmp_path / "cap"), "--method", "lambertian", "--no-progress", "--out"]
    code, stdout, stderr = run_cli([*argv, str(tmp_path / "a")], capsys)
    assert code == 0, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cnnps: note: 8-bit images were taken as linear")
    assert "--linearize srgb" in lines[0] and "--linearize none" in lines[0]
    assert len(stdout.strip().splitlines()) == 1
    info = json.loads((tmp_path / "a" / "prediction.json").read_text())
    assert info["linearize"] == "none" and info["linearize_chosen"] is False and info["image_types"] == {"uint8": 8}
    for choice in ("srgb", "none"):
        code, stdout, stderr = run_cli([*argv, str(tmp_path / choice), "--linearize", choice], capsys)
        assert code == 0 and stderr == ""
        info = json.loads((tmp_path / choice / "prediction.json").read_text())
        assert info["linearize"] == choice and info["linearize_chosen"] is True
    # 16-bit images are taken as linear without a note (DiLiGenT's are)
    write_capture(tmp_path / "cap16", fmt="png16", size=16, m=8, gt=None)
    code, _, stderr = run_cli(["predict", str(tmp_path / "cap16"), "--method", "lambertian", "--no-progress",
                               "--out", str(tmp_path / "b")], capsys)
    assert code == 0 and stderr == ""


def test_depth_and_tiles_from_the_command_line(tmp_path, capsys):
    write_capture(tmp_path / "cap", fmt="png16", size=24, m=12, max_tilt_deg=45)
    out = tmp_path / "out"
    code, stdout, stderr = run_cli(["predict", str(tmp_path / "cap"), "--out", str(out), "--method", "lambertian",
                                    "--shadow-threshold", "0.05", "--depth", "--tile-pixels", "50",
                                    "--scratch", str(tmp_path / "scratch"), "--no-progress"], capsys)
    assert code == 0, stderr
    assert {"depth.npy", "depth.png", "surface.ply", "normal.npy"} <= {p.name for p in out.iterdir()}
    info = json.loads((out / "prediction.json").read_text())
    assert info["tile_pixels"] == 50 and info["depth"]["pixels"] == info["pixels"]
    assert not (tmp_path / "scratch").exists() or list((tmp_path / "scratch").iterdir()) == []


def test_precision_auto_says_which_path_ran_and_why(tmp_path, capsys, monkeypatch):
    """The default ``--precision auto`` probes once (then reads its cache), ``-v`` prints
    the choice in one line and prediction.json records it; an explicit precision never
    probes."""
    import json

    from cnnps.models import precision_probe

    monkeypatch.setenv("CNNPS_CACHE_DIR", str(tmp_path / "cache"))
    # a loaded machine (other tests alongside) would rightly leave the first probe uncached
    monkeypatch.setattr(precision_probe, "judge_load", lambda passes: None)
    write_capture(tmp_path / "cap", fmt="exr", size=12, m=20, max_tilt_deg=45)
    argv = ["predict", str(tmp_path / "cap"), "--rotations", "1", "--no-progress"]
    code, _, stderr = run_cli([*argv, "--out", str(tmp_path / "a"), "-v"], capsys)
    assert code == 0, stderr
    lines = [line for line in stderr.splitlines() if line.startswith("cnnps: precision ")]
    assert len(lines) == 1 and "probe: fp32 " in lines[0] and "(cached)" not in lines[0], stderr
    first = json.loads((tmp_path / "a" / "prediction.json").read_text())
    assert first["precision"] in precision_probe.CANDIDATES
    assert first["precision_choice"]["requested"] == "auto" and not first["precision_choice"]["cached"]
    assert first["precision_choice"]["batch_size"] in precision_probe.BATCH_SIZES  # the pick's fastest batch
    code, _, stderr = run_cli([*argv, "--out", str(tmp_path / "b"), "-v"], capsys)
    second = json.loads((tmp_path / "b" / "prediction.json").read_text())
    assert code == 0 and "(cached, measured " in stderr and " s ago)" in stderr, stderr
    assert second["precision"] == first["precision"] and second["precision_choice"]["cached"]
    assert 0 <= second["precision_choice"]["age_seconds"] < 600 and not second["precision_choice"]["under_load"]

    def no_probe(*a, **k):
        raise AssertionError("an explicit --precision must not probe")

    monkeypatch.setattr(precision_probe, "probe", no_probe)
    code, _, stderr = run_cli([*argv, "--out", str(tmp_path / "c"), "--precision", "fp32"], capsys)
    third = json.loads((tmp_path / "c" / "prediction.json").read_text())
    assert code == 0 and "cnnps: precision" not in stderr
    assert third["precision"] == "fp32" and third["precision_choice"]["requested"] == "fp32"


def test_an_option_has_one_message_in_the_api_the_command_line_and_params_yaml(tmp_path, capsys):
    """sparse_fill is declared once (cnnps.ps.sparse_fill.SparseFill): each front end names
    it its own way and says the same thing about it."""
    from cnnps.api.prediction import predict_folder
    from cnnps.infra.errors import ConfigError
    from cnnps.pipeline import config

    write_capture(tmp_path / "cap", fmt="exr", size=8, m=6)
    said = "must be one of auto, on, off, got 'sometimes'"
    with pytest.raises(ConfigError) as api:
        predict_folder(tmp_path / "cap", tmp_path / "o1", sparse_fill="sometimes", progress=False)
    code, _, stderr = run_cli(["predict", str(tmp_path / "cap"), "--out", str(tmp_path / "o2"),
                               "--sparse-fill", "sometimes"], capsys)
    params = tmp_path / "params.yaml"
    params.write_text("eval:\n  sparse_fill: sometimes\n")
    with pytest.raises(ConfigError) as yaml_file:
        config.load_all(config.load_config(params), ["eval"], check_files=False)
    assert str(api.value) == f"sparse_fill {said}"
    assert code == 2 and stderr == f"cnnps: error: --sparse-fill {said}\n"
    assert str(yaml_file.value) == f"{params}: eval.sparse_fill {said}"


def test_help_shows_each_options_default(capsys):
    """Every default in `cnnps predict --help` is the API's (cnnps.predict), shown in words
    the help renderer prints (it reads "[...]" as markup and drops it)."""
    import inspect
    import re

    from cnnps.api.prediction import predict

    code, out, err = run_cli(["predict", "--help"], capsys)
    text = re.sub(r"[\s│]+", " ", out + err)
    assert code == 0
    for option, name in (("--rotations", "rotations"), ("--precision", "precision"), ("--saturated", "saturated")):
        default = inspect.signature(predict).parameters[name].default
        assert re.search(rf"{option} .*?\(default: {default}\)", text), (option, default)


def test_help_fits_a_screen_in_groups(capsys, monkeypatch):
    """`cnnps predict --help` at 80 columns: at most 80 lines, the flags in the groups of
    docs/predict.md (capture, method and network, camera and lights, output)."""
    monkeypatch.setenv("COLUMNS", "80")
    code, out, err = run_cli(["predict", "--help"], capsys)
    lines = (out + err).rstrip("\n").splitlines()
    assert code == 0 and len(lines) <= 80, len(lines)
    titles = [t for t in ("Capture", "Method and network", "Camera and lights", "Output") if f"─ {t} ─" in out + err]
    assert titles == ["Capture", "Method and network", "Camera and lights", "Output"]
    assert max(len(line) for line in lines) <= 80


@pytest.mark.parametrize("command, panels", [("calibrate", ("Balls", "Photos", "Output")),
                                             ("check", ("Capture", "Output"))])
def test_the_other_capture_commands_fit_half_a_screen(capsys, monkeypatch, command, panels):
    """`cnnps calibrate --help` and `cnnps check --help` at 80 columns: at most 40 lines,
    one short line a flag in its group (the details live in the docs)."""
    monkeypatch.setenv("COLUMNS", "80")
    code, out, err = run_cli([command, "--help"], capsys)
    lines = (out + err).rstrip("\n").splitlines()
    assert code == 0 and len(lines) <= 40, len(lines)
    assert [t for t in panels if f"─ {t} ─" in out + err] == list(panels)
