"""Writing a capture folder (cnnps.io.capture.write_capture) and reading it back: the same
Capture, for distant lights with an orthographic camera, with a pinhole camera, and with
point lights; benchmark rules only where they are asked for."""

from __future__ import annotations

import numpy as np
import pytest

from cnnps.infra.errors import InputError
from cnnps.io.capture import (
    DILIGENT_RULES,
    FILE_NAMES,
    FILENAMES_FILE,
    INTRINSICS_FILE,
    LIGHT_DIRECTIONS_FILE,
    LIGHT_INTENSITIES_FILE,
    LIGHT_POSITIONS_FILE,
    BenchmarkRule,
    Capture,
    benchmark_drop,
    load_capture,
    read_scene,
    scan_capture,
    subset_drop,
    write_capture,
)
from tests.support.synthetic import random_lights, sphere_normals
from tests.support.synthetic import write_capture as write_sphere


def _sphere(m: int = 6, size: int = 16, dtype=np.uint16, seed: int = 0) -> dict:
    """Arrays of a small Lambertian sphere capture: stored images, lights, mask, normals."""
    normals, mask = sphere_normals(size)
    L = random_lights(m, seed, 50.0)
    E = np.random.default_rng(seed).uniform(0.5, 2.0, (m, 3))
    shade = np.clip(np.einsum("hwc,mc->mhw", normals, L), 0, None)[..., None] * mask[None, :, :, None]
    rgb = shade * E[:, None, None, :] / E.max() * 0.9
    if dtype == np.float32:
        images, ext = rgb.astype(np.float32), "exr"
    else:
        top = np.iinfo(dtype).max
        images, ext = np.round(rgb * top).astype(dtype), "png"
    return {"images": images, "lights": L, "intensities": E, "mask": mask, "normals": normals.astype(np.float32),
            "names": [f"{j:03d}.{ext}" for j in range(m)]}


def _same(a: Capture, b: Capture) -> None:
    assert a.filenames == b.filenames
    np.testing.assert_array_equal(a.images, b.images)
    assert a.images.dtype == b.images.dtype
    np.testing.assert_array_equal(a.mask, b.mask)
    np.testing.assert_allclose(a.lights, b.lights, atol=1e-9)
    np.testing.assert_allclose(a.intensities, b.intensities, rtol=1e-8)
    for name in ("normal_gt", "depth_gt", "intrinsics", "light_positions"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9, err_msg=name)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_orthographic_round_trip(tmp_path, dtype):
    s = _sphere(dtype=dtype)
    cap = Capture(filenames=s["names"], lights=s["lights"], intensities=s["intensities"], mask=s["mask"],
                  images=s["images"], normal_gt=s["normals"])
    assert write_capture(tmp_path / "cap", cap) == tmp_path / "cap"
    back = load_capture(tmp_path / "cap")
    _same(cap, back)
    assert back.intrinsics is None and back.light_positions is None and back.root == tmp_path / "cap"
    assert not (tmp_path / "cap" / INTRINSICS_FILE).exists()
    # the grey values of the written capture are those of the one in memory, bit for bit
    np.testing.assert_array_equal(back.pixel_intensities(), cap.pixel_intensities())
    # and written again from what was read: the same folder
    write_capture(tmp_path / "again", back)
    _same(back, load_capture(tmp_path / "again"))
    for name in (FILENAMES_FILE, LIGHT_DIRECTIONS_FILE, LIGHT_INTENSITIES_FILE):
        assert (tmp_path / "cap" / name).read_bytes() == (tmp_path / "again" / name).read_bytes()


def test_perspective_round_trip(tmp_path):
    s = _sphere()
    K = np.array([[40.0, 0.0, 7.5], [0.0, 40.0, 7.5], [0.0, 0.0, 1.0]])
    depth = np.where(s["mask"], 5.0 - s["normals"][..., 2], np.nan).astype(np.float32)
    cap = Capture(filenames=s["names"], lights=s["lights"], intensities=s["intensities"], mask=s["mask"],
                  images=s["images"], normal_gt=s["normals"], intrinsics=K, depth_gt=depth)
    write_capture(tmp_path / "cap", cap)
    back = load_capture(tmp_path / "cap")
    _same(cap, back)
    np.testing.assert_array_equal(back.intrinsics, K)
    np.testing.assert_array_equal(np.isnan(back.depth_gt), ~s["mask"])


