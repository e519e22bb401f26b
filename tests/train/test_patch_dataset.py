"""The patch loader: b = 1 is the extract stage's row, training and prediction patches
agree, realism per cell, determinism and resuming by skipping batches."""

import numpy as np
import pytest
import torch

from cnnps.infra.errors import ConfigError
from cnnps.io.capture import load_capture
from cnnps.io.observation_store import observation_path, write_capture_observations
from cnnps.ps.patches import capture_patches
from cnnps.ps.rotation import rotate_z, rotation_angles
from cnnps.synth.training_samples import build_rows
from cnnps.train.patch_dataset import PatchDataset, PatchSampling, PatchStream
from tests.support.renders import make_render_dir

W = 16
SUBSETS = dict(min_lights=10, max_lights=40, w=W)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    data = make_render_dir(tmp_path_factory.mktemp("pd"), n_scenes=3, size=20, m=50)
    out = data / "obs"
    pairs = []
    for folder in sorted((data / "render").iterdir()):
        rec = write_capture_observations(out, folder.name, load_capture(folder), scene_key=f"key-{folder.name}")
        pairs.append((observation_path(out, folder.name), rec))
    return pairs


def _stream(files, batch=16, seed=3, **kw):
    return PatchStream(files, PatchSampling(**{**SUBSETS, **kw}), batch, seed=seed, scenes_in_memory=2)


def _batches(it):
    return [(p.copy(), n.copy()) for p, n in it]


def test_b1_sample_is_the_extract_stages_row(files):
    from cnnps.io.observation_store import read_observations

    stream = _stream(files, b=1)
    scenes = [read_observations(p) for p, _ in files]
    checked = 0
    for batch in stream.iter_batches(0):
        for k in range(len(batch.scene)):
            obs = scenes[batch.scene[k]]
            p = batch.pixel[k]
            I = obs.values[p : p + 1].astype(np.float32)
            maps, rot_n = build_rows(I, obs.normals[p : p + 1].astype(np.float64), obs.lights,
                                     batch.light_mask[k][None], np.array([batch.theta[k]]), W)
            assert np.array_equal(batch.patches[k, 0, 0, 0].astype(np.float16).view(np.uint16), maps[0, 0].view(np.uint16))
            assert np.array_equal(batch.normals[k], rot_n[0, 0])
            checked += 1
    assert checked == stream.batches_per_epoch(0) * 16 > 100
    assert set(np.unique(batch.theta)) <= set(rotation_angles(10))


def test_training_patches_equal_prediction_patches(files):
    """All lights (cone 180 degrees, k = m) and a right angle: a training sample is the
    prediction patch of its centre, the same cells and edge rule."""
    stream = _stream(files, b=3, rotations=4, min_lights=50, max_lights=50, cone_min_deg=180.0, cone_max_deg=180.0)
    from cnnps.io.observation_store import read_observations

    batch = next(stream.iter_batches(1))
    assert all(m.all() for m in batch.light_mask)
    for k in range(len(batch.scene)):
        obs = read_observations(files[batch.scene[k]][0])
        p = int(batch.pixel[k])
        want = capture_patches(obs.values, obs.mask, obs.lights, p, p + 1, b=3, w=W, angles=[batch.theta[k]])
        assert np.array_equal(batch.patches[k], want[0, 0])
        want_n = rotate_z(obs.normals[p].astype(np.float64), batch.theta[k]).astype(np.float32)
        assert np.array_equal(batch.normals[k], want_n)


