"""The eval stage's settings (:class:`Params`, the ``eval`` section of params.yaml) and its
rigs (:class:`Rig`: a pinhole camera and near point lights beside the orthographic
test set), each checked from its declaration when built."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

from cnnps.infra.errors import ConfigError
from cnnps.infra.machine import Device
from cnnps.infra.options import Count, Range, UnitFraction, check_fields
from cnnps.ps.sparse_fill import SparseFill
from cnnps.stages.eval_testset import (
    SPHERE,
)
from cnnps.synth.bsdf import MaterialRanges, checked_categories, checked_ranges


@dataclass(frozen=True)
class Rig:
    """The rig of the test set's twins (``eval.rig``): a pinhole camera with ``fov_deg``
    across the image and, with ``light_distance`` d, point lights d object radii from the
    object's centre (None: the distant lights of the orthographic captures). The default,
    3 radii, is 1.5 object sizes: an LED ring or dome as near as rigs build them. ``size``:
    the twins' image size; None renders them so that the object spans as many pixels as
    in its orthographic capture (:func:`cnnps.stages.eval_testset.twin_size`), so that
    ``rig_minus_ortho`` measures the rig and not a smaller object."""

    fov_deg: float = 40.0
    light_distance: float | None = 3.0
    size: int | None = None  # pixels across; None: the object spans as many as in the orthographic capture

    def __post_init__(self):
        if self.size is not None and self.size < 8:
            raise ConfigError(f"eval.rig.size must be >= 8 pixels (or null), got {self.size}")
        if not 0 < self.fov_deg < 120:
            raise ConfigError(f"eval.rig.fov_deg must be in (0, 120), got {self.fov_deg}")
        if self.light_distance is not None and not 1 < self.light_distance < 5:
            raise ConfigError(f"eval.rig.light_distance must be in (1, 5) object radii, got {self.light_distance}")

    @property
    def suffix(self) -> str:
        return f"fov{self.fov_deg:g}" + ("" if self.light_distance is None else f"-point{self.light_distance:g}")


@dataclass(frozen=True)
class Params:
    """Parameters of the eval stage (``eval:`` in params.yaml).

    ``test_shapes``: ``sphere`` and/or procedural kinds (:data:`cnnps.synth.procedural.PROCEDURAL_KINDS`);
    ``synthetic: false`` skips the synthetic test set (real captures only).
    ``categories``: the test set's material categories; ``ranges``: their BSDF ranges, a
    :class:`cnnps.synth.bsdf.MaterialRanges` or per-category overrides of the defaults as
    ``materials.ranges`` takes them (``{"metallic": {"roughness": [0.1, 0.5]}}``); the
    test set's own, not ``materials.ranges``: editing what training draws from leaves the
    yardstick as it is.
    ``real_captures``: capture folders (DiLiGenT layout) also scored; without ground
    truth only their pictures are made. ``real_subsets``: image counts n; each real
    capture is scored again from n of its images, drawn by the seeded rule of
    :func:`cnnps.io.capture.subset_drop` (named ``<capture>-<n>``).
    ``real_exclude_from_mean``: folder names of real captures scored and reported but left
    out of ``summary_real`` / ``summary_real_subsets`` (e.g. a capture kept for reference
    beside a group that is averaged). ``real_pixels``: score each real capture (and its
    subsets) on a seeded random sample of that many of its mask pixels, the same pixels for
    every model and subset (:func:`pixel_sample`; 0 = every pixel): a quick, paired
    comparison of checkpoints, not the benchmark's number. ``saturated``: "exclude" leaves saturated observations
    out, as ``cnnps predict`` does by default; "keep" uses them as stored. ``precision``:
    the network's ("auto": the measured pick of ``cnnps predict --precision auto``).
    ``model``: checkpoint;
    default ``<data_dir>/train/model.pt``. ``rig``: also render every test capture again
    through that rig (:class:`Rig`; named ``<capture>-<rig>``, e.g. ``bowl-specular-17-fov40-point1.5``)
    and score the twins as ``cnnps predict`` treats rig captures; ``summary_rig`` and
    ``rig_minus_ortho`` in metrics.json say what the rig costs.
    """

    synthetic: bool = True
    test_shapes: tuple[str, ...] = (SPHERE, "bowl", "holed")
    superpixels: Count = 100
    categories: tuple[str, ...] = ("specular", "metallic")
    ranges: MaterialRanges = field(default_factory=MaterialRanges)  # the test set's BSDF ranges (not materials')
    light_sets: tuple[int, ...] = (17, 305)
    size: Annotated[int, Range(ge=8)] = 64  # pixels
    samples: Count = 16
    rotations: tuple[int, ...] = (1, 10)
    real_captures: tuple[str, ...] = ()
    real_subsets: tuple[int, ...] = ()
    real_exclude_from_mean: tuple[str, ...] = ()
    real_pixels: Annotated[int, Range(ge=0)] = 0  # 0 = every mask pixel; N = a seeded sample of N (pixel_sample)
    rig: Rig | None = None
    # point-light captures: "known" = the median depth a render records in scene.json, as a
    # measured --distance; "estimated" = found from the images, as without --distance
    rig_distance: Literal["known", "estimated"] = "known"
    model: str | None = None
    device: Device = "auto"
    batch_size: Annotated[int, Range(ge=0)] = 0  # maps per network call (0 = the inference default: 256 on a CPU, 4096 on CUDA)
    lambertian_shadow_threshold: UnitFraction | None = None
    sparse_fill: SparseFill = "auto"  # CNN, as `cnnps predict --sparse-fill` (cnnps.ps.sparse_fill)
    saturated: Literal["exclude", "keep"] = "exclude"  # as `cnnps predict --saturated`
    precision: Literal["auto", "fp32", "bf16"] = "fp32"  # the network's; auto as `cnnps predict --precision`
    seed: Annotated[int, Range(ge=0)] = 0

    def __post_init__(self):
        for name in ("test_shapes", "categories", "light_sets", "rotations", "real_captures", "real_subsets",
                     "real_exclude_from_mean"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        object.__setattr__(self, "ranges", checked_ranges("eval", self.ranges))
        if self.synthetic:
            if not self.test_shapes:
                raise ConfigError("eval.test_shapes is empty (set eval.synthetic: false to score real captures only)")
            from cnnps.synth.procedural import PROCEDURAL_KINDS

            for s in self.test_shapes:
                if s != SPHERE and s not in PROCEDURAL_KINDS:
                    raise ConfigError(f"eval.test_shapes: unknown shape {s!r} (choose from {SPHERE}, {', '.join(PROCEDURAL_KINDS)})")
            if len(set(self.test_shapes)) != len(self.test_shapes):
                raise ConfigError(f"eval.test_shapes: duplicates in {list(self.test_shapes)}")
            object.__setattr__(self, "categories", checked_categories("eval", self.categories))
            if not self.light_sets:
                raise ConfigError("eval.light_sets is empty")
            for n in self.light_sets:
                if n < 3:
                    raise ConfigError(f"eval.light_sets: each light count must be >= 3, got {n}")
        if not self.synthetic and not self.real_captures:
            raise ConfigError("eval: nothing to evaluate (eval.synthetic is false and eval.real_captures is empty)")
        if self.real_subsets and not self.real_captures:
            raise ConfigError("eval.real_subsets needs eval.real_captures (the captures to draw the images from)")
        from cnnps.io.capture import MIN_IMAGES

        if any(n < MIN_IMAGES for n in self.real_subsets):
            raise ConfigError(f"eval.real_subsets: each image count must be >= {MIN_IMAGES}, got {list(self.real_subsets)}")
        names = [Path(c).name for c in self.real_captures]
        for name in self.real_exclude_from_mean:
            if name not in names:
                raise ConfigError(f"eval.real_exclude_from_mean: {name!r} is not the folder name of one of "
                                  f"eval.real_captures ({', '.join(names) or 'none'})")
        check_fields(self, "eval.")  # the declared ranges and choices (size, samples, device, ...)
        if not self.rotations or any(k < 1 for k in self.rotations):
            raise ConfigError(f"eval.rotations must be a non-empty list of integers >= 1, got {list(self.rotations)}")
