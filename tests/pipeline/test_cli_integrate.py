"""`cnnps integrate` end to end: outputs, the summary line, one-line errors that write nothing."""

from __future__ import annotations

import numpy as np
import pytest

from cnnps.io.images import write_png
from tests.support.cli import run_cli


def write_inputs(folder, H=24, W=32):
    """A Gaussian bump's normals (zeros outside an elliptical mask) and its mask PNG."""
    folder.mkdir(parents=True, exist_ok=True)
    r, c = np.mgrid[:H, :W].astype(np.float64)
    x, y = c - W / 2, H / 2 - r
    mask = (x / (0.45 * W)) ** 2 + (y / (0.45 * H)) ** 2 < 1
    a = 6.0 * np.exp(-(x**2 + y**2) / 50.0)
    zx, zy = -2 * x / 50.0 * a, -2 * y / 50.0 * a
    n = np.dstack([-zx, -zy, np.ones_like(a)])
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    n[~mask] = 0.0
    np.save(folder / "normal.npy", n.astype(np.float32))
    write_png(folder / "mask.png", (mask * 255).astype(np.uint8))
    return folder / "normal.npy", folder / "mask.png", n, mask


def test_integrate_writes_the_three_files(tmp_path, capsys):
    normals, mask_png, _, mask = write_inputs(tmp_path / "in")
    out = tmp_path / "out"
    code, stdout, stderr = run_cli(["integrate", str(normals), "--mask", str(mask_png), "--out", str(out)], capsys)
    assert code == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == ["depth.npy", "depth.png", "surface.ply"]
    lines = stdout.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"normal.npy: {int(mask.sum())} pixels, 1 component, depth range")
    assert str(out) in lines[0]
    depth = np.load(out / "depth.npy")
    assert np.all(np.isnan(depth[~mask])) and np.all(np.isfinite(depth[mask]))
    assert np.nanmax(depth) - np.nanmin(depth) == pytest.approx(6.0, rel=0.15)  # the bump's height
    assert np.unravel_index(np.nanargmax(depth), depth.shape) == (12, 16)  # its top, at the centre

    # into predict's output folder: its files are kept; --discontinuities runs too
    (out / "normal.npy").write_bytes(normals.read_bytes())
    code, stdout, stderr = run_cli(["integrate", str(out / "normal.npy"), "-m", str(mask_png), "-o", str(out),
                                    "--discontinuities", "--sigma", "0.2"], capsys)
    assert code == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == ["depth.npy", "depth.png", "normal.npy", "surface.ply"]


def _bad_shape(folder, normals, mask_png):
    np.save(normals, np.zeros((24, 32), np.float32))
    return normals


def _nan_inside(folder, normals, mask_png):
    n = np.load(normals)
    n[12, 16, 1] = np.nan
    np.save(normals, n)
    return normals


def _mask_wrong_size(folder, normals, mask_png):
    write_png(mask_png, np.full((20, 32), 255, np.uint8))
    return mask_png


def _empty_mask(folder, normals, mask_png):
    write_png(mask_png, np.zeros((24, 32), np.uint8))
    return mask_png


def _missing_normals(folder, normals, mask_png):
    normals.unlink()
    return normals


@pytest.mark.parametrize(
    "spoil, words",
    [
        (_bad_shape, "normals must be an H x W x 3 array, got shape (24, 32)"),
        (_nan_inside, "1 normals inside the mask are NaN or infinite (first at row 12, column 16)"),
        (_mask_wrong_size, "mask is 20 x 32 but the normals are 24 x 32"),
        (_empty_mask, "mask is empty"),
        (_missing_normals, "file not found"),
    ],
)
def test_bad_inputs_are_one_line_exit_2_and_write_nothing(tmp_path, capsys, spoil, words):
    normals, mask_png, _, _ = write_inputs(tmp_path / "in")
    culprit = spoil(tmp_path / "in", normals, mask_png)
    out = tmp_path / "out"
    code, _, stderr = run_cli(["integrate", str(normals), "--mask", str(mask_png), "--out", str(out)], capsys)
    assert code == 2
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith(f"cnnps: error: {culprit}: ") and words in lines[0], lines[0]
    assert not out.exists()
    assert sorted(p.name for p in (tmp_path / "in").iterdir()) == sorted(
        p for p in ("normal.npy", "mask.png") if (tmp_path / "in" / p).exists())


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--nz-min", "0"], "--nz-min must be a number in (0, 1]"),
        (["--nz-min", "x"], "--nz-min must be a number in (0, 1]"),
        (["--sigma", "-1"], "--sigma must be a number > 0"),
    ],
)
def test_bad_options(tmp_path, capsys, extra, words):
    normals, mask_png, _, _ = write_inputs(tmp_path / "in")
    out = tmp_path / "out"
    code, _, stderr = run_cli(["integrate", str(normals), "--mask", str(mask_png), "--out", str(out), *extra], capsys)
    assert code == 2 and stderr.strip() == f"cnnps: error: {words}, got {extra[1]!r}"
    assert not out.exists()


def test_out_is_a_file(tmp_path, capsys):
    normals, mask_png, _, _ = write_inputs(tmp_path / "in")
    blocker = tmp_path / "out"
    blocker.write_text("a file")
    code, _, stderr = run_cli(["integrate", str(normals), "--mask", str(mask_png), "--out", str(blocker)], capsys)
    assert code == 2 and stderr.strip() == f"cnnps: error: {blocker}: exists and is not a folder"
    assert blocker.read_text() == "a file"
