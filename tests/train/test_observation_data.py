"""The patch loader as the training loop reads it (cnnps.train.observation_data): sampling
from the manifest's extract params, cells as channels, epochs of equal steps, validation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cnnps.io.observation_store import manifest_observations
from cnnps.io.shards import load_manifest
from cnnps.train.observation_data import (
    PatchChannels,
    load_patch_val,
    sampling_of_manifest,
    steps_per_epoch,
    stream_rows,
)
from cnnps.train.patch_dataset import PatchSampling, PatchStream
from tests.support.observations import make_observation_extract


def test_sampling_is_the_extract_params_the_manifest_records():
    man = {"w": 12, "params": {"w": 12, "min_lights": 8, "max_lights": 20, "rotations": 3, "ambient_max": 0.1,
                               "quantize_bits": [12, 10], "val_fraction": 0.2, "seed": 4, "format": 1}}
    s = sampling_of_manifest(man, b=5)
    assert (s.b, s.w, s.min_lights, s.max_lights, s.rotations, s.ambient_max) == (5, 12, 8, 20, 3, 0.1)
    assert s.quantize_bits == (10, 12) and s.noise_max == 0.0 and s.interpolation == "bilinear"
    assert sampling_of_manifest({"params": {"w": 24}}, b=1).w == 24  # the params' w without a top-level one
    assert sampling_of_manifest({}, b=3) == PatchSampling(b=3)  # nothing recorded: extract's defaults


def test_every_epoch_takes_the_fewest_batches_any_epoch_holds():
    """Scenes of 1, 1 and 2 centres, two in memory, batches of 2: an epoch whose first window
    pairs the two 1-centre scenes holds 2 batches (2 // 2 + 2 // 2), any other 1 (3 // 2 + 1 // 2)."""
    files = [(f"s{i}.cnnobs", {"rows": n}) for i, n in enumerate((1, 1, 2))]
    stream = PatchStream(files, PatchSampling(b=1, w=8), 2, seed=2, scenes_in_memory=2)
    assert [stream.batches_per_epoch(e) for e in range(3)] == [2, 1, 1]  # seed 2's scene orders
    assert steps_per_epoch(stream, 1) == 2 and steps_per_epoch(stream, 3) == 1
    assert stream_rows(stream) == 4


@pytest.fixture(scope="module")
def extract_dir(tmp_path_factory):
    root = make_observation_extract(tmp_path_factory.mktemp("od"), n_scenes=3, size=16, m=30, w=8,
                                    min_lights=5, max_lights=20, rotations=4)
    return root / "extract"


def test_patches_are_the_cells_as_channels_and_resume_by_skipping(extract_dir):
    man = load_manifest(extract_dir)
    files = manifest_observations(extract_dir, man, "train")
    stream = PatchStream(files, sampling_of_manifest(man, 3), 8, seed=2)
    want = [(p.copy(), n.copy()) for p, n in stream.iter_epoch(1)]
    ds = PatchChannels(stream)
    ds.set_epoch(1)
    got = list(ds)
    assert len(got) == len(want) >= 4
    for (maps, normals), (p, n) in zip(got, want):
        assert maps.shape == (8, 9, 8, 8) and maps.dtype == torch.float32
        for cell in range(9):
            assert np.array_equal(maps[:, cell].numpy(), p[:, cell // 3, cell % 3, 0])  # row-major cells
        assert np.array_equal(normals.numpy(), n)
    ds.set_skip(3)
    assert all(torch.equal(a, b) for (a, _), (b, _) in zip(ds, got[3:]))


def test_validation_is_a_fixed_sample_of_the_val_scenes(extract_dir):
    man = load_manifest(extract_dir)
    files = manifest_observations(extract_dir, man, "val")
    maps, normals = load_patch_val(files, sampling_of_manifest(man, 3), 20, seed=6)
    again, _ = load_patch_val(files, sampling_of_manifest(man, 3), 20, seed=6)
    assert maps.shape == (20, 9, 8, 8) and maps.dtype == np.float16 and np.array_equal(maps, again)
    first, n0 = next(PatchStream(files, sampling_of_manifest(man, 3), 20, seed=7).iter_epoch(0))
    assert np.array_equal(maps, first.reshape(20, 9, 8, 8).astype(np.float16)) and np.array_equal(normals, n0)
    grey, _ = load_patch_val(files, sampling_of_manifest(man, 1), 20, seed=6)
    assert grey.shape == (20, 8, 8)  # b = 1: the maps a grey model's validation takes
    none, nn = load_patch_val([], sampling_of_manifest(man, 3), 20, seed=6)
    assert none.shape == (0, 9, 8, 8) and nn.shape == (0, 3)
