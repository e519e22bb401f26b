"""Reading a rendered capture folder (cnnps.synth.render.rendered_folder, and the extract
stage that reads the render stage's folders) imports neither the capture renderer nor
Blender: a fresh Python reads a finished folder, checks it against its ``scene.json`` and
loads its lights, images, mask and normals with only the reader imported."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
RENDERER = ("bpy", "cnnps.synth.capture_render", "cnnps.synth.blender", "cnnps.synth.render.resume")

READ = """
import json, sys
from pathlib import Path
import numpy as np
from cnnps.io.capture import load_capture
from cnnps.synth.render.rendered_folder import folder_problems, is_complete
import cnnps.stages.extract  # the stage that reads the render stage's folders

folder = Path(sys.argv[1])
got = {"complete": is_complete(folder, "k"), "other_key": is_complete(folder, "other"),
       "problems": [[p.name, why] for p, why in folder_problems(folder)]}
if not got["problems"]:
    cap = load_capture(folder)
    got.update(lights=cap.lights.tolist(), normal_gt=cap.normal_gt[0, 0].tolist(),
               image_sum=float(np.sum(cap.images, dtype=np.float64)))
got["renderer_modules"] = sorted(m for m in %r if m in sys.modules)
print(json.dumps(got))
""" % (RENDERER,)


def _finished_folder(out: Path, lights: np.ndarray) -> np.ndarray:
    """A finished render folder as the renderer leaves it: images, light files, mask,
    normals and a ``scene.json`` recording each file's size and SHA-256 and its own
    checksum (made here from cnnps.infra.hashing, not from the reader). Returns the images."""
    from cnnps.infra.hashing import add_json_checksum, file_record
    from cnnps.io.capture import SCENE_INDENT
    from cnnps.io.images import write_exr, write_png

    out.mkdir()
    names = [f"{i:03d}.exr" for i in range(len(lights))]
    images = np.random.default_rng(1).random((len(lights), 6, 6, 3)).astype(np.float32)
    for name, image in zip(names, images):
        write_exr(out / name, image)
    (out / "filenames.txt").write_text("".join(n + "\n" for n in names))
    np.savetxt(out / "light_directions.txt", lights)
    np.savetxt(out / "light_intensities.txt", np.ones((len(lights), 3)))
    write_png(out / "mask.png", np.full((6, 6), 255, np.uint8))
    np.save(out / "normal_gt.npy", np.tile(np.array([0.6, 0.0, 0.8], np.float32), (6, 6, 1)))
    files = ["filenames.txt", "light_directions.txt", "light_intensities.txt", "mask.png", "normal_gt.npy", *names]
    meta = {"key": "k", "filenames": names, "render_seconds": 2.5, "images_rendered_last_run": len(names),
            "files": {n: file_record(out / n) for n in files}}
    meta = add_json_checksum(meta, indent=SCENE_INDENT, skip=("render_seconds", "images_rendered_last_run"))
    (out / "scene.json").write_text(json.dumps(meta, indent=SCENE_INDENT) + "\n")
    return images


def _read_in_fresh_python(folder: Path) -> dict:
    r = subprocess.run([sys.executable, "-c", READ, str(folder)], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_reading_a_rendered_folder_imports_no_renderer(tmp_path):
    lights = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.6, 0.8]])
    images = _finished_folder(tmp_path / "cap", lights)
    got = _read_in_fresh_python(tmp_path / "cap")
    assert got["renderer_modules"] == []
    assert got["complete"] and not got["other_key"] and got["problems"] == []
    np.testing.assert_allclose(got["lights"], lights, atol=1e-12)  # unit rows, read back as written
    assert got["normal_gt"] == [np.float32(0.6).item(), 0.0, np.float32(0.8).item()]
    assert got["image_sum"] == float(np.sum(images, dtype=np.float64))  # float32 EXR round-trips exactly


def test_a_damaged_image_is_named_without_the_renderer(tmp_path):
    out = tmp_path / "cap"
    _finished_folder(out, np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.6, 0.8]]))
    data = bytearray((out / "001.exr").read_bytes())
    data[-1] ^= 0xFF  # one flipped byte: same size, another SHA-256
    (out / "001.exr").write_bytes(bytes(data))
    got = _read_in_fresh_python(out)
    assert got["renderer_modules"] == []
    assert not got["complete"]
    assert got["problems"] == [["001.exr", "its bytes do not match the SHA-256 recorded when it was written (damaged)"]]
