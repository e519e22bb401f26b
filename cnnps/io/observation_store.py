"""Per-pixel observations of a rendered scene: one file a scene, the input of patch training.

The extract stage's ``layout: observations`` writes, instead of maps, each scene's mask
pixels with their raw values under all m lights, so a loader can build any pixel's map
(and its neighbours' maps: spatial patches, :mod:`cnnps.ps.patches`) at training time,
with one copy of the data rather than one per rotation and per patch position.

File ``obs-<scene_id>.cnnobs`` (:func:`observation_file_name`), little-endian:

- 8 bytes magic ``CNNPSOBS``, then a uint64 ``n``, then ``n`` bytes of UTF-8 JSON, the
  header: ``format`` (1), ``scene``, ``scene_key`` (the render key), ``height``,
  ``width``, ``lights`` (m), ``pixels`` (P), ``centres`` (C) and ``arrays``:
  name -> ``{"dtype", "shape", "offset"}`` (offset from the file's start, a multiple of
  64);
- the arrays, each C-contiguous at its offset (zero bytes between them):

  ===========  ===========  ================================================================
  ``values``   (P, m) <f2   grey value of each mask pixel under each light, divided by the
                            light's intensity (:meth:`cnnps.io.capture.Capture.pixel_intensities`),
                            rounded to float16
  ``lights``   (m, 3) <f8   unit light directions as the capture folder holds them
  ``normals``  (P, 3) <f4   unit ground-truth normal (0 where the render has none)
  ``rows``     (P,) <i4     image row of the pixel (row 0 on top)
  ``cols``     (P,) <i4     image column
  ``centre``   (P,) |b1     the pixel may be a sample's centre: a finite ground-truth
                            normal and at least one positive value
  ===========  ===========  ================================================================

  Pixels are the mask's, in row-major order (the order of
  :class:`cnnps.io.pixel_store.PixelStack`): every mask pixel is a neighbour a patch can
  use, only ``centre`` pixels are samples. Frame: x right, y up, z toward the camera.

The bytes of a file depend only on its inputs (no time stamp): a rerun writes the same
file. Files are written under a temporary name and renamed when whole
(:func:`cnnps.infra.storage.write_bytes`); :func:`write_observations` returns the size
and SHA-256 that the scene marker and ``manifest.json`` record, and
:func:`verify_observations` checks a manifest's files against them (one line naming a
damaged file). float16 keeps 11 significant bits: a relative rounding of at most 2**-11 on each
value, below a rendered image's noise; a value above float16's largest (65504) or not
finite is refused when written.

Example::

    rec = write_observations(out_dir, "scene1", values, lights, normals, rows, cols, (H, W), scene_key=k)
    obs = read_observations(observation_path(out_dir, "scene1"))
    obs.values.shape   # (P, m) float16
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cnnps.infra import storage
from cnnps.infra.errors import InputError
from cnnps.infra.hashing import bytes_sha256
from cnnps.io.shards import MANIFEST, shard_path, verify_shards

OBSERVATION_FORMAT = 1
MAGIC = b"CNNPSOBS"
SUFFIX = ".cnnobs"
ALIGN = 64
FLOAT16_MAX = float(np.finfo(np.float16).max)
ARRAYS = {  # name -> stored dtype
    "values": np.dtype("<f2"),
    "lights": np.dtype("<f8"),
    "normals": np.dtype("<f4"),
    "rows": np.dtype("<i4"),
    "cols": np.dtype("<i4"),
    "centre": np.dtype("|b1"),
}


def observation_file_name(scene_id: str) -> str:
    return f"obs-{scene_id}{SUFFIX}"


def observation_path(out_dir: str | Path, scene_id: str) -> Path | str:
    """``out_dir/obs-<scene_id>.cnnobs``: a Path for a local folder, a URL string otherwise."""
    return shard_path(out_dir, observation_file_name(scene_id))


@dataclass(frozen=True)
class SceneObservations:
    """One scene's stored observations (shapes in the module docstring)."""

    scene: str
    scene_key: str
    height: int
    width: int
    values: np.ndarray
    lights: np.ndarray
    normals: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    centre: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: the pixels stored."""
        out = np.zeros((self.height, self.width), bool)
        out[self.rows, self.cols] = True
        return out

    def index_image(self) -> np.ndarray:
        """(H, W) int32: each stored pixel's row in ``values``, -1 elsewhere."""
        out = np.full((self.height, self.width), -1, np.int32)
        out[self.rows, self.cols] = np.arange(len(self.rows), dtype=np.int32)
        return out


