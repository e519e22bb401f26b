"""The masked pixels of a capture, stored once, read back in tiles of pixels.

Per-pixel photometric stereo needs, for each pixel, its value under every light; images
come one light at a time. Holding the whole stack (m x H x W float32) costs
96 x 12 MP x 4 B = 4.6 GB for a 12-megapixel capture, and OpenCV cannot read a band of
rows of a PNG or JPEG, so ``cnnps predict`` works in two passes:

1. :func:`build_pixel_stack` reads every image ONCE (a few at a time, on threads), keeps
   only its mask pixels' grey values and saturation flags
   (:meth:`cnnps.io.capture.Capture.read_pixels`) and writes them into a
   :class:`PixelStack`;
2. the caller reads tiles of consecutive mask pixels (row-major order, so a tile is a
   band of image rows) with :meth:`PixelStack.read`, each as a (n, m) array.

Layout: image-major, one float32 row of P values per image (``m x P``), exactly what
pass 1 produces, so it is written with plain sequential writes; a tile is m contiguous
reads of n values (n = 65,536 by default: 256 KB each, full disk speed). float32 keeps the
values bit for bit (a float16 store would halve the disk but change the answers).
Saturation flags are a second plane of one byte per observation, written (and read) only
for the images that have a saturated observation at all.

Where: in memory when the stack is at most ``memory_limit`` bytes (default
``DEFAULT_MEMORY_LIMIT`` = 256 MiB: DiLiGenT objects, small captures), else in files
``pixels.f32`` (and ``saturated.u8``) in a private temporary folder (under
``scratch_dir``; deleted on :meth:`PixelStack.close`, also after an error). The files are
read with explicit ``readinto`` calls, not ``np.memmap``: pages of a mapped file count in
the process's resident memory until unmapped, which would grow with the image again.

Peak memory of the two passes: pass 1 holds ``read_workers`` decoded images (capped by
:data:`cnnps.io.capture.DECODE_BUDGET_BYTES`) plus one image's mask pixels per worker;
pass 2 holds one tile.
"""

from __future__ import annotations

import shutil
import tempfile
import threading
from pathlib import Path

import numpy as np

from cnnps.io.capture import SATURATION_LEVEL, for_each_image

DEFAULT_MEMORY_LIMIT = 256 * 2**20  # bytes of stack kept in memory; larger stacks go to disk
ITEM = 4  # float32


def _write_all(f, offset: int, data: memoryview) -> None:
    f.seek(offset)
    done = 0
    while done < len(data):
        done += f.write(data[done:])


def _read_all(f, offset: int, buf: memoryview, name) -> None:
    f.seek(offset)
    got = 0
    while got < len(buf):
        r = f.readinto(buf[got:])
        if not r:
            raise OSError(f"{name}: unexpected end of file")
        got += r


