"""CNN-PS as a normal solver (``method="cnn"``, :mod:`cnnps.ps.solver`).

Prepared once per capture (:meth:`NetworkSolver.prepare`): the checkpoint resolved (the
shipped model, its SHA-256 checked, when none is given), loaded onto its device, in the
precision ``precision`` asks for (``auto``: the probe's cached pick for this machine and
model, :func:`cnnps.models.precision_probe.choose_precision`, at the batch size the probe
found fastest unless ``batch_size`` is given). Per tile: each pixel's observation map
under K test-time rotations, averaged (:func:`cnnps.models.inference.rotated_normals`),
with missing observations left out of the map, each pixel's view turned to +z under a
pinhole camera, and, with the sparse fill on and shared lights, the virtual Lambertian
observations of :func:`cnnps.ps.sparse_fill.lambertian_fill`. The confidence: the rotation
spread of the K answers (regression models, K > 1) or the heat-map spread (heat-map
models, any K), over the lit share (:mod:`cnnps.ps.confidence`).

A patch model (``patch`` b > 1, spatial context) reads each tile from the capture's pixel
stack with its halo (:meth:`NetworkSolver.for_capture`,
:func:`cnnps.ps.patches.patch_read_range`) and gives each pixel its b x b patch of maps
under the K rotations (:func:`cnnps.ps.patches.capture_patches`: the training rule, cells
outside the mask all-zero maps), averaged as one map's answers are
(:func:`cnnps.models.inference.rotated_answers`); distant lights and an orthographic camera
only (docs/models.md, "A patch model in cnnps predict").

Its options, declared once in :class:`NetworkOptions`: ``model``, ``rotations``,
``device``, ``precision``, ``batch_size``, ``sparse_fill``, ``heatmap_decoding`` (how a
heat-map model's heat-maps become normals, :func:`cnnps.models.heatmap.decode_heatmaps`;
a regression model ignores it).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np

from cnnps.infra.errors import CnnpsError, ConfigError, InputError
from cnnps.infra.machine import Device
from cnnps.infra.options import Count, option
from cnnps.ps.solver import Solved, Solver, Tile
from cnnps.ps.sparse_fill import SparseFill

RATE_MIN_SECONDS = 5.0  # shorter runs say too little about the machine's speed
Precision = Literal["auto", "fp32", "bf16"]  # auto: measured per machine (cnnps.models.precision_probe)
HeatmapDecoding = Literal["window", "parabola"]  # cnnps.models.heatmap.DECODINGS


@dataclass(frozen=True)
class NetworkOptions:
    """The options of :class:`NetworkSolver` (``method="cnn"``), each declared once."""

    model: Path | None = option(None, "Weights (default: the shipped model).")
    rotations: Count = option(10, "Test-time rotations averaged.", metavar="K")
    device: Device = option("auto", "Where the network runs.")
    precision: Precision = option("auto", "auto: the fastest exact one here.")
    batch_size: Count | None = option(None, "Maps per network batch.", metavar="N")
    sparse_fill: SparseFill = option("auto", "Lambertian fill of sparse maps.")
    heatmap_decoding: HeatmapDecoding = option("window", "Heat-map models: how maps decode.")

def default_model_path() -> Path:
    """Where the shipped model lives: ``cnnps/models/weights/cnnps_default.pt``."""
    from cnnps.models.shipped import weights_path

    return weights_path()


def resolve_model(model) -> Path:
    """The checkpoint to run: ``model`` when it is a file (InputError otherwise; its SHA-256
    checked when it is one of the shipped files, such as ``cnnps_v5.pt``), else the shipped
    model, its SHA-256 checked (CnnpsError saying how to get one when absent)."""
    if model is not None:
        path = Path(model)
        if not path.is_file():
            raise InputError(path, "model file not found")
        from cnnps.models.shipped import verify_if_shipped

        return verify_if_shipped(path)
    path = default_model_path()
    if not path.is_file():
        raise CnnpsError(
            f"no model given and no shipped model at {path}: train one with "
            "`cnnps run-stage train` (or `dvc repro`) and pass --model data/train/model.pt, "
            "pass --model PATH to a checkpoint, or use --method lambertian"
        )
    from cnnps.models.shipped import verify_shipped

    return verify_shipped(path)  # checks the SHA-256 recorded next to it


def torch_device(device: str) -> str:
    """The torch device ``--device`` names (:func:`cnnps.models.devices.resolve_device`:
    ``auto`` = CUDA when available); a ConfigError naming the option when it cannot be had."""
    try:
        from cnnps.models.devices import resolve_device
    except ImportError as exc:  # pragma: no cover - torch is a dependency
        raise ConfigError(f"--method cnn needs PyTorch, which failed to import ({exc})") from exc
    try:
        return str(resolve_device(device))
    except CnnpsError as exc:
        raise ConfigError(f"--device {device}: {exc}") from None


def load_predictor(model_path: Path, device: str, precision: str, batch_size: int | None,
                   heatmap_decoding: str = "window"):
    """(MapPredictor, checkpoint meta, how the precision was chosen): the network prepared
    once for every tile (see the module docstring)."""
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import MapPredictor

    dev = torch_device(device)
    net, _config, meta = load_checkpoint(model_path, dev)  # InputError naming the file
    channels = getattr(net, "in_channels", 1)
    if channels != 1:  # the pixel stack holds grey values
        raise ConfigError(f"{model_path}: an RGB model ({channels} input channels); prediction and scoring "
                          "(`cnnps predict`, `cnnps score`, the eval stage) read grey values only: use a grey model")
    if precision == "auto":
        import torch

        from cnnps.infra.hashing import file_sha256
        from cnnps.models.precision_probe import choose_precision

        choice = choose_precision(net, torch.device(dev), file_sha256(model_path), batch_size)
        how = {"requested": "auto", "reason": choice.reason, "cached": choice.cached,
               "age_seconds": None if choice.age_seconds is None else round(choice.age_seconds, 1),
               "under_load": choice.under_load, "probe_seconds": choice.probe_seconds, "key": choice.key}
        precision = choice.precision
        how["threads"] = choice.threads
        if batch_size is None and choice.batch_size:
            batch_size = how["batch_size"] = choice.batch_size  # the pick's fastest batch
    else:
        how = {"requested": precision, "reason": f"--precision {precision} given"}
        if dev == "cpu":
            from cnnps.models.inference import set_cpu_threads

            how["threads"] = set_cpu_threads()  # every CPU the affinity allows
    predictor = MapPredictor(net, device=dev, precision=precision, batch_size=batch_size,
                             heatmap_decoding=heatmap_decoding)
    return predictor, meta, how


class CapturePixels(NamedTuple):
    """What a patch model reads a tile's neighbours from: ``stack`` (the
    :class:`cnnps.io.pixel_store.PixelStack` of the mask pixels), ``mask`` (H, W) bool and
    its :func:`cnnps.ps.patches.mask_row_starts`."""

    stack: object
    mask: np.ndarray
    row_starts: np.ndarray


class NetworkSolver(Solver):
    """CNN-PS per tile (see the module docstring)."""

    name = "cnn"
    Options = NetworkOptions

    def __init__(self, predictor, rotations: int, model_path: Path, meta: dict | None = None,
                 precision_how: dict | None = None, precision: str | None = None, sparse_fill: str = "auto"):
        self.predictor, self.rotations, self.model_path = predictor, int(rotations), Path(model_path)
        self.meta, self.precision_how, self.precision, self.sparse_fill = meta, precision_how, precision, sparse_fill
        self.pixels: CapturePixels | None = None  # a patch model's neighbours: set by for_capture

    @property
    def patch(self) -> int:
        """The model's patch size b (1: one pixel's map)."""
        return int(getattr(self.predictor, "patch", 1))

    def for_capture(self, stack, mask: np.ndarray) -> "NetworkSolver":
        """The solver for one pass over ``stack`` (the
        :class:`cnnps.io.pixel_store.PixelStack` of ``mask``'s pixels): a patch model's
        copy that reads each tile's neighbours from it; a per-pixel model itself."""
        if self.patch == 1:
            return self
        from cnnps.ps.patches import mask_row_starts

        bound = copy.copy(self)
        mask = np.asarray(mask, bool)
        bound.pixels = CapturePixels(stack, mask, mask_row_starts(mask))
        return bound

    @classmethod
    def check(cls, options: NetworkOptions) -> None:
        """The model file and the device, checked before any capture is read."""
        resolve_model(options.model)
        torch_device(options.device)

    @classmethod
    def prepare(cls, options: NetworkOptions) -> "NetworkSolver":
        model_path = resolve_model(options.model)
        predictor, meta, how = load_predictor(model_path, options.device, options.precision, options.batch_size,
                                              options.heatmap_decoding)
        return cls(predictor, options.rotations, model_path, meta, how, options.precision, options.sparse_fill)

    def quick(self) -> "NetworkSolver":
        """One rotation instead of K: the intermediate rounds under point lights."""
        if self.rotations == 1:
            return self
        quick = copy.copy(self)
        quick.rotations = 1
        return quick

    def fills(self, n_images: int, shared_lights: bool = True) -> bool:
        """Whether the sparse fill runs for ``n_images`` images (shared lights only)."""
        from cnnps.ps.sparse_fill import should_fill

        return shared_lights and should_fill(self.sparse_fill, n_images)

    def solve(self, tile: Tile, bar=None) -> Solved:
        from cnnps.models.inference import PIXEL_CHUNK, rotated_normals
        from cnnps.ps.confidence import heatmap_confidence, lit_share, network_confidence

        share = lit_share(tile.values, tile.missing)
        spread = np.zeros(tile.n, np.float32) if self.rotations > 1 or self.heatmap else None
        if self.patch > 1:
            N, filled = self._patch_normals(tile, bar, spread)
        else:
            I, lights = tile.values, tile.lights
            present = None if tile.missing is None else ~tile.missing
            filled = 0
            if self.fills(I.shape[1], lights.ndim == 2):
                from cnnps.ps.sparse_fill import lambertian_fill

                f = lambertian_fill(I, lights, light_mask=present, w=self.predictor.w)
                I, lights, present, filled = f.intensities, f.lights, f.light_mask, int(f.filled.sum())
            N = rotated_normals(self.predictor, I, lights, self.rotations, light_mask=present, progress=bar,
                                pixel_chunk=PIXEL_CHUNK, views=tile.views, spread=spread)
        N = np.asarray(N, dtype=np.float64)
        if N.shape != (tile.n, 3) or not np.all(np.isfinite(N)):
            raise CnnpsError(f"the model returned invalid normals (shape {N.shape} or NaN values)")
        confidence = heatmap_confidence if self.heatmap else network_confidence
        return Solved(N, {"filled": filled}, None if spread is None else confidence(spread, share))

    def _patch_normals(self, tile: Tile, bar, spread: np.ndarray | None) -> tuple[np.ndarray, int]:
        """((n, 3) float32 normals, pixels filled) of a patch model: each pixel's b x b
        patch under the K rotations (:func:`cnnps.ps.patches.capture_patches`, the tile read
        with its halo of neighbours), about ``PIXEL_CHUNK`` maps a chunk, answers averaged
        by :func:`cnnps.models.inference.rotated_answers`; ``spread`` filled as
        :func:`cnnps.models.inference.rotated_normals` fills it (docs/models.md)."""
        from cnnps.infra.prefetch import prefetched
        from cnnps.models.inference import PIXEL_CHUNK, rotated_answers
        from cnnps.ps.patches import capture_patches, patch_read_range
        from cnnps.ps.rotation import rotation_angles

        self._check_patch_tile(tile)
        stack, mask, row_starts = self.pixels
        b, w = self.patch, self.predictor.w
        start = int(row_starts[tile.rows[0]]) + int(np.count_nonzero(mask[tile.rows[0], :tile.cols[0]]))
        stop = start + tile.n
        if int(row_starts[tile.rows[-1]]) + int(np.count_nonzero(mask[tile.rows[-1], :tile.cols[-1]])) != stop - 1:
            raise ValueError("a patch model solves tiles of consecutive mask pixels (row-major)")
        first, last = patch_read_range(mask, start, stop, b, row_starts=row_starts)
        values, missing = stack.read(first, last)  # the tile and its halo, (last - first, m)
        lights, filled = tile.lights, 0
        if self.fills(values.shape[1]):  # each pixel's own fit: the halo's filled as the tile's would be
            from cnnps.ps.sparse_fill import lambertian_fill

            f = lambertian_fill(values, lights, light_mask=None if missing is None else ~missing, w=w)
            values, lights, missing = f.intensities, f.lights, ~f.light_mask
            filled = int(f.filled[start - first:stop - first].sum())
        angles = rotation_angles(self.rotations)
        chunk = max(1, PIXEL_CHUNK // (len(angles) * b * b))  # about PIXEL_CHUNK maps built at once
        starts = range(start, stop, chunk)

        def patches_of(s: int) -> np.ndarray:  # (K, n, b^2, w, w): the network's (b^2, w, w) inputs
            x = capture_patches(values, mask, lights, s, min(s + chunk, stop), b=b, w=w, angles=angles, first=first,
                                missing=missing, row_starts=row_starts)
            return x.reshape(x.shape[:2] + (b * b, w, w))

        N = np.empty((tile.n, 3), np.float32)
        for s, maps in zip(starts, prefetched(patches_of, starts, depth=1)):
            part = slice(s - start, s - start + maps.shape[1])
            N[part] = rotated_answers(self.predictor, maps, angles, progress=bar,
                                      spread=None if spread is None else spread[part])
        return N, filled

    def _check_patch_tile(self, tile: Tile) -> None:
        """ConfigError (one line naming the option and the model file) for what a patch
        model does not run under: near point lights, a pinhole camera; CnnpsError when no
        pixel stack was given (:meth:`for_capture`)."""
        b = self.patch
        if np.ndim(tile.lights) == 3:
            raise ConfigError(f"{self.model_path}: a patch model (patch={b}) needs distant lights; this capture has "
                              "near point lights (--light-model point): use --light-model directional or a model "
                              "with patch 1")
        if tile.views is not None:
            raise ConfigError(f"{self.model_path}: a patch model (patch={b}) needs an orthographic camera; this "
                              "capture has a pinhole one (--camera-model pinhole, or the capture's intrinsics): use "
                              "--camera-model orthographic or a model with patch 1")
        if self.pixels is None:
            raise CnnpsError(f"{self.model_path}: a patch model (patch={b}) reads each tile's neighbours from the "
                             "capture's pixel stack: prepare the solver with for_capture(stack, mask)")

    @property
    def heatmap(self) -> bool:
        """Whether the model has a heat-map head (its confidence is the heat-map spread)."""
        from cnnps.models.heads import REGRESSION, is_heatmap

        return is_heatmap(getattr(self.predictor, "head", REGRESSION))

    def confidence_record(self) -> dict | None:
        if self.heatmap:
            return {"measure": "1 / (1 + u / 6.5 deg), u = the heat-map spread (its windowed second moment, deg, "
                               "mean over the K rotations) / the lit share"}
        if self.rotations == 1:
            return None  # one answer a pixel: no spread to measure
        return {"measure": "1 / (1 + u / 3 deg), u = the spread of the K rotated answers (deg) / the lit share"}

    def progress_bar(self, n_pixels: int):
        from cnnps.infra.progress import progress_bar

        return progress_bar(total=n_pixels * self.rotations, unit="map", unit_scale=True, desc="cnn-ps")

    def warnings(self, n_images: int) -> list[str]:
        """One line when the capture has fewer images than the model's sparsest training maps."""
        from cnnps.models.shipped import trained_min_lights

        fewest = trained_min_lights(self.model_path, self.meta)
        if fewest is None or n_images >= fewest:
            return []
        how = ("the Lambertian fill is on: see --sparse-fill" if self.fills(n_images)
               else "try --sparse-fill on, --method lambertian, or a model trained with sparse lights")
        return [f"{n_images} images, but this model was trained on maps of {fewest} or more lights: "
                f"expect larger errors ({how})"]

    def record(self, counts: dict[str, int], n_images: int, shared_lights: bool) -> dict:
        return {"model": str(self.model_path), "rotations": self.rotations,
                "precision": getattr(self.predictor, "precision", self.precision),
                "precision_choice": self.precision_how,
                "sparse_fill": {"mode": self.sparse_fill, "used": self.fills(n_images, shared_lights),
                                "filled_pixels": int(counts.get("filled", 0))},
                "shadow_threshold": None,
                **({"heatmap_decoding": self.predictor.heatmap_decoding} if self.heatmap else {})}

    def finish(self, n_pixels: int, seconds: float) -> None:
        """Tell the precision probe how fast this run went (maps per second), so a cached
        choice far slower than its probe is measured again next time
        (:func:`cnnps.models.precision_cache.report_rate`); only for ``precision="auto"``."""
        how = self.precision_how or {}
        if how.get("requested") != "auto" or not how.get("key") or seconds < RATE_MIN_SECONDS:
            return
        from cnnps.models.precision_cache import report_rate

        rate = n_pixels * self.rotations / seconds
        how["run_maps_per_second"] = round(rate, 1)
        how["cache_dropped"] = bool(report_rate(how["key"], rate))
