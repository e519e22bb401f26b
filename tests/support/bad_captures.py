"""Every kind of broken capture folder: (corruption, file the error must name, words it must say)."""

from __future__ import annotations

import numpy as np

from cnnps.io import images
from tests.support.synthetic import write_capture


def _rewrite_line(path, lineno, text):
    lines = path.read_text().splitlines()
    lines[lineno - 1] = text
    path.write_text("\n".join(lines) + "\n")


def _write_exr_pixel(cap, name, value):
    from cnnps.io.images import read_image, write_exr

    img = read_image(cap / name)
    img[3, 4, 1] = value
    write_exr(cap / name, img)


# (corruption, file named in the error, words in the message)
BAD_INPUTS = {
    "no filenames.txt, no images": (lambda c: [f.unlink() for f in c.iterdir() if f.name == "filenames.txt" or f.suffix == ".exr"],
                                    "filenames.txt", "not found"),
    # without filenames.txt the images are taken in name order: a stray one is one image too many
    "no filenames.txt, a stray image": (lambda c: ((c / "filenames.txt").unlink(),
                                                   images.write_exr(c / "extra.exr", np.zeros((16, 16, 3), np.float32))),
                                        "light_directions.txt", "7 images"),
    "no light_directions.txt": (lambda c: (c / "light_directions.txt").unlink(), "light_directions.txt", "not found"),
    "no light_intensities.txt": (lambda c: (c / "light_intensities.txt").unlink(), "light_intensities.txt", "not found"),
    "no mask": (lambda c: (c / "mask.png").unlink(), "mask.png", "not found"),
    "missing image": (lambda c: (c / "003.exr").unlink(), "003.exr", "not found"),
    "fewer lights than images": (lambda c: _rewrite_line(c / "light_directions.txt", 6, ""), "light_directions.txt", "5 light directions"),
    "fewer intensities": (lambda c: _rewrite_line(c / "light_intensities.txt", 1, ""), "light_intensities.txt", "5 light intensities"),
    "more images than lights": (lambda c: (c / "filenames.txt").write_text("\n".join(f"{i:03d}.exr" for i in range(6)) + "\n000.exr\n"), "light_directions.txt", "7 images"),
    "zero light vector": (lambda c: _rewrite_line(c / "light_directions.txt", 4, "0 0 0"), "light_directions.txt", "line 4"),
    "nan light vector": (lambda c: _rewrite_line(c / "light_directions.txt", 2, "nan 0 1"), "light_directions.txt", "line 2"),
    "two numbers": (lambda c: _rewrite_line(c / "light_directions.txt", 3, "0.1 0.2"), "light_directions.txt", "line 3"),
    "text in lights": (lambda c: _rewrite_line(c / "light_directions.txt", 3, "0.1 x 0.9"), "light_directions.txt", "line 3"),
    "zero intensity": (lambda c: _rewrite_line(c / "light_intensities.txt", 5, "1 0 1"), "light_intensities.txt", "line 5"),
    "inf intensity": (lambda c: _rewrite_line(c / "light_intensities.txt", 6, "1 inf 1"), "light_intensities.txt", "line 6"),
    "nan pixel": (lambda c: _write_exr_pixel(c, "002.exr", np.nan), "002.exr", "NaN"),
    "inf pixel": (lambda c: _write_exr_pixel(c, "004.exr", np.inf), "004.exr", "infinite"),
    "image of another size": (lambda c: images.write_exr(c / "005.exr", np.zeros((10, 12, 3), np.float32)), "005.exr", "12x10"),
    "mask of another size": (lambda c: images.write_png(c / "mask.png", np.ones((16, 8), np.uint8)), "mask.png", "8x16"),
    "empty mask": (lambda c: images.write_png(c / "mask.png", np.zeros((16, 16), np.uint8)), "mask.png", "empty"),
    "unreadable image": (lambda c: (c / "001.exr").write_bytes(b"not an exr at all"), "001.exr", "unreadable"),
    "unreadable mask": (lambda c: (c / "mask.png").write_bytes(b"\x89PNG garbage"), "mask.png", "unreadable"),
    "gt wrong shape": (lambda c: np.save(c / "normal_gt.npy", np.zeros((16, 16), np.float32)), "normal_gt.npy", "shape"),
    "gt not finite": (lambda c: np.save(c / "normal_gt.npy", np.full((16, 16, 3), np.nan, np.float32)), "normal_gt.npy", "NaN"),
    "mat gt without variable": (lambda c: __import__("scipy.io").io.savemat(c / "Normal_gt.mat", {"N": np.zeros((16, 16, 3))}), "Normal_gt.mat", "Normal_gt"),
    "empty filenames": (lambda c: (c / "filenames.txt").write_text("\n"), "filenames.txt", "empty"),
}


def make_bad_capture(tmp_path, case):
    """A 16x16, 6-image EXR capture broken in the way ``case`` names."""
    cap = tmp_path / "cap"
    write_capture(cap, fmt="exr", size=16, m=6)
    corrupt, name, words = BAD_INPUTS[case]
    corrupt(cap)
    return cap, name, words
