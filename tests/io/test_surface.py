"""depth.npy / depth.png / surface.ply: contents, mesh layout and orientation, reload
with trimesh, the banded PLY writer against a one-piece reference, all-or-nothing writing."""

from __future__ import annotations

import numpy as np
import pytest

from cnnps.infra.errors import InputError
from cnnps.io.images import read_image
from cnnps.io.surface import (
    OUTPUT_FILES,
    build_surface,
    depth_picture,
    read_normals,
    surface_mesh,
    write_surface_outputs,
)
from cnnps.ps.integrate import integrate_normals


def dome(H=40, W=50, radius=30.0):
    """Normals of a sphere cap of the given radius centred in the frame, over a disc mask
    with a hole; zeros outside the mask (as `cnnps predict` writes them)."""
    r, c = np.mgrid[:H, :W].astype(np.float64)
    x, y = c - (W - 1) / 2, (H - 1) / 2 - r
    mask = x**2 + y**2 < (0.45 * min(H, W)) ** 2
    mask &= (x - 6) ** 2 + (y - 4) ** 2 > 9
    zc = np.sqrt(np.maximum(radius**2 - x**2 - y**2, 1.0))
    n = np.dstack([x / zc, y / zc, np.ones_like(zc)])
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    n[~mask] = 0.0
    return n.astype(np.float32), mask, zc


def test_write_surface_outputs(tmp_path):
    import trimesh

    normals, mask, truth = dome()
    out = tmp_path / "out"
    report = write_surface_outputs(out, normals, mask)
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUT_FILES)  # no temp files left
    for key in ("method", "pixels", "components", "residual_rms", "seconds", "vertices", "faces", "depth_min", "depth_max"):
        assert key in report
    assert report["pixels"] == int(mask.sum()) and report["components"] == 1

    depth = np.load(out / "depth.npy")
    assert depth.dtype == np.float32 and depth.shape == mask.shape
    assert np.all(np.isnan(depth[~mask])) and abs(float(np.nanmean(depth))) < 1e-4
    assert np.allclose(depth, integrate_normals(normals, mask), atol=1e-4, equal_nan=True)
    err = (depth[mask] - truth[mask]) - (depth[mask] - truth[mask]).mean()
    assert np.sqrt(np.mean(err**2)) < 0.01 * np.ptp(truth[mask])
    assert report["depth_max"] == pytest.approx(float(np.nanmax(depth)))

    picture = read_image(out / "depth.png")
    assert picture.shape == mask.shape + (3,)
    assert np.all(picture[~mask] == 0) and np.all(picture[mask].max(axis=1) > 0)

    mesh = trimesh.load(out / "surface.ply", process=False)
    assert isinstance(mesh, trimesh.Trimesh)
    assert len(mesh.vertices) == report["vertices"] and len(mesh.faces) == report["faces"] > 0
    assert "vertex_normals" in mesh._cache  # read from the file, not recomputed
    H, W = mask.shape
    rows = np.round((H - 1) / 2 - mesh.vertices[:, 1]).astype(int)
    cols = np.round(mesh.vertices[:, 0] + (W - 1) / 2).astype(int)
    assert mask[rows, cols].all()
    assert np.allclose(mesh.vertices[:, 2], depth[rows, cols], atol=1e-4)
    assert np.allclose(mesh.vertex_normals, normals[rows, cols], atol=1e-5)
    # faces wind counter-clockwise seen from the camera: their normals point to +z
    # and agree with the measured normals
    assert np.all(mesh.face_normals[:, 2] > 0)
    fn = normals[rows[mesh.faces], cols[mesh.faces]].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", mesh.face_normals, fn / np.linalg.norm(fn, axis=1, keepdims=True)) > 0.95)
    assert mesh.is_winding_consistent


def test_mesh_faces_on_small_masks():
    """Two triangles per full 2 x 2 block, one per block of three; lone pixels dropped."""
    mask = np.zeros((4, 5), bool)
    mask[0:2, 0:2] = True  # a full block: 2 triangles
    mask[2, 3] = mask[3, 3] = mask[3, 4] = True  # three of a block: 1 triangle
    mask[0, 4] = True  # isolated: no triangle, no vertex
    depth = np.where(mask, 1.0, np.nan).astype(np.float32)
    normals = np.zeros((4, 5, 3))
    normals[..., 2] = 1.0
    mesh = surface_mesh(depth, normals, mask)
    assert len(mesh.faces) == 3 and len(mesh.vertices) == 7
    assert np.all(mesh.face_normals[:, 2] > 0.999)
    assert np.allclose(mesh.vertices[:, 2], 1.0)


