"""Batches of b x b patches of observation maps from per-pixel observations (spatial
context): :class:`PatchStream` (numpy) and :class:`PatchDataset` (torch).

Input: the observation files of an extract run with ``layout: observations``
(:mod:`cnnps.io.observation_store`; :func:`cnnps.io.observation_store.manifest_observations`
lists a split's files with their records, :func:`~cnnps.io.observation_store.verify_observations`
checks them). Every sample is drawn when its batch is made, as the extract stage draws a
row (docs/extract.md):

1. a centre: a stored pixel with a ground-truth normal and a positive value;
2. a light subset by :func:`cnnps.synth.training_samples.sample_light_masks` (a cone
   about the view axis, k lights, sparse pixels), shared by the patch's cells; a subset
   whose centre values are all dark is drawn again (at most :data:`DARK_REDRAWS` times);
3. a rotation theta: one of :func:`cnnps.ps.rotation.rotation_angles` (``rotations``),
   or uniform in [0, 2 pi) with ``rotations: 0``;
4. the b x b cells' observations at the rotated offsets (:mod:`cnnps.ps.patches`:
   bilinear or nearest, zero outside the mask), then the capture realism of
   :func:`cnnps.synth.training_samples.apply_capture_effects` on each in-mask cell as on a
   pixel of the extract stage (per scene: the gains, direction error, black level, full
   scale and bit depth of :func:`~cnnps.synth.training_samples.draw_capture_effects`,
   drawn once from the scene's seed ``derive_seed64(seed, scene_key)`` like the extract
   stage's; per cell: ambient and noise);
5. the maps by :func:`cnnps.ps.patches.patch_maps` (lights rotated by theta) and the
   centre's normal rotated by theta.

Batch: ``(patches (B, b, b, 1, w, w) float32, normals (B, 3) float32)``; layout of a
patch in :mod:`cnnps.ps.patches` (``patches.reshape(B, b * b, w, w)`` for a network
taking the cells as channels). b = 1 gives the extract stage's rows: the same map, bit
for bit, for the same pixel, light subset and angle.

Order: per epoch the scenes are permuted by ``(seed, epoch)`` and taken
``scenes_in_memory`` at a time (a window); the centres of a window are permuted and cut
into batches of ``batch_size`` (the last partial batch of each window is left out of the
epoch). Every batch's draws come from generators seeded by ``(seed, epoch, batch
index)``, so a batch does not depend on the batches before it: ``skip_batches`` skips
without computing (and without reading the windows it skips whole), DataLoader workers
and DDP ranks take every ``parts``-th / ``world_size``-th batch (every rank the same
number), and the batches are the same whatever the split.

Example::

    manifest = load_manifest(extract_dir)
    verify_observations(extract_dir, manifest)
    files = manifest_observations(extract_dir, manifest, "train")
    stream = PatchStream(files, PatchSampling(b=3), batch_size=128, seed=0)
    ds = PatchDataset(stream)
    ds.set_epoch(0); ds.set_skip(resume_step)
    for patches, normals in DataLoader(ds, batch_size=None): ...
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import get_worker_info

from cnnps.infra.errors import ConfigError, InputError
from cnnps.infra.hashing import derive_seed64
from cnnps.io.observation_store import SceneObservations, read_observations
from cnnps.ps.patches import (
    INTERPOLATIONS,
    check_patch_size,
    gather_taps,
    neighbour_taps,
    patch_maps,
    patch_offsets,
    rotated_normals,
)
from cnnps.ps.rotation import rotation_angles
from cnnps.synth.light_subsets import RULE, check_light_subsets, sample_light_masks
from cnnps.synth.training_samples import (
    CaptureEffects,
    apply_capture_effects,
    draw_capture_effects,
)
from cnnps.train.shard_dataset import ShardDataset

DARK_REDRAWS = 8  # light subsets drawn again for a centre whose chosen values are all dark
STREAM_LIGHTS, STREAM_SPARSE, STREAM_ANGLE = 1, 2, 3  # a batch's generators: [seed, epoch, batch, scene, stream]


@dataclass(frozen=True)
class PatchSampling:
    """How a sample is drawn. The light-subset and realism fields have the names, meaning
    and defaults of :class:`cnnps.stages.extract.Params` (docs/extract.md); ``b`` the
    patch size (odd), ``interpolation`` ``bilinear`` | ``nearest`` (:mod:`cnnps.ps.patches`),
    ``rotations`` the number of angles (0: any angle)."""

    b: int = 3
    w: int = 32
    interpolation: str = "bilinear"
    rotations: int = 10
    min_lights: int = RULE.min_lights
    max_lights: int = RULE.max_lights
    cone_min_deg: float = RULE.cone_min_deg
    cone_max_deg: float = RULE.cone_max_deg
    sparse_fraction: float = 0.0
    sparse_min_lights: int = RULE.sparse_min_lights
    ambient_max: float = 0.0
    intensity_error: float = 0.0
    direction_error_deg: float = 0.0
    black_level_max: float = 0.0
    noise_max: float = 0.0
    saturated_fraction_max: float = 0.0
    quantize_bits: tuple[int, ...] = ()

    def __post_init__(self):
        try:
            check_patch_size(self.b)
        except ValueError as exc:
            raise ConfigError(f"patch.b: {exc}") from None
        if self.interpolation not in INTERPOLATIONS:
            raise ConfigError(f"patch.interpolation must be one of {', '.join(INTERPOLATIONS)}, "
                              f"got {self.interpolation!r}")
        if not 4 <= self.w <= 256:
            raise ConfigError(f"patch.w must be in [4, 256], got {self.w}")
        if not 0 <= self.rotations <= 127:
            raise ConfigError(f"patch.rotations must be in [0, 127], got {self.rotations}")
        check_light_subsets("patch", self, self.sparse_fraction)
        object.__setattr__(self, "quantize_bits", tuple(sorted({int(b) for b in self.quantize_bits})))

    @classmethod
    def from_settings(cls, settings, **overrides) -> PatchSampling:
        """The fields found on ``settings`` (e.g. an extract ``Params``), then ``overrides``."""
        names = {f.name for f in fields(cls)}
        values = {n: getattr(settings, n) for n in names if hasattr(settings, n)}
        return cls(**{**values, **overrides})

    def effects(self) -> dict:
        """The keyword arguments of :func:`cnnps.synth.training_samples.draw_capture_effects`."""
        return {n: getattr(self, n) for n in ("ambient_max", "noise_max", "intensity_error", "direction_error_deg",
                                              "black_level_max", "saturated_fraction_max", "quantize_bits")}


@dataclass
class _Scene:
    obs: SceneObservations
    index: np.ndarray  # (H, W) row in obs.values, -1 outside the mask
    centres: np.ndarray  # (C,) rows of obs.values that are centres
    fx: CaptureEffects
    map_lights: np.ndarray  # (m, 3) the directions written into the maps


@dataclass
class PatchBatch:
    """One batch and how it was drawn: ``patches`` (B, b, b, 1, w, w), ``normals`` (B, 3),
    per sample ``scene`` (index into the stream's files), ``pixel`` (row in the scene's
    values), ``theta`` (radians), ``light_mask`` (list of (m_scene,) bool)."""

    patches: np.ndarray
    normals: np.ndarray
    scene: np.ndarray
    pixel: np.ndarray
    theta: np.ndarray
    light_mask: list


class PatchStream:
    """Deterministic, resumable batches of patches (numpy side); order and seeds in the
    module docstring. ``files``: (path, record) pairs, ``record["rows"]`` the file's
    centres (the manifest's records); ``scenes_in_memory``: scenes loaded at a time."""

    def __init__(
        self,
        files: Sequence[tuple[str | Path, dict]],
        sampling: PatchSampling,
        batch_size: int,
        seed: int = 0,
        scenes_in_memory: int = 8,
        rank: int = 0,
        world_size: int = 1,
    ):
        if not files:
            raise ValueError("no observation files to read")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} outside world of {world_size}")
        if batch_size < 1 or scenes_in_memory < 1:
            raise ValueError("batch_size and scenes_in_memory must be >= 1")
        self.paths = [p for p, _ in files]
        self.counts = np.array([int(r["rows"]) for _, r in files], np.int64)
        self.sampling = sampling
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.scenes_in_memory = int(scenes_in_memory)
        self.rank, self.world_size = int(rank), int(world_size)
        self._loaded: dict[int, _Scene] = {}

    # -- the epoch's plan ------------------------------------------------------------------
    def windows(self, epoch: int) -> list[tuple[np.ndarray, int, int]]:
        """(scene indices, first global batch, batches) of each window of the epoch."""
        order = np.random.default_rng([self.seed, int(epoch), 0x5CE7E]).permutation(len(self.paths))
        out, g = [], 0
        for s in range(0, len(order), self.scenes_in_memory):
            scenes = order[s : s + self.scenes_in_memory]
            n = int(self.counts[scenes].sum()) // self.batch_size
            out.append((scenes, g, n))
            g += n
        return out

    def batches_per_epoch(self, epoch: int = 0) -> int:
        """This rank's batches in the epoch: the same number for every rank (DDP steps
        together), the last ``total % world_size`` batches left out."""
        return sum(n for _, _, n in self.windows(epoch)) // self.world_size

    def iter_epoch(self, epoch: int, skip_batches: int = 0, part: int = 0, parts: int = 1) -> Iterator[tuple]:
        """Yield (patches (B,b,b,1,w,w) float32, normals (B,3) float32) of this rank's
        batches from its ``skip_batches``-th on; with ``parts`` > 1 only every
        ``parts``-th of them, from the ``part``-th (DataLoader workers)."""
        for batch in self.iter_batches(epoch, skip_batches, part, parts):
            yield batch.patches, batch.normals

    def iter_batches(self, epoch: int, skip_batches: int = 0, part: int = 0, parts: int = 1) -> Iterator[PatchBatch]:
        """:meth:`iter_epoch` with each batch's draws (:class:`PatchBatch`)."""
        per_rank = self.batches_per_epoch(epoch)
        for scenes, g0, n in self.windows(epoch):
            mine = [g for g in range(g0, g0 + n) if self._yields(g, skip_batches, part, parts, per_rank)]
            if not mine:
                continue
            self._load(scenes)
            sizes = self.counts[scenes]
            order = np.random.default_rng([self.seed, int(epoch), g0, 0xCE7]).permutation(int(sizes.sum()))
            which = np.repeat(np.arange(len(scenes)), sizes)  # window position -> scene slot
            within = np.arange(int(sizes.sum())) - np.repeat(np.cumsum(sizes) - sizes, sizes)
            for g in mine:
                take = order[(g - g0) * self.batch_size : (g - g0 + 1) * self.batch_size]
                yield self.make_batch(epoch, g, scenes[which[take]], within[take])
        self._loaded.clear()

    def _yields(self, g: int, skip: int, part: int, parts: int, per_rank: int) -> bool:
        if g % self.world_size != self.rank:
            return False
        q = g // self.world_size  # this rank's batch number
        return skip <= q < per_rank and (q - skip) % parts == part

    # -- scenes ----------------------------------------------------------------------------
    def _load(self, scenes: np.ndarray) -> None:
        keep = {int(s) for s in scenes}
        for s in list(self._loaded):
            if s not in keep:
                del self._loaded[s]
        for s in sorted(keep - set(self._loaded)):
            self._loaded[s] = self._open(s)

    def _open(self, s: int) -> _Scene:
        obs = read_observations(self.paths[s])
        centres = np.flatnonzero(obs.centre)
        if len(centres) != self.counts[s]:
            raise InputError(self.paths[s], f"holds {len(centres)} centres, the manifest records {self.counts[s]}; "
                             "rerun `cnnps run-stage extract`")
        sp = self.sampling
        fx_args = sp.effects()
        needs_scale = sp.black_level_max or sp.saturated_fraction_max or sp.quantize_bits
        values = obs.values.astype(np.float32) if needs_scale else obs.values
        fx = draw_capture_effects(derive_seed64(self.seed, obs.scene_key), values, centres, obs.lights, **fx_args)
        return _Scene(obs, obs.index_image(), centres, fx, obs.lights if fx.lights is None else fx.lights)

    # -- one batch -------------------------------------------------------------------------
    def make_batch(self, epoch: int, g: int, scenes: np.ndarray, within: np.ndarray) -> PatchBatch:
        """Batch ``g`` of ``epoch``: sample k is centre ``within[k]`` of scene ``scenes[k]``
        (loaded)."""
        sp = self.sampling
        B, b, w = len(scenes), sp.b, sp.w
        patches = np.empty((B, b, b, 1, w, w), np.float32)
        normals = np.empty((B, 3), np.float32)
        pixel = np.empty(B, np.int64)
        theta = np.empty(B, np.float64)
        masks: list = [None] * B
        batch_seed = derive_seed64(self.seed, int(epoch), int(g))
        for s in np.unique(scenes):
            sel = np.flatnonzero(scenes == s)
            sc = self._loaded[int(s)]
            pix = sc.centres[within[sel]]
            gen = [np.random.default_rng([self.seed, int(epoch), int(g), int(s), k])
                   for k in (STREAM_LIGHTS, STREAM_SPARSE, STREAM_ANGLE)]
            light_mask = self._light_masks(gen[0], gen[1], sc, pix)
            th = self._angles(gen[2], len(sel))
            obs, inside = self._cells(sc, pix, th)
            if sc.fx.changes_values:
                m = obs.shape[2]
                flat = obs.reshape(-1, m)
                cell_mask = np.repeat(light_mask, b * b, axis=0)
                flat = apply_capture_effects(flat, cell_mask, sc.fx, batch_seed, int(s))
                obs = np.where(inside[..., None], flat.reshape(obs.shape), np.float32(0.0))
            patches[sel] = patch_maps(obs, sc.map_lights, th, w, light_mask=light_mask)
            normals[sel] = rotated_normals(sc.obs.normals[pix].astype(np.float64), th)
            pixel[sel], theta[sel] = pix, th
            for k, i in enumerate(sel):
                masks[i] = light_mask[k]
        return PatchBatch(patches, normals, np.asarray(scenes, np.int64), pixel, theta, masks)

    def _light_masks(self, rng, sparse_rng, sc: _Scene, pix: np.ndarray) -> np.ndarray:
        sp = self.sampling
        lights = sc.obs.lights

        def draw(n):
            mask, _, _ = sample_light_masks(
                rng, lights, n, sp.min_lights, sp.max_lights, sp.cone_min_deg, sp.cone_max_deg,
                sparse_fraction=sp.sparse_fraction, sparse_min_lights=sp.sparse_min_lights,
                sparse_rng=sparse_rng if sp.sparse_fraction else None,
            )
            return mask

        mask = draw(len(pix))
        for _ in range(DARK_REDRAWS):
            dark = np.flatnonzero(~(np.where(mask, sc.obs.values[pix], 0) > 0).any(axis=1))
            if not len(dark):
                break
            mask[dark] = draw(len(dark))
        return mask

    def _angles(self, rng, n: int) -> np.ndarray:
        R = self.sampling.rotations
        if R == 0:
            return rng.uniform(0.0, 2.0 * np.pi, size=n)
        return rotation_angles(R)[rng.integers(0, R, size=n)]

    def _cells(self, sc: _Scene, pix: np.ndarray, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, b*b, m) float32 observations of the cells and (n, b*b) which are in the mask."""
        sp = self.sampling
        taps, weights = neighbour_taps(sc.index, sc.obs.rows[pix], sc.obs.cols[pix],
                                       patch_offsets(sp.b, th), sp.interpolation)
        obs, _ = gather_taps(sc.obs.values, taps, weights)
        return obs, (taps >= 0).any(axis=-1)


class PatchDataset(ShardDataset):
    """torch ``IterableDataset`` of ready batches ``(patches (B, b, b, 1, w, w) float32,
    normals (B, 3) float32)`` of a :class:`PatchStream`. Use with
    ``DataLoader(ds, batch_size=None)``; :meth:`set_epoch` before each epoch,
    :meth:`set_skip` to resume mid-epoch (this rank's batches already taken). With
    DataLoader workers each makes every ``num_workers``-th batch, and the DataLoader's
    round-robin gives the same sequence as one process."""

    def __init__(self, stream: PatchStream):
        super().__init__(stream)

    def __iter__(self):
        info = get_worker_info()
        part, parts = (0, 1) if info is None else (info.id, info.num_workers)
        for patches, normals in self.stream.iter_epoch(self.epoch, self.skip, part, parts):
            yield torch.from_numpy(patches), torch.from_numpy(normals)
