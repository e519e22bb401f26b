"""A folder without filenames.txt: its photos in name order (a phone's numbering)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from cnnps.infra.errors import InputError
from cnnps.io.capture import is_capture_folder, read_filenames, scan_capture, scan_images
from cnnps.io.capture.files import photo_names
from tests.support.synthetic import write_capture


def _touch(folder, *names):
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes(b"")


def test_photos_in_natural_name_order_without_the_pictures_beside_them(tmp_path):
    _touch(tmp_path / "f", "IMG_10.JPG", "IMG_2.jpg", "IMG_1.jpeg", "mask.png", "Normal_gt.png", ".hidden.png",
           "notes.txt", "light_directions.txt", "b.tif")
    (tmp_path / "f" / "sub.png").mkdir()
    assert photo_names(tmp_path / "f") == ["b.tif", "IMG_1.jpeg", "IMG_2.jpg", "IMG_10.JPG"]
    notes = []
    assert read_filenames(tmp_path / "f", notes) == photo_names(tmp_path / "f")
    assert len(notes) == 1 and "name order" in notes[0] and "b.tif ... IMG_10.JPG" in notes[0]
    assert is_capture_folder(tmp_path / "f")


def test_filenames_txt_wins_over_name_order(tmp_path):
    _touch(tmp_path, "a.png", "b.png")
    (tmp_path / "filenames.txt").write_text("b.png\na.png\n")
    notes = []
    assert read_filenames(tmp_path, notes) == ["b.png", "a.png"] and notes == []


def test_no_list_and_no_photo_is_one_error_naming_the_list(tmp_path):
    _touch(tmp_path, "mask.png", "light_directions.txt")
    with pytest.raises(InputError) as err:
        read_filenames(tmp_path)
    assert str(err.value).startswith(str(tmp_path / "filenames.txt")) and "no images" in str(err.value)
    assert not is_capture_folder(tmp_path)


def test_a_capture_without_its_list_reads_the_same_as_with_it(tmp_path):
    listed = tmp_path / "listed"
    write_capture(listed, fmt="png8", size=12, m=8)
    bare = tmp_path / "bare"
    shutil.copytree(listed, bare)
    (bare / "filenames.txt").unlink()
    a, b = scan_capture(listed), scan_capture(bare)
    assert a.filenames == b.filenames
    np.testing.assert_array_equal(a.lights, b.lights)
    assert not any("name order" in n for n in a.notes)
    assert any("name order" in n for n in b.notes)
    photos = scan_images(bare, "chrome ball")
    assert photos.filenames == a.filenames and any("name order" in n for n in photos.notes)