class PixelStack:
    """(m, P) float32 values and saturation flags, image-major, in memory or in files.

    Use as a context manager (or call :meth:`close`): the files and their folder go away.
    ``write(k, ...)`` may be called from several threads at once.
    """

    def __init__(self, m: int, P: int, scratch_dir: str | Path | None = None, on_disk: bool = False):
        self.m, self.P = int(m), int(P)
        self.kinds: dict[str, int] = {}  # stored pixel type -> number of images (build_pixel_stack)
        self._counts: dict[int, int] = {}  # image -> its saturated observations (images with any)
        self._mem_flags: dict[int, np.ndarray] = {}  # in memory: image -> (P,) bool flags
        self._lock = threading.Lock()
        self._dir: Path | None = None
        self._values = self._flags = None
        self._array: np.ndarray | None = None
        if not on_disk:
            self._array = np.empty((self.m, self.P), dtype=np.float32)
            return
        if scratch_dir is not None:
            Path(scratch_dir).mkdir(parents=True, exist_ok=True)
        self._dir = Path(tempfile.mkdtemp(prefix=".cnnps-pixels-", dir=None if scratch_dir is None else str(scratch_dir)))
        try:
            self.path = self._dir / "pixels.f32"
            self._values = open(self.path, "w+b", buffering=0)
            self._values.truncate(self.m * self.P * ITEM)  # sparse until written
        except BaseException:
            self.close()
            raise

    @property
    def on_disk(self) -> bool:
        return self._dir is not None

    @property
    def nbytes(self) -> int:
        return self.m * self.P * ITEM

    def write(self, k: int, values: np.ndarray, saturated: np.ndarray | None = None) -> None:
        """Store image ``k``'s (P,) float32 values and (P,) bool saturation flags (None: none)."""
        values = np.ascontiguousarray(values, dtype=np.float32)
        if values.shape != (self.P,):
            raise ValueError(f"expected {self.P} values for image {k}, got {values.shape}")
        if not 0 <= k < self.m:
            raise IndexError(f"image {k} out of range 0..{self.m - 1}")
        flags = None
        if saturated is not None:
            flags = np.ascontiguousarray(saturated, dtype=bool)
            if flags.shape != (self.P,):
                raise ValueError(f"expected {self.P} flags for image {k}, got {flags.shape}")
            if not flags.any():
                flags = None
        with self._lock:
            if self._array is not None:
                self._array[k] = values
                if flags is not None:
                    self._mem_flags[k] = flags
                else:
                    self._mem_flags.pop(k, None)
            else:
                _write_all(self._values, k * self.P * ITEM, memoryview(values).cast("B"))
                if flags is not None:
                    if self._flags is None:
                        self._flags = open(self._dir / "saturated.u8", "w+b", buffering=0)
                        self._flags.truncate(self.m * self.P)
                    _write_all(self._flags, k * self.P, memoryview(flags.view(np.uint8)))
            if flags is None:
                self._counts.pop(k, None)
            else:
                self._counts[k] = int(flags.sum())

    @property
    def n_saturated(self) -> int:
        """Observations flagged saturated, over all images."""
        return sum(self._counts.values())

    def read(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Pixels ``start:stop``: ((n, m) float32 values, (n, m) bool saturated or None
        when none of them is), both fresh C-ordered arrays."""
        start, stop = max(0, int(start)), min(self.P, int(stop))
        n = max(0, stop - start)
        flagged = sorted(self._counts)
        sat = None
        if self._array is not None:
            values = np.ascontiguousarray(self._array[:, start:stop].T)
            if flagged:
                rows = np.zeros((self.m, n), dtype=bool)
                for k in flagged:
                    rows[k] = self._mem_flags[k][start:stop]
                sat = np.ascontiguousarray(rows.T)
        else:
            rows = np.empty((self.m, n), dtype=np.float32)
            flags = np.zeros((self.m, n), dtype=bool) if flagged else None
            if n:
                with self._lock:
                    for k in range(self.m):
                        _read_all(self._values, (k * self.P + start) * ITEM, memoryview(rows[k]).cast("B"), self.path)
                    for k in flagged:
                        _read_all(self._flags, k * self.P + start, memoryview(flags[k].view(np.uint8)), self._dir)
            values = np.ascontiguousarray(rows.T)
            if flags is not None:
                sat = np.ascontiguousarray(flags.T)
        if sat is not None and not sat.any():
            sat = None
        return values, sat

    def tiles(self, tile_pixels: int):
        """(start, stop) ranges covering 0..P in steps of ``tile_pixels``."""
        step = max(1, int(tile_pixels))
        for s in range(0, self.P, step):
            yield s, min(s + step, self.P)

    def close(self) -> None:
        for f in (self._values, self._flags):
            if f is not None:
                f.close()
        self._values = self._flags = None
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None
        self._array = None
        self._mem_flags = {}

    def __enter__(self) -> "PixelStack":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def build_pixel_stack(
    capture,
    scratch_dir: str | Path | None = None,
    memory_limit: int = DEFAULT_MEMORY_LIMIT,
    saturation: float | None = SATURATION_LEVEL,
    workers: int | None = None,
    progress: bool = False,
) -> PixelStack:
    """Pass 1: read every image of a scanned ``capture`` once into a new PixelStack.

    capture: a :class:`cnnps.io.capture.Capture` from ``scan_capture`` (images read
        from their files), or one holding its images (``load_capture``, or made in memory).
    scratch_dir: where the temporary folder goes when the stack is larger than
        ``memory_limit`` bytes (None: the system's temporary folder).
    saturation: the fraction of an integer type's maximum at and above which an
        observation is flagged saturated (``cnnps.io.capture.SATURATION_LEVEL`` = 0.99);
        None flags nothing.
    Records ``n_saturated`` and ``kinds`` (pixel types seen). The stack is closed (its
    files deleted) if reading fails.
    """
    level = None if saturation is None else float(saturation)
    P, m = capture.n_pixels, capture.n_images
    stack = PixelStack(m, P, scratch_dir=scratch_dir, on_disk=m * P * ITEM > int(memory_limit))
    kinds = [""] * m
    try:

        def work(k: int) -> None:
            pix = capture.read_pixels(k, saturation=level)
            stack.write(k, pix.values, pix.saturated)
            kinds[k] = pix.kind

        for_each_image(capture, work, workers=workers, progress=progress, desc=f"reading {capture.name}")
    except BaseException:
        stack.close()
        raise
    for kind in kinds:
        stack.kinds[kind] = stack.kinds.get(kind, 0) + 1
    return stack


__all__ = ["DEFAULT_MEMORY_LIMIT", "PixelStack", "build_pixel_stack"]