def test_same_seed_same_batches_and_resume_by_skipping(files):
    full = _batches(_stream(files, b=3, ambient_max=0.2, noise_max=0.05, rotations=0).iter_epoch(2))
    again = _batches(_stream(files, b=3, ambient_max=0.2, noise_max=0.05, rotations=0).iter_epoch(2))
    assert len(full) == _stream(files).batches_per_epoch(2) >= 6
    for (p, n), (q, o) in zip(full, again):
        assert np.array_equal(p, q) and np.array_equal(n, o)
    resumed = _batches(_stream(files, b=3, ambient_max=0.2, noise_max=0.05, rotations=0).iter_epoch(2, skip_batches=4))
    assert len(resumed) == len(full) - 4
    assert all(np.array_equal(p, q) for (p, _), (q, _) in zip(resumed, full[4:]))
    other = _batches(_stream(files, b=3, seed=4, ambient_max=0.2, noise_max=0.05, rotations=0).iter_epoch(2))
    assert not np.array_equal(other[0][0], full[0][0])
    # two DataLoader workers' shares interleave into the same sequence
    stream = _stream(files, b=3, ambient_max=0.2, noise_max=0.05, rotations=0)
    parts = [_batches(stream.iter_epoch(2, 1, part, 2)) for part in (0, 1)]
    merged = [parts[i % 2][i // 2] for i in range(len(full) - 1)]
    assert all(np.array_equal(p, q) for (p, _), (q, _) in zip(merged, full[1:]))
    # two ranks split the batches
    sampling = PatchSampling(b=3, ambient_max=0.2, noise_max=0.05, rotations=0, **SUBSETS)
    ranks = [PatchStream(files, sampling, 16, seed=3, scenes_in_memory=2, rank=r, world_size=2) for r in (0, 1)]
    assert ranks[0].batches_per_epoch(2) == ranks[1].batches_per_epoch(2) == len(full) // 2
    odd = _batches(ranks[1].iter_epoch(2))
    assert len(odd) == len(full) // 2 and np.array_equal(odd[0][0], full[1][0])


def test_realism_applies_per_cell_and_keeps_the_edge_rule(files):
    from cnnps.io.observation_store import read_observations
    from cnnps.ps.patches import patch_offsets

    kw = dict(b=5, rotations=4)  # right angles: every cell is one whole pixel
    plain = next(_stream(files, **kw).iter_batches(0))
    lit = next(_stream(files, ambient_max=0.3, black_level_max=0.05, noise_max=0.05, **kw).iter_batches(0))
    assert np.array_equal(plain.pixel, lit.pixel) and np.array_equal(plain.theta, lit.theta)
    inside = np.zeros((16, 25), bool)
    for k in range(16):
        obs = read_observations(files[plain.scene[k]][0])
        pos = np.array([obs.rows[plain.pixel[k]], obs.cols[plain.pixel[k]]]) + patch_offsets(5, [plain.theta[k]])[0]
        pos = pos.astype(int)
        ok = (pos >= 0).all(1) & (pos[:, 0] < obs.height) & (pos[:, 1] < obs.width)
        inside[k, ok] = obs.mask[pos[ok, 0], pos[ok, 1]]
    assert (~inside).any() and inside.any()
    cells = lit.patches.reshape(16, 25, -1)
    assert not cells[~inside].any()  # black level, ambient and noise never light a cell outside the mask
    assert cells[inside].max(axis=1).min() == 1.0  # every inside cell is lit (the black level alone does)
    base = plain.patches.reshape(16, 25, -1)
    assert not base[~inside].any() and not np.array_equal(cells[inside], base[inside])
    assert (cells[inside] > 0).mean() > (base[inside] > 0).mean()  # ambient: fewer dark cells


def test_torch_dataset_and_options(files):
    ds = PatchDataset(_stream(files, b=3))
    ds.set_epoch(1)
    ds.set_skip(2)
    patches, normals = next(iter(torch.utils.data.DataLoader(ds, batch_size=None)))
    assert patches.shape == (16, 3, 3, 1, W, W) and patches.dtype == torch.float32 and normals.shape == (16, 3)
    want = next(_stream(files, b=3).iter_epoch(1, 2))
    assert np.array_equal(patches.numpy(), want[0])
    # two DataLoader worker processes: the same batches in the same order
    two = [p for p, _ in torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2)]
    one = [p for p, _ in _stream(files, b=3).iter_epoch(1, 2)]
    assert len(two) == len(one) and all(np.array_equal(a.numpy(), b) for a, b in zip(two, one))
    for bad in (dict(b=2), dict(b=0), dict(interpolation="cubic"), dict(rotations=-1)):
        with pytest.raises(ConfigError, match="patch"):
            PatchSampling(**bad)
    assert PatchSampling.from_settings(type("P", (), {"min_lights": 7, "rotations": 4})(), b=5) == \
        PatchSampling(min_lights=7, rotations=4, b=5)
