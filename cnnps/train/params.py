"""The train stage's typed parameters: ``train:`` in params.yaml as a tree of frozen
dataclasses, checked when built.

:class:`Params` holds the top-level keys (the run's length, validation, checkpoints, where
and how a step runs) and six sections: :class:`OptimiserParams` (``optimiser``: Adam and
its step schedule), :class:`DataParams` (``data``: shards, batches), :class:`PixelwiseParams`
(``pixelwise``: per-pixel maps in a batch), :class:`CpuParams` (``cpu``: how a CPU step
runs), :class:`SynthesisParams` (``synthesis``: what per-pixel maps are drawn from,
filled by the config layer from ``materials`` and ``extract``, :data:`FROM_SECTIONS`) and
:class:`ModelParams` (``model``: the network trained, its head and its input patch).
The stage (:mod:`cnnps.stages.train`: its run key and ``run``) and the training loop
(:mod:`cnnps.train.loop` and the modules it calls) both read this one tree, so a
setting's type, check and default are written once, here::

    >>> Params(optimiser={"lr": 1e-4}).optimiser.lr
    0.0001

A run key hashes :meth:`Params.result_key`, the params under their flat names
(:data:`MOVED_KEYS`, :data:`OMITTED_AT_DEFAULT`), so keys do not depend on the sections.
This module loads no torch (the stage imports it before torch loads).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Annotated, ClassVar, Literal

from cnnps.infra.errors import ConfigError
from cnnps.infra.options import Count, Positive, Range, UnitFraction, check_fields
from cnnps.synth.bsdf import DEFAULT_CATEGORIES, MaterialRanges, checked_categories, checked_ranges
from cnnps.synth.effect_settings import EFFECT_NAMES
from cnnps.synth.light_subsets import RULE, SETTINGS, check_light_subsets
from cnnps.train.phase_params import PhaseParams, check_phases, phase_values


Steps = Annotated[int, Range(ge=0)]  # a count where 0 means none (or no limit)


@dataclass(frozen=True)
class OptimiserParams:
    """``train.optimiser``: Adam and its step schedule. The learning rate of step k + 1 is
    ``lr * lr_gamma ** (milestones <= k)`` (:func:`cnnps.train.optimiser.lr_at`)."""

    lr: Positive = 1e-3
    lr_milestones: tuple[int, ...] = ()  # steps at which the learning rate is multiplied by lr_gamma
    lr_gamma: Annotated[float, Range(gt=0.0, le=1.0)] = 0.1
    weight_decay: Annotated[float, Range(ge=0.0)] = 0.0
    fused_adam: bool = True  # torch's fused Adam kernel (same algorithm, one pass per tensor)
    # N >= 1: model.pt is the mean of the weights at every checkpoint from step N on (each
    # checkpoint_every steps and the last; cnnps.train.averaging); 0: the last step's weights
    average_from: Annotated[int, Range(ge=0)] = 0
    # d in (0, 1): model.pt is the exponential moving average of the weights over the steps,
    # e <- d e + (1 - d) w after each step (cnnps.train.averaging.WeightEMA); 0: off
    ema_decay: Annotated[float, Range(ge=0.0, lt=1.0)] = 0.0

    def __post_init__(self):
        check_fields(self, "train.optimiser.")
        if self.average_from and self.ema_decay:
            raise ConfigError("train.optimiser: average_from and ema_decay are two ways to average the weights; "
                              "set one of them")
        object.__setattr__(self, "lr_milestones", tuple(self.lr_milestones or ()))
        if any(not isinstance(m, int) or m < 1 for m in self.lr_milestones) or list(self.lr_milestones) != sorted(
            set(self.lr_milestones)
        ):
            raise ConfigError(f"train.optimiser.lr_milestones must be increasing steps >= 1, "
                              f"got {list(self.lr_milestones)}")


@dataclass(frozen=True)
class DataParams:
    """``train.data``: where the training rows come from and how they are batched."""

    shards: str | None = None  # where extract wrote (its `output`: path or fsspec URL); None = data_dir/extract
    batch_size: Count = 128  # rows a step (the global batch under torchrun)
    shuffle_buffer: Count = 65536  # rows
    prefetch: Steps = 2  # row groups decoded ahead in a background thread (0 = none); batches do not change
    num_workers: Steps = 0  # DataLoader worker processes; 0 = load in the main process

    def __post_init__(self):
        check_fields(self, "train.data.")
        if self.shards is not None and (not isinstance(self.shards, str) or not self.shards.strip()):
            raise ConfigError(f"train.data.shards must be a folder path or URL, got {self.shards!r}")


@dataclass(frozen=True)
class PixelwiseParams:
    """``train.pixelwise``: per-pixel maps (:mod:`cnnps.synth.pixelwise`) in every batch."""

    # this share of a batch's rows, the rest from the Cycles shards; 1 = per-pixel maps only (no renders
    # or shards: a core install or a GPU machine trains; needs max_steps, and validates on a fixed per-pixel set)
    share: Annotated[float, Range(ge=0.0, le=1.0)] = 0.0
    effects: dict[str, float] = field(default_factory=dict)  # cnnps.synth.pixelwise.Effects, e.g. {ambient: 0.05}
    sparse_fraction: Annotated[float, Range(ge=0.0, le=1.0)] = 0.0  # per-pixel maps of 6..49 lights
    w: Annotated[int, Range(ge=2)] = 32  # map width of per-pixel-only training (shards carry their own)
    # made this many steps ahead in a background thread (on CUDA on a stream of its own;
    # cnnps.train.maps_ahead); 0 = in the step's thread. The maps do not change.
    ahead: Annotated[int, Range(ge=0, le=8)] = 1
    # colour maps: the network takes (B, 4, w, w), the grey map then R, G, B (cnnps.synth.pixelwise.generate
    # with rgb=True); needs share: 1 (the shards are grey); a grey train.init is widened (colour filters at 0)
    rgb: bool = False
    # directions in each batch's light set (a jittered spiral, cnnps.synth.pixelwise.default_lights): the
    # per-pixel counterpart of render.lights; a map takes k <= min(extract.max_lights, lights) of them
    lights: Annotated[int, Range(ge=3)] = 1300

    def __post_init__(self):
        check_fields(self, "train.pixelwise.")
        if not isinstance(self.rgb, bool):
            raise ConfigError(f"train.pixelwise.rgb must be true or false, got {self.rgb!r}")
        for k, v in self.effects.items():
            if k not in EFFECT_NAMES:
                raise ConfigError(f"train.pixelwise.effects: unknown effect {k!r}; "
                                  f"effects (cnnps.synth.pixelwise.Effects): {', '.join(EFFECT_NAMES)}")
            if not 0.0 <= float(v) <= 1.0:
                raise ConfigError(f"train.pixelwise.effects.{k} must be a number in [0, 1], got {v!r}")


@dataclass(frozen=True)
class SynthesisParams:
    """``train.synthesis``: the settings per-pixel maps share with the rendered training
    data, each with one source in params.yaml: ``categories`` and ``ranges`` are
    ``materials.categories`` and ``materials.ranges`` (what the rendered scenes' materials
    are drawn from), the light-subset rules are extract's (``extract.min_lights``,
    ``max_lights``, ``cone_min_deg``, ``cone_max_deg``, ``sparse_min_lights``: what the
    shards' maps are cut by). The config layer fills this section from those keys
    (:data:`Params.FROM_SECTIONS`); a params file's ``train:`` cannot set it. The defaults
    are those sections' defaults, so ``Params()`` in Python draws what an empty params file
    does. :func:`cnnps.train.pixelwise_batches.pixelwise_maker` hands every field to
    :func:`cnnps.synth.pixelwise.generate`."""

    categories: tuple[str, ...] = DEFAULT_CATEGORIES
    ranges: MaterialRanges = field(default_factory=MaterialRanges)
    # the light-subset rule's settings (cnnps.synth.light_subsets declares them and their defaults)
    min_lights: int = RULE.min_lights
    max_lights: int = RULE.max_lights
    cone_min_deg: float = RULE.cone_min_deg
    cone_max_deg: float = RULE.cone_max_deg
    sparse_min_lights: int = RULE.sparse_min_lights  # sparse maps (train.pixelwise.sparse_fraction)

    def __post_init__(self):
        object.__setattr__(self, "ranges", checked_ranges("train.synthesis", self.ranges))
        object.__setattr__(self, "categories", checked_categories("train.synthesis", self.categories))
        check_light_subsets("train.synthesis", self)

    def changed(self) -> dict:
        """The settings not at their defaults, as plain data (what a run key holds);
        ``ranges`` only for the categories drawn."""
        default = SynthesisParams()
        out: dict = {}
        if self.categories != default.categories:
            out["categories"] = list(self.categories)
        ranges = {c: self.ranges.get(c).to_dict() for c in self.categories
                  if self.ranges.get(c) != default.ranges.get(c)}
        if ranges:
            out["ranges"] = ranges
        for name in SETTINGS:
            if getattr(self, name) != getattr(default, name):
                out[name] = getattr(self, name)
        return out


@dataclass(frozen=True)
class CpuParams:
    """``train.cpu``: how a step runs on a CPU. None of these changes the model or the loss."""

    threads: Steps = 0  # torch CPU threads; 0 = one per core
    # processes that share each CPU step, the batch split between them by rows, each with
    # threads / step_processes torch threads (cnnps.train.step_processes): eager steps (fp32 or bf16) with
    # counter masks in one training process (not under torchrun, not on CUDA). 0 = auto: one
    # process per thread of `threads` (one per core), at most one per 16 rows of a batch, where
    # that applies and the run has 200 steps or more to go, else 1. The weights do not change.
    step_processes: Annotated[int, Range(ge=0, le=64)] = 0
    # dropout masks: "counter16" = drawn from a stream keyed by (seed, rank, step, layer, 16-row block),
    # 16 bits an element (the drop rate to 2^-17), cheaper than torch's and resume-exact with no RNG
    # state (cnnps.models.network.counter_dropout); "counter" = the same with 32 bits an element (rate to
    # 2^-33; what runs started with counter keep); "torch" = torch's generator.
    # CUDA and compiled models always use torch's.
    dropout_masks: Literal["counter16", "counter", "torch"] = "counter16"
    # eager float32 CPU steps with counter masks: "fused" = the layers of cnnps.models.train_layers
    # (fewer passes over memory, the same results up to float rounding); "reference" = torch's layers
    layers: Literal["fused", "reference"] = "fused"
    # glibc keeps freed memory for the next step instead of returning it to the kernel
    # (cnnps.train.allocator: no page faults on every step's large blocks); process-wide
    keep_freed_memory: bool = True

    def __post_init__(self):
        check_fields(self, "train.cpu.")


# cnnps.models.model_options.ARCHS, cnnps.models.heads.HEADS, cnnps.models.patch.PATCHES
# (named here: this module loads without torch; tests/train/test_params.py checks they agree)
ARCHS = ("cnnps", "unet")
HEADS = ("regression", "heatmap", "heatmap-softmax")
PATCHES = (1, 3, 5)


@dataclass(frozen=True)
class ModelParams:
    """``train.model``: the network trained (:func:`cnnps.models.model_options.build_model`).
    ``arch``: ``cnnps`` (the paper's CNN-PS) or ``unet`` (the bias-free heat-map U-Net,
    heat-map head only); ``head``: ``regression`` (a unit normal, MSE loss), ``heatmap``
    (a w x w heat-map, MSE against a Gaussian) or ``heatmap-softmax`` (w x w logits, the
    cross-entropy of their softmax; what trains on the CNN-PS trunk), losses and decoding
    in :mod:`cnnps.models.heads`; ``patch``: b,
    the network takes the b x b maps around a pixel (b > 1 needs the extract stage's
    ``layout: observations``: patches are drawn from per-pixel observations,
    :mod:`cnnps.train.patch_dataset`). The defaults are the paper's network::

        train:
          model: {arch: unet, head: heatmap, patch: 3}
    """

    arch: Literal["cnnps", "unet"] = "cnnps"
    head: Literal["regression", "heatmap", "heatmap-softmax"] = "regression"
    patch: Literal[1, 3, 5] = 1

    def __post_init__(self):
        if isinstance(self.patch, bool):
            raise ConfigError(f"train.model.patch must be one of 1, 3, 5, got {self.patch!r}")
        check_fields(self, "train.model.")
        if self.arch == "unet" and self.head != "heatmap":
            raise ConfigError(f"train.model.head: arch unet has the heatmap head only, got {self.head!r}")

    def options(self) -> dict:
        """The keyword arguments of :func:`cnnps.models.model_options.build_model` it sets."""
        return {"arch": self.arch, "head": self.head, "patch": int(self.patch)}


SECTIONS = {"optimiser": OptimiserParams, "data": DataParams, "pixelwise": PixelwiseParams, "cpu": CpuParams,
            "synthesis": SynthesisParams, "model": ModelParams}

# The flat name of each section key -> its place, "section.key": run keys hash the flat
# names (Params.flat), and a record holding the train section flat is read through it.
MOVED_KEYS = {
    **{k: f"optimiser.{k}" for k in ("lr", "lr_milestones", "lr_gamma", "weight_decay", "fused_adam")},
    **{k: f"data.{k}" for k in ("shards", "batch_size", "shuffle_buffer", "prefetch", "num_workers")},
    "pixelwise": "pixelwise.share", "pixelwise_effects": "pixelwise.effects",
    "pixelwise_sparse_fraction": "pixelwise.sparse_fraction", "w": "pixelwise.w", "pixelwise_ahead": "pixelwise.ahead",
    **{k: f"cpu.{k}" for k in ("threads", "step_processes", "dropout_masks", "keep_freed_memory")},
    "cpu_layers": "cpu.layers",
}


# Section keys with no flat name, with their defaults: in the flat params (and so in the
# run key) as ``<section>_<key>`` only off that default. (``synthesis``'s keys: SynthesisParams.changed.)
OMITTED_AT_DEFAULT = {"pixelwise.rgb": False, "optimiser.average_from": 0, "optimiser.ema_decay": 0.0,
                      "pixelwise.lights": 1300,
                      "model.arch": "cnnps", "model.head": "regression", "model.patch": 1}

# Sections of the train params filled from other stages' sections by the config layer
# (cnnps.pipeline.config.build_params): section -> {stage: keys}. dvc.yaml's train stage lists
# each "stage.key" among its params (tests/pipeline/test_dvc.py checks it).
FROM_SECTIONS = {
    "synthesis": {
        "materials": ("categories", "ranges"),
        "extract": SETTINGS,
    },
}


def _section(cls: type, value, name: str):
    """``value`` as section ``cls``: itself, or built from a mapping (unknown keys named)."""
    if isinstance(value, cls):
        return value
    if not isinstance(value, Mapping):
        raise ConfigError(f"train.{name} must be a mapping of its keys, got {value!r}")
    known = [f.name for f in fields(cls)]
    unknown = [k for k in value if k not in known]
    if unknown:
        raise ConfigError(f"train.{name}: unknown key {unknown[0]!r}; known keys: {', '.join(known)}")
    return cls(**value)


@dataclass(frozen=True)
class Params:
    """``train:`` in params.yaml. The run's length, validation, checkpoints and where it
    runs are top-level keys; the rest sits in five sections::

        train:
          max_steps: 3000
          optimiser: {lr: 0.001, lr_milestones: [2000], lr_gamma: 0.2}
          data: {batch_size: 128}
          pixelwise: {share: 0.5, effects: {ambient: 0.05}}
          cpu: {threads: 2}
          model: {arch: cnnps, head: heatmap, patch: 3}

    and a sixth, ``synthesis`` (:class:`SynthesisParams`), that the config layer fills from
    ``materials`` and ``extract`` (:data:`FROM_SECTIONS`), so per-pixel maps draw the
    materials and light subsets the renders and shards do.

    A key of the flat section that preceded them (``train: {lr: 0.001}``) is refused with
    its new place (``train.lr moved to train.optimiser.lr``; :data:`MOVED_KEYS`). In Python
    a section is its dataclass or a mapping of its keys:
    ``Params(max_steps=10, optimiser={"lr": 1e-4}, synthesis={"categories": ["metallic"]})``.
    """

    # flat key -> "section.key", for the one-line error of cnnps.pipeline.config
    MOVED_KEYS: ClassVar[dict[str, str]] = MOVED_KEYS
    # section -> {stage: keys} the config layer fills it from (cnnps.pipeline.config.build_params)
    FROM_SECTIONS: ClassVar[dict[str, dict[str, tuple[str, ...]]]] = FROM_SECTIONS

    epochs: Count = 10
    max_steps: Steps = 0  # 0 = no limit; otherwise stop after this many optimiser steps
    init: str | None = None  # start from these weights (a cnnps checkpoint) instead of a random init
    dropout: UnitFraction = 0.2
    seed: int = 0
    val_every: Steps = 2000  # steps; 0 = only at the end
    val_max_rows: Count = 50000
    checkpoint_every: Count = 1000  # steps
    keep_checkpoints: Count = 2
    log_every: Count = 50  # steps between loss points in plots/loss.csv
    device: Literal["auto", "cpu", "cuda"] = "auto"
    # auto = the faster of fp32 and bf16 on this machine, timed at the run's start
    # (cnnps.train.precision; bf16 only where the CPU or GPU has bf16 units); fp32 | bf16 (autocast)
    precision: Literal["auto", "fp32", "bf16"] = "auto"
    channels_last: bool = True  # NHWC activations (oneDNN's faster CPU kernels)
    compile: bool = False  # torch.compile the model (inductor); falls back to eager with a warning
    progress: bool = True
    optimiser: OptimiserParams = field(default_factory=OptimiserParams)
    data: DataParams = field(default_factory=DataParams)
    pixelwise: PixelwiseParams = field(default_factory=PixelwiseParams)
    cpu: CpuParams = field(default_factory=CpuParams)
    synthesis: SynthesisParams = field(default_factory=SynthesisParams)  # from materials and extract
    model: ModelParams = field(default_factory=ModelParams)
    # the run as a sequence of phases, each with its own steps and changed settings (cnnps.train.phase_params);
    # empty: one run of max_steps / epochs
    phases: tuple[PhaseParams, ...] = ()

    def __post_init__(self):
        for name, cls in SECTIONS.items():
            object.__setattr__(self, name, _section(cls, getattr(self, name), name))
        object.__setattr__(self, "phases", check_phases(self.phases))
        check_fields(self, "train.")  # every declared field: counts, steps, dropout, device, precision
        if self.init is not None and (not isinstance(self.init, str) or not self.init.strip()):
            raise ConfigError(f"train.init must be a checkpoint path, got {self.init!r}")
        if self.cpu.step_processes > 1 and (self.compile or self.cpu.dropout_masks == "torch"):
            raise ConfigError("train.cpu.step_processes > 1 needs eager steps with counter dropout masks "
                              "(compile: false, cpu.dropout_masks: counter16 or counter)")
        if self.pixelwise.share >= 1.0 and not self.max_steps and not self.phases:
            raise ConfigError("train.pixelwise.share: 1 (per-pixel maps only) needs train.max_steps: "
                              "there are no epochs")
        syn = self.synthesis
        if self.pixelwise.share and self.pixelwise.sparse_fraction and syn.sparse_min_lights >= syn.min_lights:
            raise ConfigError(f"train.pixelwise.sparse_fraction needs extract.sparse_min_lights < extract.min_lights "
                              f"(a sparse map has fewer lights than a dense one), got {syn.sparse_min_lights} "
                              f"and {syn.min_lights}")
        if self.model.patch > 1 and self.pixelwise.share:
            raise ConfigError(f"train.model.patch: {self.model.patch} needs train.pixelwise.share: 0 (a per-pixel "
                              f"map has no neighbours to make a patch of), got share {self.pixelwise.share}")
        if self.pixelwise.rgb and self.pixelwise.share < 1.0:
            raise ConfigError(f"train.pixelwise.rgb: true needs train.pixelwise.share: 1.0 (the rendered shards "
                              f"hold grey maps only), got share {self.pixelwise.share}")

        for i, ph in enumerate(self.phases):  # each phase's settings checked as a run's
            try:
                self.phase(i)
            except ConfigError as exc:
                said = str(exc)
                raise ConfigError(said if said.startswith("train.phases") else f"train.phases: {ph.name!r}: {said}") \
                    from None

    def phase(self, i: int, init: str | None = None) -> Params:
        """The params phase ``i`` of ``phases`` runs with: these with its ``set`` applied,
        ``max_steps`` its steps (1 for a phase of 0 steps: it runs none), starting from
        ``init``, no phases of its own."""
        ph = self.phases[i]
        values = phase_values({f.name: getattr(self, f.name) for f in fields(self)}, ph, SECTIONS)
        values.update(max_steps=ph.steps or 1, init=init, phases=())
        return Params(**values)

    @classmethod
    def from_record(cls, record: Mapping) -> Params:
        """The params a model file or ``metrics.json`` recorded (``meta["params"]``), in
        sections or flat (each flat key put in its section, :data:`MOVED_KEYS`).

        >>> Params.from_record({"lr": 1e-4, "batch_size": 64, "max_steps": 10}).optimiser.lr
        0.0001
        """
        nested: dict = {}
        sections: dict[str, dict] = {}
        for key, value in record.items():
            if key in MOVED_KEYS and not (key in SECTIONS and isinstance(value, Mapping)):
                section, _, name = MOVED_KEYS[key].partition(".")
                sections.setdefault(section, {})[name] = value
            else:
                nested[key] = value
        for section, values in sections.items():
            nested[section] = {**(nested.get(section) or {}), **values}
        return cls(**nested)

    def flat(self) -> dict:
        """The params as one flat mapping, each key under its flat name (:data:`MOVED_KEYS`):
        what :meth:`result_key` hashes, so run keys do not depend on the sections. A
        section key with no flat name (:data:`OMITTED_AT_DEFAULT`, and ``synthesis``'s:
        :meth:`SynthesisParams.changed`) is ``<section>_<key>`` and only there when it is
        not at its default, so a Params that leaves it at its default keys its runs without it."""
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in SECTIONS and f.name != "phases"}
        if self.phases:  # no key at all without phases: a run's key is what it was before they existed
            d["phases"] = [ph.record() for ph in self.phases]
        back = {new: old for old, new in MOVED_KEYS.items()}
        d.update({f"synthesis_{key}": value for key, value in self.synthesis.changed().items()})
        for name in SECTIONS:
            if name == "synthesis":
                continue
            for key, value in asdict(getattr(self, name)).items():
                place = f"{name}.{key}"
                if place in OMITTED_AT_DEFAULT:
                    if value != OMITTED_AT_DEFAULT[place]:
                        d[f"{name}_{key}"] = value
                    continue
                d[back[place]] = value
        return d

    def result_key(self) -> dict:
        """Params that change the trained weights (a resume needs them equal), under their
        flat names. ``init`` enters :func:`run_key` as the SHA-256 of its weights, not as a
        path. Without per-pixel maps (``pixelwise.share: 0``) the per-pixel light set and
        ``synthesis`` change nothing (the shards' manifest, in the key, holds what made them)."""
        d = self.flat()
        for k in ("epochs", "max_steps", "val_every", "val_max_rows", "checkpoint_every", "keep_checkpoints",
                  "log_every", "threads", "num_workers", "prefetch", "progress", "shards", "init",
                  "keep_freed_memory", "pixelwise_ahead", "step_processes"):
            d.pop(k)
        if not self.pixelwise.share:
            for k in [k for k in d if k.startswith("synthesis_") or k == "pixelwise_lights"]:
                d.pop(k)
        d["lr_milestones"] = list(self.optimiser.lr_milestones)
        return d
