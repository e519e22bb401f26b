"""What a training run reads: the extract stage's manifest and its shards (or per-pixel
observation files), opened and checked before the first step (:func:`open_training_data`),
or nothing at all when every map is made per pixel (:func:`pixelwise_only_data`); and the
fewest lights a training map was built from (:func:`fewest_lights`), which prediction warns
below.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from cnnps.infra import storage
from cnnps.infra.errors import InputError
from cnnps.io.observation_store import manifest_observations, verify_observations
from cnnps.io.shards import (
    MANIFEST,
    load_manifest,
    manifest_digest,
    manifest_files,
    shard_path,
    verify_shards,
)
from cnnps.train.observation_data import sampling_of_manifest

from cnnps.synth.light_subsets import RULE


@dataclasses.dataclass(frozen=True)
class TrainingData:
    """The extract stage's output as training reads it."""

    manifest: dict
    manifest_url: Path | str
    manifest_sha256: str  # of the manifest's content (shards.manifest_digest): part of the run key
    w: int
    train_files: list
    val_files: list
    # "maps": Parquet shards of observation maps; "observations": per-pixel observation files
    # (extract.layout: observations), (path, record) pairs, read as patches (cnnps.train.observation_data)
    layout: str = "maps"


OBSERVATIONS = "observations"  # the extract manifest's layout of per-pixel observation files


def fewest_lights(manifest: dict) -> int | None:
    """The fewest lights any training map was built from, read from the extract params the
    manifest records (dense maps: ``min_lights``; with sparse pixels: ``sparse_min_lights``).
    Prediction warns when a capture has fewer images than this."""
    params = manifest.get("params") or {}
    lo = params.get("min_lights")
    if lo is None:
        return None
    if params.get("sparse_fraction"):
        # manifests leave out extract parameters at their defaults: sparse_min_lights is 6 then
        lo = min(int(lo), int(params.get("sparse_min_lights", RULE.sparse_min_lights)))
    return int(lo)


def open_training_data(extract_dir: str | Path, verify: bool = True) -> TrainingData:
    """Read the manifest at ``extract_dir`` (a folder or an fsspec URL) and check it: its
    own checksum (an edited manifest is refused), that it lists training shards, and
    that every shard it lists exists and, with ``verify``, has the size and SHA-256 the
    manifest records (one read of every shard before the first step, small beside an
    epoch of training; docs/reliability.md). Problems raise InputError naming the file and
    the fix. A manifest of per-pixel observation files (``layout: observations``) gives
    their (path, record) pairs as the files, ``layout`` ``observations`` and ``w`` the
    width of the maps its patches are drawn at (:func:`cnnps.train.observation_data.sampling_of_manifest`)."""
    if isinstance(extract_dir, str):
        extract_dir = extract_dir.rstrip("/")
    manifest = load_manifest(extract_dir)
    manifest_url = shard_path(extract_dir, MANIFEST)
    manifest_sha256 = manifest_digest(extract_dir, manifest)
    layout = manifest.get("layout", "maps") if isinstance(manifest, dict) else "maps"
    try:
        if layout == OBSERVATIONS:
            w = sampling_of_manifest(manifest, 1).w
            train_files, val_files = (manifest_observations(extract_dir, manifest, split) for split in ("train", "val"))
            if not train_files:
                raise InputError(str(manifest_url), "lists no training observation files")
            for f, _ in train_files + val_files:
                if not storage.exists(f):
                    raise InputError(str(f), "observation file listed in the manifest is missing; rerun "
                                     "`cnnps run-stage extract`")
            if verify:
                verify_observations(extract_dir, manifest)
            return TrainingData(manifest, manifest_url, manifest_sha256, w, train_files, val_files, layout)
        w = int(manifest["w"])
        train_files = manifest_files(extract_dir, manifest, "train")
        val_files = manifest_files(extract_dir, manifest, "val")
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(str(manifest_url), f"not an extract manifest ({type(exc).__name__}: {exc}); "
                         "rerun `cnnps run-stage extract`") from None
    if not train_files:
        raise InputError(str(manifest_url), "lists no training shards")
    for f in train_files + val_files:
        if not storage.exists(f):
            raise InputError(str(f), "shard listed in the manifest is missing; rerun `cnnps run-stage extract` "
                             "(it redoes the scenes whose shards are missing)")
    if verify:
        verify_shards(extract_dir, manifest)
    return TrainingData(manifest, manifest_url, manifest_sha256, w, train_files, val_files)


PIXELWISE_VAL_ROWS = 10000  # per-pixel validation maps when there are no val shards


def pixelwise_only_data(w: int) -> TrainingData:
    """What training reads when every map is made per pixel (``train.pixelwise.share: 1``): no
    manifest, no shards; ``w`` is the maps' width."""
    return TrainingData({}, "", "pixelwise", int(w), [], [])