def encode_observations(
    scene: str,
    values: np.ndarray,
    lights: np.ndarray,
    normals: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    size: tuple[int, int],
    *,
    scene_key: str = "",
) -> tuple[bytes, dict]:
    """The bytes of one observation file and its header.

    values (P, m) float (mask pixels, row-major), lights (m, 3), normals (P, 3) (rows of
    zeros, NaN or a norm below 0.5: no ground truth, never a centre), rows / cols (P,) the
    pixels, size (H, W). ValueError on shapes that disagree, a pixel order that is not
    row-major, or a value that is not finite or outside float16's range."""
    values = np.asarray(values)
    P, m = values.shape
    H, W = (int(s) for s in size)
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    lights = np.asarray(lights, np.float64)
    normals = np.asarray(normals, np.float64)
    if lights.shape != (m, 3) or normals.shape != (P, 3) or rows.shape != (P,) or cols.shape != (P,):
        raise ValueError(f"shapes disagree: values {values.shape}, lights {lights.shape}, normals {normals.shape}, "
                         f"rows {rows.shape}, cols {cols.shape}")
    if P and not (rows.min() >= 0 and rows.max() < H and cols.min() >= 0 and cols.max() < W):
        raise ValueError(f"pixels outside the {H} x {W} image")
    flat = rows * W + cols
    if P > 1 and not (np.diff(flat) > 0).all():
        raise ValueError("pixels must be distinct and in row-major order")
    if P and m and not (np.isfinite(values).all() and np.abs(values).max() <= FLOAT16_MAX):
        raise ValueError(f"values must be finite and within float16's range (+-{FLOAT16_MAX:g})")
    norm = np.linalg.norm(normals, axis=1)
    has_normal = np.isfinite(norm) & (norm > 0.5)
    unit = np.zeros((P, 3), np.float32)
    unit[has_normal] = normals[has_normal] / norm[has_normal, None]
    centre = has_normal & (values > 0).any(axis=1) if m else np.zeros(P, bool)
    data = {"values": values, "lights": lights, "normals": unit, "rows": rows, "cols": cols, "centre": centre}
    header = {"format": OBSERVATION_FORMAT, "scene": scene, "scene_key": scene_key, "height": H, "width": W,
              "lights": int(m), "pixels": int(P), "centres": int(centre.sum()), "arrays": {}}
    blobs = {name: np.ascontiguousarray(data[name], dtype=dt).tobytes() for name, dt in ARRAYS.items()}
    start = 0
    while True:  # the header's length depends on the offsets it lists: repeat until they fit
        offset = start
        for name, dt in ARRAYS.items():
            header["arrays"][name] = {"dtype": dt.str, "shape": list(np.shape(data[name])), "offset": offset}
            offset = _aligned(offset + len(blobs[name]))
        head = _header_bytes(header)
        if _aligned(len(MAGIC) + 8 + len(head)) <= start:
            break
        start = _aligned(len(MAGIC) + 8 + len(head))
    out = bytearray(MAGIC + struct.pack("<Q", len(head)) + head)
    for name in ARRAYS:
        out += bytes(header["arrays"][name]["offset"] - len(out))
        out += blobs[name]
    return bytes(out), header


def _header_bytes(header: dict) -> bytes:
    return json.dumps(header, sort_keys=True, separators=(",", ":")).encode()


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def write_observations(out_dir: str | Path, scene: str, values, lights, normals, rows, cols, size, *,
                       scene_key: str = "") -> dict:
    """Write ``obs-<scene>.cnnobs`` into ``out_dir`` (a path or an fsspec URL) atomically
    (arguments: :func:`encode_observations`). Returns its record for the scene marker:
    ``{"file", "rows" (centres), "pixels", "lights", "bytes", "sha256"}``."""
    data, header = encode_observations(scene, values, lights, normals, rows, cols, size, scene_key=scene_key)
    storage.write_bytes(observation_path(out_dir, scene), data)
    return {"file": observation_file_name(scene), "rows": header["centres"], "pixels": header["pixels"],
            "lights": header["lights"], "bytes": len(data), "sha256": bytes_sha256(data)}


