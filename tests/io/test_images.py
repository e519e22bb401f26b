"""Image readers: raw types, the scaled reader, JPEG, channel order, formats."""

import numpy as np
import pytest

from cnnps.infra.errors import InputError
from cnnps.io.images import max_code, read_image, read_image_raw, write_exr, write_png


def _colour_image(h=16, w=20, dtype=np.uint16):
    top = np.iinfo(dtype).max
    img = np.zeros((h, w, 3), dtype)
    img[..., 0] = top  # red everywhere
    img[: h // 2, :, 1] = top // 2
    img[:, : w // 2, 2] = top // 4
    return img


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_raw_and_scaled(tmp_path, dtype):
    img = _colour_image(dtype=dtype)
    write_png(tmp_path / "a.png", img)
    raw = read_image_raw(tmp_path / "a.png")
    assert raw.dtype == dtype and raw.shape == img.shape
    np.testing.assert_array_equal(raw, img)  # RGB order, not OpenCV's BGR
    scaled = read_image(tmp_path / "a.png")
    assert scaled.dtype == np.float32
    np.testing.assert_array_equal(scaled, img.astype(np.float32) / float(max_code(dtype)))


@pytest.mark.parametrize("suffix", [".jpg", ".jpeg", ".JPG"])
def test_jpeg(tmp_path, suffix):
    import cv2

    img = _colour_image(32, 32, np.uint8)
    path = tmp_path / f"a{suffix}"
    assert cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 100])
    raw = read_image_raw(path)
    assert raw.dtype == np.uint8 and raw.shape == (32, 32, 3)
    # lossy, but the colours are where they should be (R full, G top half, B left half)
    assert np.abs(raw.astype(int) - img).mean() < 3
    assert raw[24, 24, 0] > 240 and raw[4, 24, 1] > 110 and raw[24, 4, 2] > 50 and raw[24, 24, 2] < 10


def test_grey_and_alpha(tmp_path):
    grey = (np.arange(12 * 10).reshape(12, 10) % 256).astype(np.uint8)
    write_png(tmp_path / "g.png", grey)
    raw = read_image_raw(tmp_path / "g.png")
    assert raw.shape == (12, 10, 1)
    np.testing.assert_array_equal(raw[..., 0], grey)
    import cv2

    rgba = np.dstack([_colour_image(8, 8, np.uint16)[..., ::-1], np.full((8, 8), 7, np.uint16)])
    cv2.imwrite(str(tmp_path / "rgba.png"), rgba)
    np.testing.assert_array_equal(read_image_raw(tmp_path / "rgba.png"), _colour_image(8, 8, np.uint16))


def test_exr_and_tiff_raw(tmp_path):
    import tifffile

    img = np.random.default_rng(0).uniform(0, 3, (6, 7, 3)).astype(np.float32)
    write_exr(tmp_path / "a.exr", img)
    raw = read_image_raw(tmp_path / "a.exr")
    assert raw.dtype == np.float32 and max_code(raw.dtype) is None
    np.testing.assert_array_equal(raw, img)
    t8 = _colour_image(6, 7, np.uint8)
    tifffile.imwrite(tmp_path / "a.tif", t8, photometric="rgb")
    assert read_image_raw(tmp_path / "a.tif").dtype == np.uint8
    np.testing.assert_array_equal(read_image(tmp_path / "a.tif"), t8.astype(np.float32) / 255.0)
    tifffile.imwrite(tmp_path / "b.tif", np.zeros((4, 4), np.int16))
    with pytest.raises(InputError, match="unsupported pixel type int16"):
        read_image(tmp_path / "b.tif")


def test_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_image_raw(tmp_path / "none.png")
    (tmp_path / "x.bmp").write_bytes(b"BM")
    with pytest.raises(InputError, match="JPEG"):
        read_image_raw(tmp_path / "x.bmp")
    (tmp_path / "bad.jpg").write_bytes(b"\xff\xd8 not really")
    with pytest.raises(InputError, match="unreadable") as info:
        read_image(tmp_path / "bad.jpg")
    assert info.value.path == tmp_path / "bad.jpg"


def test_max_code():
    assert max_code(np.uint8) == 255 and max_code(np.uint16) == 65535 and max_code(np.float32) is None