def reference_ply(depth, normals, mask, K=None) -> bytes:
    """surface.ply as the module docstring lays it out, built in one piece with numpy and
    written by trimesh (independent of the banded writer)."""
    import trimesh

    from cnnps.ps.camera import pixel_rays

    present = mask & np.isfinite(depth)
    H, W = present.shape
    index = np.full((H, W), -1, dtype=np.int64)
    rows, cols = np.nonzero(present)
    index[rows, cols] = np.arange(rows.size)
    a, b, d, e = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    A, B, D, E = a >= 0, b >= 0, d >= 0, e >= 0
    full = A & B & D & E
    parts = [(full, (a, d, b)), (full, (b, d, e)), (~E & A & B & D, (a, d, b)), (~D & A & B & E, (a, e, b)),
             (~B & A & D & E, (a, d, e)), (~A & B & D & E, (b, d, e))]
    faces = np.concatenate([np.stack([i[sel], j[sel], k[sel]], 1) for sel, (i, j, k) in parts])
    used = np.zeros(rows.size, dtype=bool)
    used[faces.ravel()] = True
    faces = (np.cumsum(used) - 1)[faces]
    r, c = rows[used], cols[used]
    z = depth[r, c].astype(np.float64)
    if K is None:
        vertices = np.stack([c - (W - 1) / 2.0, (H - 1) / 2.0 - r, z], axis=1)
    else:
        vertices = pixel_rays(K, r, c) * z[:, None]
    n = normals[r, c].astype(np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_normals=n, process=False, validate=False)
    return mesh.export(file_type="ply", encoding="binary", vertex_normal=True)


@pytest.mark.parametrize("band_pixels", [60, 250, 1 << 16])
@pytest.mark.parametrize("camera", ["orthographic", "pinhole"])
def test_streamed_ply_is_the_reference_byte_for_byte(tmp_path, monkeypatch, band_pixels, camera):
    """surface.ply, written a band of rows at a time (bands of one row, a few rows, the
    whole map), is byte for byte the one-piece mesh written by trimesh: holes, an island
    of one 2 x 2 block, lone pixels, one-pixel lines and diagonal borders (blocks of
    three); Surface.mesh (built on demand) exports the same bytes."""
    from cnnps.io import surface

    normals, mask, _ = dome(37, 53, 30.0)
    mask[1:3, 1:3] = True  # an island of one full block
    mask[0, 50] = mask[5, 2] = True  # lone pixels
    mask[34, 10:30] = True  # a one-pixel line
    mask[30:33, 44] = mask[31, 45] = True  # blocks of three
    normals[mask & (normals[..., 2] == 0)] = (0.1, -0.2, 0.97)
    K = np.array([[60.0, 0.0, 26.0], [0.0, 60.0, 18.0], [0.0, 0.0, 1.0]]) if camera == "pinhole" else None
    options = {} if K is None else {"intrinsics": K, "distance": 3.0}
    monkeypatch.setattr(surface, "CHUNK_PIXELS", band_pixels)
    surf = build_surface(normals, mask, **options)
    report = surf.write(tmp_path)
    expected = reference_ply(np.load(tmp_path / "depth.npy"), normals, mask, K)
    assert (tmp_path / "surface.ply").read_bytes() == expected
    assert surf.mesh.export(file_type="ply", encoding="binary", vertex_normal=True) == expected
    assert (report["vertices"], report["faces"]) == (len(surf.mesh.vertices), len(surf.mesh.faces))


def test_mask_without_a_2x2_block_writes_an_empty_mesh(tmp_path):
    """One-pixel lines carry no triangle: surface.ply holds the header only."""
    mask = np.zeros((6, 9), bool)
    mask[2, 1:8] = True
    mask[4:6, 6] = True
    normals = np.zeros((6, 9, 3), np.float32)
    normals[..., 2] = 1.0
    report = write_surface_outputs(tmp_path, normals, mask)
    assert (report["vertices"], report["faces"]) == (0, 0)
    text = (tmp_path / "surface.ply").read_bytes().decode("ascii")
    assert text.endswith("end_header\n") and "element vertex 0\n" in text and "element face 0\n" in text


