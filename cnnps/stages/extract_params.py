"""The extract stage's settings (:class:`Params`, the ``extract`` section of params.yaml):
the map width and its rows, the light-subset rule, the realism of the shards' maps and
the layout of the output, each field checked from its declaration when built."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Annotated, Literal, get_args

import numpy as np

from cnnps.infra.errors import ConfigError
from cnnps.infra.executor import ExecutorParams
from cnnps.infra.options import Count, Range, check_fields
from cnnps.io.observation_store import OBSERVATION_FORMAT
from cnnps.synth.light_subsets import RULE, check_light_subsets

FORMAT_VERSION = 1  # bump when the rows written for the same inputs change
Fraction = Annotated[float, Range(ge=0.0, le=1.0)]  # a share or strength in [0, 1]
Layout = Literal["maps", "observations"]  # what a scene becomes: shards of maps, or per-pixel observations
LAYOUTS = get_args(Layout)


@dataclass(frozen=True)
class Params:
    """``extract:`` in params.yaml. A field declared with a type (a range, a choice) is
    checked from its declaration (:func:`cnnps.infra.options.check_fields`); the light-subset
    settings by :func:`cnnps.synth.light_subsets.check_light_subsets`; the rest below."""

    w: Annotated[int, Range(ge=4, le=256)] = 32
    # the light-subset rule (module docstring, steps 1 and 2): cnnps.synth.light_subsets declares it
    min_lights: int = RULE.min_lights
    max_lights: int = RULE.max_lights
    cone_min_deg: float = RULE.cone_min_deg
    cone_max_deg: float = RULE.cone_max_deg
    rotations: Annotated[int, Range(ge=1, le=127)] = 10
    ambient_max: Fraction = 0.0  # per-pixel ambient offset a ~ U(0, ambient_max), times the pixel's brightest light
    # sensor and capture realism (module docstring, step 4; each 0 / empty = off)
    intensity_error: Fraction = 0.0  # per scene and light: intensity factor 1 + e, e ~ N(0, intensity_error)
    direction_error_deg: Annotated[float, Range(ge=0.0, le=90.0)] = 0.0  # per scene and light: written direction turned by |N(0, this)| degrees
    black_level_max: Fraction = 0.0  # per scene: offset b * E, b ~ U(0, black_level_max), E the scene's full scale
    noise_max: Fraction = 0.0  # per pixel: read and shot noise levels ~ U(0, noise_max) x the pixel's brightest value
    saturated_fraction_max: Fraction = 0.0  # per scene: clip at the (1 - f) quantile of pixel peaks, f ~ U(0, this)
    quantize_bits: tuple[int, ...] = ()  # per scene: a bit depth drawn from these, grid E / (2^bits - 1)
    # sparse light subsets (module docstring, step 2): a pixel is sparse with this probability
    sparse_fraction: Fraction = 0.0
    sparse_min_lights: int = RULE.sparse_min_lights  # sparse k is log-uniform in [sparse_min_lights, min_lights)
    pixels_per_scene: Annotated[int, Range(ge=0)] = 0  # 0 = every foreground pixel
    val_fraction: Annotated[float, Range(ge=0.0, lt=1.0)] = 0.1
    val_scenes: tuple[str, ...] = ()  # explicit validation scenes (or view ids); overrides val_fraction
    seed: int = 0
    rows_per_group: Count = 8192
    rows_per_shard: Count = 262144
    chunk_pixels: Count = 2048
    # how scenes are run: params.yaml's shared ``executor`` section (None = in this process);
    # ``workers`` overrides executor.workers when set (1 = in this process, 0 = one per core)
    executor: ExecutorParams | None = None
    workers: Annotated[int, Range(ge=0)] | None = None
    # where shards + manifest go: a path or an fsspec URL (s3://, gs://, file://, memory://);
    # None = data_dir/extract. The train stage reads the same place (train.data.shards).
    output: str | None = None
    # what a scene becomes: "maps" (the shards) or "observations" (one file of per-pixel
    # observations, cnnps.io.observation_store; pixels_per_scene and the map params unused)
    layout: Layout = "maps"
    # which rendered scenes the stage reads: fnmatch patterns of scene ids
    # (``<source>-<view>-<hash>``, e.g. ["*-0-*", "*-1-*"] = views 0 and 1); empty = every scene
    scenes: tuple[str, ...] = ()

    def __post_init__(self):
        check_fields(self, "extract.")
        check_light_subsets("extract", self, self.sparse_fraction)
        bits = tuple(self.quantize_bits)
        if not all(isinstance(b, (int, np.integer)) and not isinstance(b, bool) and 1 <= b <= 16 for b in bits):
            raise ConfigError(f"extract.quantize_bits must be bit depths in [1, 16], got {list(bits)}")
        object.__setattr__(self, "quantize_bits", tuple(sorted({int(b) for b in bits})))
        if self.output is not None and (not isinstance(self.output, str) or not self.output.strip()):
            raise ConfigError(f"extract.output must be a folder path or URL, got {self.output!r}")
        object.__setattr__(self, "val_scenes", tuple(self.val_scenes))
        patterns = [self.scenes] if isinstance(self.scenes, str) else list(self.scenes)
        bad = [p for p in patterns if not isinstance(p, str) or not p.strip()]
        if bad:
            raise ConfigError(f"extract.scenes must be a list of scene-id patterns, got {bad[0]!r}")
        object.__setattr__(self, "scenes", tuple(sorted(set(patterns))))

    def row_key(self) -> dict:
        """The params that change the rows of a scene (not the split, not parallelism)."""
        if self.layout == "observations":  # the rows' params are the loader's
            return {"layout": self.layout, "format": FORMAT_VERSION, "observation_format": OBSERVATION_FORMAT}
        d = self.manifest_params()
        for k in ("val_fraction", "val_scenes", "scenes"):  # which scenes, not their rows
            d.pop(k, None)
        d["format"] = FORMAT_VERSION
        return d

    def manifest_params(self) -> dict:
        """The params recorded in the manifest: not where or how the stage ran."""
        d = asdict(self)
        for k in ("executor", "workers", "output"):
            d.pop(k)
        for k, default in OMITTED_AT_DEFAULT.items():  # absent = default: the keys of format 1
            if d[k] == default:
                d.pop(k)
        if not self.sparse_fraction:  # no sparse pixels: their size has no effect on the rows
            d.pop("sparse_min_lights", None)
        return d


# Params outside format 1's keys: left out of manifest_params() and row_key() at these
# (their "off") values, so a Params that leaves them alone has format 1's cache keys and
# manifest.
OMITTED_AT_DEFAULT = {
    "ambient_max": 0.0,
    "intensity_error": 0.0,
    "direction_error_deg": 0.0,
    "black_level_max": 0.0,
    "noise_max": 0.0,
    "saturated_fraction_max": 0.0,
    "quantize_bits": (),
    "sparse_fraction": 0.0,
    "sparse_min_lights": RULE.sparse_min_lights,
    "layout": "maps",
    "scenes": (),
}
