"""The files of a capture folder: every file name, and the reader and the writer of each.

Every name a capture folder uses is a constant here (``*_FILE``; :data:`FILE_NAMES`
lists them); no other module of ``cnnps`` spells one (``tests/io/test_capture_names.py``
holds that). The layout (docs/capture.md):

- :data:`FILENAMES_FILE` ``filenames.txt``: one image name a line, in light order;
- :data:`LIGHT_DIRECTIONS_FILE` ``light_directions.txt``: m lines ``lx ly lz`` (camera
  frame: x right, y up, z toward the camera);
- :data:`LIGHT_INTENSITIES_FILE` ``light_intensities.txt``: m lines ``r g b``;
- :data:`LIGHT_POSITIONS_FILE` ``light_positions.txt``: point lights near the object, m
  lines ``x y z`` (origin at the camera's optical centre), in place of the directions;
  needs :data:`INTRINSICS_FILE` ``intrinsics.txt``, a pinhole camera's K (3 rows of 3);
- :data:`MASK_FILE` ``mask.png``: non-zero = object;
- ground truth: :data:`NORMAL_GT_MAT_FILE` ``Normal_gt.mat`` (variable ``Normal_gt``) or
  :data:`NORMAL_GT_FILE` ``normal_gt.npy`` (H x W x 3), and :data:`DEPTH_GT_FILE`
  ``depth_gt.npy`` (H x W depth along the optical axis, NaN outside the mask);
- :data:`SCENE_FILE` ``scene.json``: a renderer's record of how the folder was made.

Readers raise one :class:`cnnps.infra.errors.InputError` naming the bad file. Writers
write each file atomically (:mod:`cnnps.infra.atomic`: temporary name, then rename), in
the formats the readers read back to the same numbers (directions and positions with 9
decimals, intensities with 9 significant digits, K with 12).

Example::

    write_light_directions(folder, L)               # folder / "light_directions.txt"
    read_filenames(folder)                           # ['000.png', '001.png', ...]
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from cnnps.infra.atomic import atomic_path, write_text
from cnnps.infra.errors import InputError

FILENAMES_FILE = "filenames.txt"
LIGHT_DIRECTIONS_FILE = "light_directions.txt"
LIGHT_INTENSITIES_FILE = "light_intensities.txt"
LIGHT_POSITIONS_FILE = "light_positions.txt"
INTRINSICS_FILE = "intrinsics.txt"
MASK_FILE = "mask.png"
NORMAL_GT_MAT_FILE = "Normal_gt.mat"
NORMAL_GT_FILE = "normal_gt.npy"
DEPTH_GT_FILE = "depth_gt.npy"
SCENE_FILE = "scene.json"
FILE_NAMES = (FILENAMES_FILE, LIGHT_DIRECTIONS_FILE, LIGHT_INTENSITIES_FILE, LIGHT_POSITIONS_FILE, INTRINSICS_FILE,
              MASK_FILE, NORMAL_GT_MAT_FILE, NORMAL_GT_FILE, DEPTH_GT_FILE, SCENE_FILE)
NORMAL_GT_MAT_VARIABLE = "Normal_gt"  # the variable of NORMAL_GT_MAT_FILE
GROUND_TRUTH_FILES = (NORMAL_GT_MAT_FILE, NORMAL_GT_FILE)  # normals; the first present is read
# the stems of pictures a capture folder may hold beside its photos (mask.png, DiLiGenT's
# Normal_gt.png): never taken for photos when there is no FILENAMES_FILE
NOT_PHOTO_STEMS = ("mask", "normal_gt")
SCENE_INDENT = 2  # SCENE_FILE is json.dumps(scene, indent=2) + "\n"


# ----------------------------------------------------------------------------- text files


def _read_lines(path: Path) -> list[tuple[int, str]]:
    """Non-empty lines with their 1-based line numbers (comments with '#' allowed)."""
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"unreadable text file ({exc})") from exc
    out = []
    for i, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if line:
            out.append((i, line))
    return out


def read_vectors(path: Path, what: str) -> tuple[np.ndarray, list[int]]:
    """((n, 3) float64 rows, their 1-based line numbers) of a text file of three numbers a
    line (spaces or commas; '#' comments and blank lines skipped); ``what`` names the
    numbers in errors (e.g. ``"lx ly lz"``). An InputError naming the file for a missing or
    empty file, a line without three numbers, or a non-finite value."""
    path = Path(path)
    rows = []
    for lineno, line in _read_lines(path):
        parts = line.replace(",", " ").split()
        if len(parts) != 3:
            raise InputError(path, f"line {lineno}: expected 3 numbers ({what}), got {line!r}")
        try:
            v = [float(p) for p in parts]
        except ValueError:
            raise InputError(path, f"line {lineno}: not a number in {line!r}") from None
        if not all(np.isfinite(v)):
            raise InputError(path, f"line {lineno}: non-finite value in {line!r}")
        rows.append((lineno, v))
    if not rows:
        raise InputError(path, "file is empty")
    return np.array([v for _, v in rows], dtype=np.float64), [n for n, _ in rows]


def _natural_key(name: str) -> list:
    """Sort key putting ``IMG_2`` before ``IMG_10``: digit runs compared as numbers."""
    return [(0, int(part), part) if part.isdigit() else (1, 0, part.lower()) for part in re.split(r"(\d+)", name)]


def photo_names(root: Path) -> list[str]:
    """The photos of a folder without ``filenames.txt``: its image files
    (:data:`cnnps.io.images.IMAGE_SUFFIXES`) in natural name order (``IMG_2`` before
    ``IMG_10``), less hidden files and the pictures a capture folder holds beside its photos
    (:data:`NOT_PHOTO_STEMS`: ``mask.png``, ``Normal_gt.png``). Sub-folders are not read."""
    from cnnps.io.images import IMAGE_SUFFIXES

    root = Path(root)
    if not root.is_dir():
        return []
    names = [p.name for p in root.iterdir()
             if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
             and p.stem.lower() not in NOT_PHOTO_STEMS]
    return sorted(names, key=_natural_key)


def read_filenames(root: Path, notes: list[str] | None = None) -> list[str]:
    """The image names of ``root/filenames.txt`` (one a line, light order; '#' comments
    and blank lines skipped). Without that file, the folder's photos in name order
    (:func:`photo_names`), with a line saying so appended to ``notes``. An InputError when
    the file lists nothing, or when there is neither the file nor a photo."""
    path = Path(root) / FILENAMES_FILE
    if not path.is_file():
        names = photo_names(root)
        if not names:
            raise InputError(path, "file not found, and the folder holds no images (PNG, JPEG, TIFF, EXR or RAW) "
                                   "to take in name order")
        if notes is not None:
            notes.append(f"{FILENAMES_FILE}: none in {root}; its {len(names)} images taken in name order "
                         f"({names[0]} ... {names[-1]}): light files must list the lights in that order")
        return names
    names = [line for _, line in _read_lines(path)]
    if not names:
        raise InputError(path, "file is empty")
    return names


def is_capture_folder(path: Path) -> bool:
    """Whether ``path`` holds a ``filenames.txt`` or, without it, photos to take in name
    order (:func:`photo_names`)."""
    return (Path(path) / FILENAMES_FILE).is_file() or bool(photo_names(path))


def read_intrinsics(path: Path) -> np.ndarray | None:
    """K (3, 3) from an intrinsics file (three rows of three numbers; a capture's is
    ``root / INTRINSICS_FILE``), None when the file does not exist; an InputError naming
    it when it is not a valid pinhole matrix (:func:`cnnps.ps.camera.check_intrinsics`)."""
    from cnnps.ps.camera import check_intrinsics

    path = Path(path)
    if not path.is_file():
        return None
    try:
        return check_intrinsics(np.loadtxt(path, dtype=np.float64, ndmin=2))
    except ValueError as exc:
        raise InputError(path, str(exc)) from None


def read_light_positions(root: Path, m: int, notes: list[str]) -> np.ndarray | None:
    """(m, 3) float64 point-light positions of ``root/light_positions.txt`` (None without
    one); an InputError naming the file for a wrong count, a light behind the camera, or
    no intrinsics file beside it. A note is added when the directions file is there too."""
    from cnnps.ps.near_lights import check_positions

    root = Path(root)
    path = root / LIGHT_POSITIONS_FILE
    if not path.is_file():
        return None
    pos, _lines = read_vectors(path, "x y z")
    if len(pos) != m:
        raise InputError(path, f"has {len(pos)} light positions but {FILENAMES_FILE} lists {m} images")
    try:
        pos = check_positions(pos)
    except ValueError as exc:
        raise InputError(path, str(exc)) from None
    if not (root / INTRINSICS_FILE).is_file():
        raise InputError(path, f"point lights need a perspective camera: add {INTRINSICS_FILE} (K, 3 x 3) to the folder")
    if (root / LIGHT_DIRECTIONS_FILE).is_file():
        notes.append(f"{LIGHT_POSITIONS_FILE} and {LIGHT_DIRECTIONS_FILE} are both present: the point lights are used")
    return pos


def read_light_directions(root: Path, m: int | None = None, unit: bool = True) -> np.ndarray:
    """(m, 3) float64 light directions of ``root/light_directions.txt``: normalised to
    unit length (``unit``), or as written. An InputError naming the file for a count other
    than ``m`` (when given) or a zero-length direction."""
    path = Path(root) / LIGHT_DIRECTIONS_FILE
    dirs, lines = read_vectors(path, "lx ly lz")
    if m is not None and len(dirs) != m:
        raise InputError(path, f"has {len(dirs)} light directions but {FILENAMES_FILE} lists {m} images")
    norms = np.linalg.norm(dirs, axis=1)
    bad = np.flatnonzero(norms < 1e-8)
    if bad.size:
        raise InputError(path, f"line {lines[bad[0]]}: zero-length light direction")
    return dirs / norms[:, None] if unit else dirs


def read_light_intensities(root: Path, m: int, required: bool = True) -> np.ndarray | None:
    """(m, 3) float64 RGB intensities of ``root/light_intensities.txt``, all > 0; an
    InputError naming the file otherwise. Without the file: None when not ``required``
    (the caller estimates them: :mod:`cnnps.ps.intensity_estimate`)."""
    path = Path(root) / LIGHT_INTENSITIES_FILE
    if not required and not path.is_file():
        return None
    ints, lines = read_vectors(path, "r g b")
    if len(ints) != m:
        raise InputError(path, f"has {len(ints)} light intensities but {FILENAMES_FILE} lists {m} images")
    bad = np.flatnonzero(np.any(ints <= 0, axis=1))
    if bad.size:
        raise InputError(path, f"line {lines[bad[0]]}: light intensities must be > 0, got {ints[bad[0]].tolist()}")
    return ints


def read_lights(root: Path, m: int, positions: np.ndarray | None = None,
                intensities_required: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """((m, 3) unit directions, (m, 3) intensities) of a capture folder. With point-light
    ``positions`` the directions are those seen from the optical axis at their median
    distance (:func:`cnnps.ps.near_lights.directions_from_positions`) and no directions
    file is read. Intensities None: no file, and not ``intensities_required``."""
    if positions is not None:
        from cnnps.ps.near_lights import directions_from_positions

        return directions_from_positions(positions), read_light_intensities(root, m, intensities_required)
    return read_light_directions(root, m), read_light_intensities(root, m, intensities_required)


def read_light_files(root: Path, m: int, notes: list[str], lights_dir: Path | None = None,
                     missing_ok: tuple[str, ...] = ()):
    """(positions or None, (m, 3) directions or None, (m, 3) intensities or None, K or None)
    of a capture folder ``root`` whose light files (directions or positions, intensities and
    the camera's ``intrinsics.txt`` when there) are in ``lights_dir`` (a ``cnnps calibrate``
    output folder; default: ``root`` itself; ``intrinsics.txt`` is then read from ``root``
    when ``lights_dir`` has none). ``missing_ok`` may hold ``"lights"`` (no directions or
    positions file: directions None) and ``"intensities"`` (:func:`read_lights`)."""
    src = Path(root) if lights_dir is None else Path(lights_dir)
    if lights_dir is not None and not src.is_dir():
        raise InputError(src, "light files folder not found" if not src.exists() else "not a folder")
    K = read_intrinsics(src / INTRINSICS_FILE)
    K = read_intrinsics(Path(root) / INTRINSICS_FILE) if K is None else K
    positions = read_light_positions(src, m, notes)
    if positions is None and "lights" in missing_ok and not (src / LIGHT_DIRECTIONS_FILE).is_file():
        return None, None, read_light_intensities(src, m, "intensities" not in missing_ok), K
    return (positions, *read_lights(src, m, positions, intensities_required="intensities" not in missing_ok), K)


# ----------------------------------------------------------------------------- mask, ground truth, record


def require_mask(root: Path) -> None:
    """An InputError naming ``root/mask.png`` when it is missing."""
    path = Path(root) / MASK_FILE
    if not path.is_file():
        raise InputError(path, "file not found (every capture needs an object mask)")


def read_mask_file(root: Path, shape: tuple[int, int] | None, required: bool = True) -> np.ndarray | None:
    """(H, W) bool mask of ``root/mask.png`` (non-zero = object), checked to be ``shape``
    (images' (H, W); None: not checked) and not empty. Without the file: an InputError
    when ``required``, else None."""
    from cnnps.io.images import read_mask

    path = Path(root) / MASK_FILE
    if not path.is_file():
        if required:
            require_mask(root)
        return None
    mask = read_mask(path)
    if shape is not None and mask.shape != tuple(shape):
        H, W = shape
        raise InputError(path, f"mask is {mask.shape[1]}x{mask.shape[0]} but the images are {W}x{H}")
    if not mask.any():
        raise InputError(path, "mask is empty (no non-zero pixel)")
    return mask


def ground_truth_file(root: Path) -> Path | None:
    """The normals' ground-truth file of a capture folder (``Normal_gt.mat`` first, then
    ``normal_gt.npy``), or None."""
    for name in GROUND_TRUTH_FILES:
        if (Path(root) / name).is_file():
            return Path(root) / name
    return None


def read_normal_gt(root: Path, shape: tuple[int, int]) -> np.ndarray | None:
    """(H, W, 3) float32 ground-truth normals (:func:`ground_truth_file`), None without;
    an InputError naming the file when it is unreadable, not ``shape`` x 3, or not finite."""
    path = ground_truth_file(root)
    if path is None:
        return None
    if path.name == NORMAL_GT_MAT_FILE:
        import scipy.io

        try:
            data = scipy.io.loadmat(str(path))
        except Exception as exc:
            raise InputError(path, f"unreadable MATLAB file ({exc})") from exc
        if NORMAL_GT_MAT_VARIABLE not in data:
            raise InputError(path, f"has no variable '{NORMAL_GT_MAT_VARIABLE}'")
        gt = data[NORMAL_GT_MAT_VARIABLE]
    else:
        gt = _load_npy(path)
    if gt.shape != tuple(shape) + (3,):
        raise InputError(path, f"ground truth has shape {gt.shape}, expected {tuple(shape) + (3,)} (H x W x 3)")
    if not np.issubdtype(gt.dtype, np.number):
        raise InputError(path, f"ground truth has non-numeric type {gt.dtype}")
    gt = gt.astype(np.float32)
    if not np.all(np.isfinite(gt)):
        raise InputError(path, "ground truth contains NaN or infinity")
    return gt


def read_depth_gt(root: Path, shape: tuple[int, int]) -> np.ndarray | None:
    """(H, W) float32 ground-truth depth along the optical axis (``root/depth_gt.npy``,
    NaN outside the object), None without; an InputError naming the file when it is
    unreadable, not ``shape`` or not numeric."""
    path = Path(root) / DEPTH_GT_FILE
    if not path.is_file():
        return None
    depth = _load_npy(path)
    if depth.shape != tuple(shape):
        raise InputError(path, f"depth has shape {depth.shape}, expected {tuple(shape)} (H x W)")
    if not np.issubdtype(depth.dtype, np.number):
        raise InputError(path, f"depth has non-numeric type {depth.dtype}")
    return depth.astype(np.float32)


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:
        raise InputError(path, f"unreadable .npy file ({exc})") from exc


def read_scene(root: Path) -> dict | None:
    """The renderer's record ``root/scene.json`` (a dict), or None when it is missing or
    not a JSON object."""
    try:
        scene = json.loads((Path(root) / SCENE_FILE).read_text())
    except (OSError, ValueError):
        return None
    return scene if isinstance(scene, dict) else None


# ----------------------------------------------------------------------------- writers


def directions_text(L: np.ndarray) -> str:
    """The text of a directions or positions file: one ``x y z`` line (9 decimals) per light."""
    return "".join(f"{x:.9f} {y:.9f} {z:.9f}\n" for x, y, z in np.asarray(L, dtype=np.float64).reshape(-1, 3))


def intensities_text(E: np.ndarray) -> str:
    """The text of an intensities file: one ``r g b`` line (9 significant digits) per light."""
    return "".join(f"{r:.9g} {g:.9g} {b:.9g}\n" for r, g, b in np.asarray(E, dtype=np.float64).reshape(-1, 3))


def write_filenames(root: Path, names) -> None:
    """``root/filenames.txt``: one image name a line, in light order."""
    write_text(Path(root) / FILENAMES_FILE, "".join(f"{n}\n" for n in names))


def write_light_directions(root: Path, L: np.ndarray) -> None:
    """``root/light_directions.txt`` from (m, 3) directions (camera frame)."""
    write_text(Path(root) / LIGHT_DIRECTIONS_FILE, directions_text(L))


def write_light_intensities(root: Path, E: np.ndarray) -> None:
    """``root/light_intensities.txt`` from (m, 3) RGB intensities."""
    write_text(Path(root) / LIGHT_INTENSITIES_FILE, intensities_text(E))


def write_light_positions(root: Path, P: np.ndarray) -> None:
    """``root/light_positions.txt`` from (m, 3) point-light positions (capture frame,
    origin at the camera's optical centre)."""
    write_text(Path(root) / LIGHT_POSITIONS_FILE, directions_text(P))


def write_intrinsics(root: Path, K: np.ndarray) -> None:
    """``root/intrinsics.txt`` from a pinhole camera's (3, 3) K (OpenCV convention)."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    write_text(Path(root) / INTRINSICS_FILE, "".join(" ".join(f"{v:.12g}" for v in row) + "\n" for row in K))


def write_mask(root: Path, mask: np.ndarray) -> None:
    """``root/mask.png`` from an (H, W) bool mask (0 / 255, 8-bit)."""
    from cnnps.io.images import write_png

    write_png(Path(root) / MASK_FILE, np.asarray(mask, dtype=bool).astype(np.uint8) * 255)


def write_normal_gt(root: Path, normals: np.ndarray) -> None:
    """``root/normal_gt.npy`` from (H, W, 3) normals (float32, camera frame)."""
    _save_npy(Path(root) / NORMAL_GT_FILE, np.asarray(normals, dtype=np.float32))


def write_depth_gt(root: Path, depth: np.ndarray) -> None:
    """``root/depth_gt.npy`` from (H, W) depth along the optical axis (float32, NaN outside)."""
    _save_npy(Path(root) / DEPTH_GT_FILE, np.asarray(depth, dtype=np.float32))


def _save_npy(path: Path, arr: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        np.save(tmp, arr)


def write_scene(root: Path, scene: dict) -> None:
    """``root/scene.json``: ``json.dumps(scene, indent=SCENE_INDENT) + "\\n"``."""
    write_text(Path(root) / SCENE_FILE, json.dumps(scene, indent=SCENE_INDENT) + "\n")


def write_image(path: Path, image: np.ndarray) -> None:
    """One image of a capture, by the name's suffix: ``.exr`` (float32 linear, RGB or
    grey) or ``.png`` (uint8 / uint16, RGB or grey); a ValueError for another suffix."""
    from cnnps.io.images import write_exr, write_png

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        write_exr(path, image)
    elif suffix == ".png":
        write_png(path, np.asarray(image))
    else:
        raise ValueError(f"{path.name}: images are written as .exr or .png, not {suffix or 'no suffix'}")