def test_depth_picture_does_not_depend_on_the_bands(monkeypatch):
    from cnnps.io import surface

    normals, mask, _ = dome(37, 53, 30.0)
    depth = integrate_normals(normals, mask)
    whole = depth_picture(depth, normals, mask)
    monkeypatch.setattr(surface, "CHUNK_PIXELS", 70)
    assert np.array_equal(depth_picture(depth, normals, mask), whole)


def test_depth_picture_colours_heights():
    mask = np.ones((4, 8), bool)
    depth = np.tile(np.arange(8, dtype=np.float32), (4, 1))
    normals = np.zeros((4, 8, 3))
    normals[..., 2] = 1.0
    rgb = depth_picture(depth, normals, mask).astype(int)
    assert rgb[0, 0, 2] > rgb[0, 0, 0] and rgb[0, 7, 0] > rgb[0, 7, 2]  # far blue, near red
    assert np.all(depth_picture(np.full((4, 8), np.nan, np.float32), normals, mask) == 0)


def test_failure_while_writing_leaves_the_folder_as_it_was(tmp_path, monkeypatch):
    normals, mask, _ = dome(20, 24, 20.0)
    out = tmp_path / "out"
    out.mkdir()
    (out / "normal.npy").write_bytes(b"keep me")
    (out / "depth.npy").write_bytes(b"old")

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    from cnnps.io import images

    monkeypatch.setattr(images, "write_png", broken)
    with pytest.raises(OSError):
        write_surface_outputs(out, normals, mask)
    assert sorted(p.name for p in out.iterdir()) == ["depth.npy", "normal.npy"]
    assert (out / "depth.npy").read_bytes() == b"old"
    monkeypatch.undo()
    write_surface_outputs(out, normals, mask)  # other files in the folder are kept
    assert (out / "normal.npy").read_bytes() == b"keep me"
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUT_FILES + ("normal.npy",))


def test_bad_input_raises_before_writing(tmp_path):
    normals, mask, _ = dome(20, 24, 20.0)
    out = tmp_path / "out"
    with pytest.raises(InputError, match="mask is empty"):
        write_surface_outputs(out, normals, np.zeros_like(mask))
    with pytest.raises(InputError, match="H x W x 3"):
        write_surface_outputs(out, normals[..., :2], mask)
    assert not out.exists()


def test_read_normals(tmp_path):
    good = tmp_path / "n.npy"
    np.save(good, np.zeros((3, 4, 3), np.float32))
    assert read_normals(good).shape == (3, 4, 3)
    with pytest.raises(InputError, match="file not found"):
        read_normals(tmp_path / "missing.npy")
    pickled = tmp_path / "p.npy"
    np.save(pickled, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match=r"p\.npy: unreadable \.npy array"):
        read_normals(pickled)
    text = tmp_path / "t.npy"
    text.write_text("not numpy")
    with pytest.raises(InputError, match="unreadable"):
        read_normals(text)


BLENDER_CHECK = """
import sys, bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.ply_import(filepath=sys.argv[1])
me = bpy.context.selected_objects[0].data
up = sum(p.normal[2] > 0 for p in me.polygons)
print(len(me.vertices), len(me.polygons), up, int(me.has_custom_normals))
"""


@pytest.mark.blender
def test_surface_ply_opens_in_blender(tmp_path):
    """Blender's own PLY importer reads the mesh with its normals, faces toward the camera
    (in a separate process, so Blender's state cannot leak into other tests)."""
    import subprocess
    import sys

    normals, mask, _ = dome(20, 24, 20.0)
    report = write_surface_outputs(tmp_path, normals, mask)
    run = subprocess.run([sys.executable, "-c", BLENDER_CHECK, str(tmp_path / "surface.ply")],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path, check=False)
    assert run.returncode == 0, run.stderr
    vertices, faces, up, custom = map(int, run.stdout.strip().splitlines()[-1].split())
    assert (vertices, faces) == (report["vertices"], report["faces"])
    assert up == faces and custom == 1
