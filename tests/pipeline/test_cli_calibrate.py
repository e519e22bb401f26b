"""`cnnps calibrate`: analytic ball folders (no Blender), one-line errors that write nothing,
and the end-to-end check on rendered balls: calibrate, then `cnnps predict` with the
calibrated lights is as good as with the true ones."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from cnnps.io.images import write_png
from cnnps.synth.lights import hemisphere_lights
from tests.support.calibration import (
    BALL,
    angles_deg,
    chrome_image,
    matte_image,
    write_ball_folder,
)
from tests.support.cli import run_cli

LIGHTS = hemisphere_lights(8, jitter_deg=4.0, seed=11, min_elevation_deg=10.0)
E = np.random.default_rng(2).uniform(0.7, 1.3, (len(LIGHTS), 3))


@pytest.fixture
def balls(tmp_path):
    """chrome/ (16-bit PNG, no mask) and matte/ (EXR) folders of analytic balls."""
    chrome = [chrome_image(l, peak=0.8, body=0.08) for l in LIGHTS]
    matte = [matte_image(l, e) * 0.6 for l, e in zip(LIGHTS, E)]
    write_ball_folder(tmp_path / "chrome", chrome, "png16")
    write_ball_folder(tmp_path / "matte", matte, "exr")
    return tmp_path / "chrome", tmp_path / "matte"


def test_calibrate_writes_lights_picture_and_report(tmp_path, balls, capsys):
    chrome, matte = balls
    out = tmp_path / "lights"
    code, stdout, stderr = run_cli(["calibrate", str(chrome), "--matte", str(matte), "--out", str(out),
                                    "--no-progress"], capsys)
    assert code == 0, stderr
    lines = stdout.strip().splitlines()
    # the matte ball's limb is dim where no light grazes it (8 lights): its outline is less sharp
    for line, what, tol in zip(lines[:2], ("chrome ball", "matte ball"), (0.03, 0.15)):
        m = re.match(rf"{what}: centre x=([-\d.]+), y=([-\d.]+) px, radius ([\d.]+) px \(", line)
        assert m, line
        x, y, r = map(float, m.groups())
        assert abs(x - BALL.cx) < tol and abs(y - BALL.cy) < tol and abs(r - BALL.radius) < tol, line
    assert "median image" in lines[0] and "maximum image" in lines[1]
    assert "mean over lights and channels is 1" in lines[2]
    assert "8 light directions" in lines[-1]
    L = np.loadtxt(out / "light_directions.txt")
    err = angles_deg(L, LIGHTS)
    assert err.mean() < 0.1 and err.max() < 0.3
    I = np.loadtxt(out / "light_intensities.txt")
    assert I.mean() == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(I, E / E.mean(), rtol=0.01)
    report = json.loads((out / "calibration.json").read_text())
    assert report["chrome_ball"]["radius_px"] == pytest.approx(BALL.radius, abs=0.1)
    from cnnps.io.images import read_image

    pic = read_image(out / "calibration.png")
    assert pic.shape[2] == 3 and min(pic.shape[:2]) >= 400
    # again without --matte into the same folder: no intensities any more, a note says so
    code, stdout, _ = run_cli(["calibrate", str(chrome), "--out", str(out), "--no-progress"], capsys)
    assert code == 0 and "note: no --matte" in stdout
    assert not (out / "light_intensities.txt").exists() and (out / "light_directions.txt").exists()


def test_srgb_8bit_photos_need_linearize_srgb(tmp_path, capsys):
    """Camera-like ball photos (8-bit sRGB-encoded PNGs): with --linearize srgb the
    intensities are right within 3 %; without a choice the images are taken as linear,
    one note on stderr says so, and the intensities are wrong (as in cnnps predict)."""
    chrome = [chrome_image(l, peak=0.8, body=0.08) for l in LIGHTS]
    matte = [matte_image(l, e) * 0.6 for l, e in zip(LIGHTS, E)]
    write_ball_folder(tmp_path / "chrome", chrome, "png8", srgb=True)
    write_ball_folder(tmp_path / "matte", matte, "png8", srgb=True)
    args = ["calibrate", str(tmp_path / "chrome"), "--matte", str(tmp_path / "matte"), "--no-progress"]
    truth = E / E.mean()
    results = {}
    for choice in ("srgb", "none", None):
        out = tmp_path / f"lights_{choice}"
        code, _, stderr = run_cli(args + ["--out", str(out)] + ([] if choice is None else ["--linearize", choice]),
                                  capsys)
        assert code == 0, stderr
        results[choice] = (np.loadtxt(out / "light_intensities.txt"), np.loadtxt(out / "light_directions.txt"),
                           stderr, json.loads((out / "calibration.json").read_text()))
    I, L, stderr, report = results["srgb"]
    assert np.abs(I / truth - 1).max() < 0.03
    assert angles_deg(L, LIGHTS).max() < 0.5
    assert stderr == "" and report["linearize"] == "srgb" and report["linearize_chosen"]
    assert report["image_types"] == {"chrome": {"uint8": 8}, "matte": {"uint8": 8}}
    # unset: taken as linear, one note; the same numbers as an explicit "none", which is silent
    I, L, stderr, report = results[None]
    lines = stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("cnnps: note: 8-bit images were taken as linear"), stderr
    assert "--linearize srgb" in lines[0]
    assert report["linearize"] == "none" and not report["linearize_chosen"]
    assert np.abs(I / truth - 1).max() > 0.1  # the sRGB curve left in flattens the intensities
    np.testing.assert_array_equal(I, results["none"][0])
    np.testing.assert_array_equal(L, results["none"][1])
    assert results["none"][2] == ""
    # a bad choice: one line, exit 2, nothing written
    out = tmp_path / "lights_bad"
    code, _, stderr = run_cli(args + ["--out", str(out), "--linearize", "gamma"], capsys)
    assert code == 2 and stderr.count("\n") == 1 and "--linearize must be one of srgb, none" in stderr, stderr
    assert not out.exists()


def _edit_image(folder, j, image):
    write_ball_folder(folder / "tmp", [image], "png16")
    shutil.move(folder / "tmp" / "000.png", folder / f"{j:03d}.png")
    shutil.rmtree(folder / "tmp")


BAD = {
    "no highlight": (lambda c, m: _edit_image(c, 3, chrome_image(LIGHTS[3], peak=0.0, body=0.08)),
                     "chrome/003.png", "no specular highlight"),
    "two highlights": (lambda c, m: _edit_image(c, 5, chrome_image(LIGHTS[5], peak=0.8, body=0.08,
                                                                   extra_spots=[(BALL.cx - 14, BALL.cy - 3)])),
                       "chrome/005.png", "2 separate highlights"),
    "saturated": (lambda c, m: _edit_image(c, 2, chrome_image(LIGHTS[2], peak=40.0, sigma=3.0, body=0.08)),
                  "chrome/002.png", "saturated"),
    "no filenames.txt, no images": (lambda c, m: [f.unlink() for f in c.iterdir() if f.name != "mask.png"],
                                    "chrome/filenames.txt", "not found"),
    "missing image": (lambda c, m: (c / "004.png").unlink(), "chrome/004.png", "not found"),
    "count mismatch": (lambda c, m: (m / "filenames.txt").write_text("000.exr\n001.exr\n"),
                       "matte/filenames.txt", "lists 2 images"),
    "matte image missing": (lambda c, m: (m / "006.exr").unlink(), "matte/006.exr", "not found"),
    "image of another size": (lambda c, m: _edit_image(c, 1, np.zeros((20, 20))), "chrome/001.png", "20x20"),
    "mask of another size": (lambda c, m: write_png(c / "mask.png", np.full((9, 9), 255, np.uint8)),
                             "chrome/mask.png", "9x9"),
    "empty mask": (lambda c, m: write_png(m / "mask.png", np.zeros((72, 80), np.uint8)), "matte/mask.png", "empty"),
    "no ball": (lambda c, m: [_edit_image(c, j, np.full((72, 80), 0.3)) for j in range(len(LIGHTS))],
                "chrome", "add a mask.png"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_is_one_line_exit_2_nothing_written(tmp_path, balls, capsys, case):
    chrome, matte = balls
    corrupt, where, words = BAD[case]
    corrupt(chrome, matte)
    out = tmp_path / "lights"
    code, stdout, stderr = run_cli(["calibrate", str(chrome), "--matte", str(matte), "--out", str(out),
                                    "--no-progress"], capsys)
    assert code == 2, (stdout, stderr)
    assert stderr.count("\n") == 1 and stderr.startswith("cnnps: error: "), stderr
    assert where in stderr and words in stderr, stderr
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".lights")]  # no temp folder left


def test_output_folder_is_checked_first(tmp_path, balls, capsys):
    chrome, matte = balls
    out = tmp_path / "full"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    code, _, stderr = run_cli(["calibrate", str(chrome), "--out", str(out), "--no-progress"], capsys)
    assert code == 2 and "keep.txt" in stderr and (out / "keep.txt").read_text() == "mine"
    code, _, stderr = run_cli(["calibrate", str(chrome), "--out", str(chrome), "--no-progress"], capsys)
    assert code == 2 and "input folder" in stderr
    code, _, stderr = run_cli(["calibrate", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o"),
                               "--no-progress"], capsys)
    assert code == 2 and "nowhere: chrome ball folder not found" in stderr and not (tmp_path / "o").exists()


# --------------------------------------------------------------------------- rendered, end to end


@pytest.mark.blender
def test_calibrated_lights_predict_as_well_as_true_ones(tmp_path, capsys):
    """A chrome ball, a matte ball and an object rendered under the same jittered lights
    with per-light RGB intensities: `cnnps calibrate` then `cnnps predict` (Lambertian
    least squares) gives normals within 0.5 degrees (mean) of those from the true lights."""
    from cnnps.synth.calibration_scenes import (
        random_intensities,
        render_calibration_set,
    )

    L = hemisphere_lights(24, jitter_deg=5.0, seed=21)
    E = random_intensities(len(L), seed=22, spread=0.3)
    sets = render_calibration_set(tmp_path / "set", L, E, size=32, ball_radius_px=36, samples=4, seed=0,
                                  threads=2, progress=False)
    lights = tmp_path / "lights"
    code, stdout, stderr = run_cli(["calibrate", str(sets["chrome"]), "--matte", str(sets["matte"]),
                                    "--out", str(lights), "--no-progress"], capsys)
    assert code == 0, stderr
    calibrated = tmp_path / "object_calibrated"
    shutil.copytree(sets["object"], calibrated)
    for name in ("light_directions.txt", "light_intensities.txt"):
        shutil.copyfile(lights / name, calibrated / name)
    err = angles_deg(np.loadtxt(lights / "light_directions.txt"), L)
    assert err.mean() <= 0.5 and err.max() <= 1.5, err

    means = {}
    for name, cap in (("true", sets["object"]), ("calibrated", calibrated)):
        out = tmp_path / f"pred_{name}"
        code, stdout, stderr = run_cli(["predict", str(cap), "--out", str(out), "--method", "lambertian",
                                        "--shadow-threshold", "0.05", "--no-progress"], capsys)
        assert code == 0, stderr
        means[name] = json.loads((out / "metrics.json").read_text())["mean_deg"]
    assert abs(means["calibrated"] - means["true"]) <= 0.5, means