def test_point_light_round_trip(tmp_path):
    s = _sphere()
    positions = s["lights"] * 3.0 - [0.0, 0.0, 5.0]  # in front of the camera: z < 0
    K = np.array([[40.0, 0.0, 7.5], [0.0, 40.0, 7.5], [0.0, 0.0, 1.0]])
    cap = Capture(filenames=s["names"], light_positions=positions, intensities=s["intensities"], mask=s["mask"],
                  images=s["images"], intrinsics=K)
    assert cap.lights.shape == (6, 3)  # seen from the optical axis at the lights' median distance
    write_capture(tmp_path / "cap", cap)
    names = {p.name for p in (tmp_path / "cap").iterdir()}
    assert LIGHT_POSITIONS_FILE in names and LIGHT_DIRECTIONS_FILE not in names
    back = scan_capture(tmp_path / "cap")
    assert back.images is None and back.notes == []
    np.testing.assert_allclose(back.light_positions, positions, atol=1e-9)
    np.testing.assert_allclose(back.lights, cap.lights, atol=1e-9)
    _same(cap, load_capture(tmp_path / "cap"))


def test_images_from_a_generator_and_a_scene_record(tmp_path):
    s = _sphere(dtype=np.float32)
    cap = Capture(filenames=s["names"], lights=s["lights"], intensities=s["intensities"], mask=s["mask"])
    made = []

    def scene():
        return {"images_made": len(made)}

    def images():
        for img in s["images"]:
            made.append(1)
            yield img

    write_capture(tmp_path / "cap", cap, images(), scene=scene)
    np.testing.assert_array_equal(load_capture(tmp_path / "cap").images, s["images"])
    assert read_scene(tmp_path / "cap") == {"images_made": 6}  # called after the images


def test_a_failed_write_leaves_nothing_and_an_existing_folder_is_kept(tmp_path):
    s = _sphere()
    cap = Capture(filenames=s["names"], lights=s["lights"], intensities=s["intensities"], mask=s["mask"])
    with pytest.raises(ValueError, match="5 images for 6"):
        write_capture(tmp_path / "cap", cap, list(s["images"][:5]))
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="needs the images"):
        write_capture(tmp_path / "cap", cap)
    write_capture(tmp_path / "cap", cap, s["images"])
    with pytest.raises(InputError, match="exists"):
        write_capture(tmp_path / "cap", cap, s["images"])
    write_capture(tmp_path / "cap", cap, s["images"] // 2, overwrite=True)
    np.testing.assert_array_equal(load_capture(tmp_path / "cap").images, s["images"] // 2)
    with pytest.raises(ValueError, match=r"lights must be \(6, 3\)"):
        Capture(filenames=s["names"], lights=s["lights"][:5])


def test_every_written_name_is_a_capture_file_name(tmp_path):
    s = _sphere()
    K = np.diag([40.0, 40.0, 1.0])
    cap = Capture(filenames=s["names"], lights=s["lights"], intensities=s["intensities"], mask=s["mask"],
                  images=s["images"], normal_gt=s["normals"], intrinsics=K,
                  depth_gt=np.ones(s["mask"].shape, np.float32))
    write_capture(tmp_path / "cap", cap, scene={"k": 1})
    names = {p.name for p in (tmp_path / "cap").iterdir()}
    assert names - set(s["names"]) <= set(FILE_NAMES)


# ---------------------------------------------------------------- benchmark rules


def test_the_bear_rule_applies_only_when_asked(tmp_path):
    write_sphere(tmp_path / "bearPNG", fmt="png8", size=8, m=24)
    write_sphere(tmp_path / "ballPNG", fmt="png8", size=8, m=24)
    assert load_capture(tmp_path / "bearPNG").n_images == 24  # the reader knows no benchmark
    drop = benchmark_drop(tmp_path / "bearPNG", DILIGENT_RULES)
    assert drop == list(range(20)) and DILIGENT_RULES["bearPNG"].reason
    cap = load_capture(tmp_path / "bearPNG", drop=drop)
    assert cap.dropped == list(range(20)) and cap.n_images == 4
    assert cap.filenames == [f"{j:03d}.png" for j in range(20, 24)]
    assert benchmark_drop(tmp_path / "ballPNG", DILIGENT_RULES) == []
    assert benchmark_drop(tmp_path / "bearPNG", {}) == []
    # a rule's indices past a short capture's end are left out
    assert benchmark_drop(tmp_path / "bearPNG", {"bearPNG": BenchmarkRule(drop=(0, 30), reason="x")}) == [0]


def test_subsets_are_drawn_from_what_the_rule_leaves(tmp_path):
    write_sphere(tmp_path / "bearPNG", fmt="png8", size=8, m=30)
    rule = benchmark_drop(tmp_path / "bearPNG", DILIGENT_RULES)
    drop = subset_drop(tmp_path / "bearPNG", 6, exclude=rule)
    kept = sorted(set(range(30)) - set(drop))
    assert len(kept) == 6 and min(kept) >= 20
    anywhere = subset_drop(tmp_path / "bearPNG", 6)
    assert len(set(range(30)) - set(anywhere)) == 6 and anywhere != drop