def write_capture_observations(out_dir: str | Path, scene: str, capture, *, scene_key: str = "",
                               clip_fraction: float = 0.0) -> dict:
    """:func:`write_observations` of a :class:`cnnps.io.capture.Capture` with ground-truth
    normals (its mask pixels' grey values, lights, normals).

    Finite values above float16's largest (65504) are clipped to it, as a saturating sensor
    would, when they are at most ``clip_fraction`` of the capture's values (a render's rare
    firefly), and the record gains ``"clipped_values"``, their count. More of them (an
    exposure far off), or any value that is not finite, raises InputError naming the
    capture folder. The default 0 clips nothing.

    Example: ``write_capture_observations(out, "s00", load_capture(folder), clip_fraction=1e-4)``."""
    rows, cols = np.nonzero(capture.mask)
    values = capture.pixel_intensities()
    high = values > FLOAT16_MAX  # NaN compares False: it is refused below
    clipped = int(high.sum())
    if clipped and clipped <= clip_fraction * values.size:
        values = np.where(high, np.float32(FLOAT16_MAX), values)
    elif clipped:
        raise InputError(capture.root, f"cannot store its observations: {clipped} of {values.size} "
                         f"values ({100 * clipped / values.size:.3g}%) above float16's range (+-{FLOAT16_MAX:g}), more "
                         f"than the {100 * clip_fraction:.3g}% clipped as fireflies; check its exposure")
    try:
        record = write_observations(out_dir, scene, values, capture.lights, capture.normal_gt[rows, cols], rows,
                                    cols, capture.mask.shape, scene_key=scene_key)
    except ValueError as exc:
        raise InputError(capture.root, f"cannot store its observations: {exc}") from None
    if clipped:
        record["clipped_values"] = clipped
    return record


def read_observations(path: str | Path) -> SceneObservations:
    """The arrays of one observation file (read whole). A file that is not one, or is cut
    short, raises InputError naming it."""
    data = storage.read_bytes(path)
    bad = f"not a whole observation file; {_FIX}"
    if len(data) < len(MAGIC) + 8 or data[: len(MAGIC)] != MAGIC:
        raise InputError(str(path), bad)
    (n,) = struct.unpack("<Q", data[len(MAGIC) : len(MAGIC) + 8])
    try:
        header = json.loads(data[len(MAGIC) + 8 : len(MAGIC) + 8 + n])
        arrays = {}
        for name, dt in ARRAYS.items():
            spec = header["arrays"][name]
            shape = tuple(int(s) for s in spec["shape"])
            count = int(np.prod(shape))
            if np.dtype(spec["dtype"]) != dt or spec["offset"] + count * dt.itemsize > len(data):
                raise ValueError(name)
            arrays[name] = np.frombuffer(data, dt, count, spec["offset"]).reshape(shape)
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(str(path), bad) from exc
    if header.get("format") != OBSERVATION_FORMAT:
        raise InputError(str(path), f"observation format {header.get('format')!r}, this cnnps reads "
                         f"{OBSERVATION_FORMAT}; {_FIX}")
    return SceneObservations(
        scene=str(header["scene"]), scene_key=str(header.get("scene_key", "")), height=int(header["height"]),
        width=int(header["width"]), values=arrays["values"], lights=arrays["lights"].astype(np.float64),
        normals=arrays["normals"], rows=arrays["rows"], cols=arrays["cols"], centre=arrays["centre"],
    )


_FIX = "rerun `cnnps run-stage extract` (it rewrites the damaged scenes)"


def manifest_observations(extract_dir: str | Path, manifest: dict, split: str) -> list[tuple[Path | str, dict]]:
    """(path, record) of every observation file of one split ('train' or 'val'), in
    manifest order; a manifest of maps raises InputError."""
    if manifest.get("layout", "maps") != "observations":
        raise InputError(str(shard_path(extract_dir, MANIFEST)),
                         "holds observation maps, not per-pixel observations (extract.layout: observations)")
    return [(shard_path(extract_dir, s["file"]), s) for s in manifest["shards"] if s["split"] == split]


def verify_observations(extract_dir: str | Path, manifest: dict, splits: tuple[str, ...] = ("train", "val")) -> int:
    """Check every observation file of ``splits`` against its recorded size and SHA-256
    (:func:`cnnps.io.shards.verify_shards`); the first mismatch raises InputError naming
    the file. Returns the bytes checked."""
    for split in splits:
        manifest_observations(extract_dir, manifest, split)  # a manifest of maps: one line
    return verify_shards(extract_dir, manifest, splits, fix=_FIX)
