"""Kill anywhere: SIGKILL a stage's whole process group, re-run it, get the same bytes.

CI subset: one seeded kill per stage, in the stretch where the stage writes its outputs
(a kill during interpreter start-up proves nothing). The full matrix (several seeds per
stage, kill moments over the whole run too) is ``benchmarks/pipeline/fault_matrix.py``.
"""

from __future__ import annotations

import pytest

from tests.support import faults

BLENDER_STAGES = {"render", "extract", "train", "eval"}  # their upstream (or they) render
CI_SEED = 0

pytestmark = pytest.mark.faults


def _params():
    return [
        pytest.param(s, marks=[pytest.mark.blender] if s in BLENDER_STAGES else [], id=s)
        for s in faults.STAGES
    ]


@pytest.mark.parametrize("stage", _params())
def test_killed_stage_reruns_to_identical_outputs(stage, tmp_path):
    ref, (res,) = faults.kill_matrix(tmp_path, stage, [CI_SEED], window="writing")
    print(f"{stage}: reference {ref.seconds:.2f} s, {len(ref.hashes)} files; kill {res.as_dict()}")
    assert ref.hashes, f"the uninterrupted {stage} run wrote nothing"
    assert res.outcome != "rerun-failed", f"re-run after the kill failed: {res.rerun_error}"
    assert res.outcome == "identical", f"outputs differ after kill + re-run: {res.differences}"


def test_hash_outputs_leaves_out_only_the_documented_fields(tmp_path):
    """A timing field does not change the hash; any other byte does; hidden files count."""
    out = tmp_path / "data" / "extract"
    out.mkdir(parents=True)
    (out / "scene-a.json").write_text('{"key": "k", "rows": 3, "seconds": 1.5}')
    (out / "manifest.json").write_text('{"seconds": 1.5}')
    first = faults.hash_outputs(tmp_path / "data", "extract")
    (out / "scene-a.json").write_text('{"rows": 3, "seconds": 9.25, "key": "k"}')
    assert faults.hash_outputs(tmp_path / "data", "extract") == first
    (out / "manifest.json").write_text('{"seconds": 9.25}')  # not an excluded field there
    (out / ".shard-x.parquet.tmp").write_bytes(b"torn")
    diff = faults.differences(first, faults.hash_outputs(tmp_path / "data", "extract"))
    assert diff == ["+.shard-x.parquet.tmp", "~manifest.json"]
    (out / "scene-a.json").write_text('{"key": "k", "rows": 4, "seconds": 1.5}')
    assert "~scene-a.json" in faults.differences(first, faults.hash_outputs(tmp_path / "data", "extract"))


def test_kill_moments_are_seeded_and_inside_the_window():
    a = faults.kill_moments("render", range(5), 10.0, start=4.0)
    assert a == faults.kill_moments("render", range(5), 10.0, start=4.0)
    assert all(4.0 <= t < 10.0 for _, t in a)
    assert len({t for _, t in a}) == 5
    assert a != faults.kill_moments("extract", range(5), 10.0, start=4.0)


def test_torch_payload_digest_ignores_only_the_archive_name(tmp_path):
    torch = pytest.importorskip("torch")
    t = {"w": torch.arange(6.0)}
    torch.save(t, tmp_path / "a.pt")
    torch.save(t, tmp_path / "b.pt")
    torch.save({"w": torch.arange(6.0) + 1}, tmp_path / "c.pt")
    assert faults.file_digest(tmp_path / "a.pt") != faults.file_digest(tmp_path / "b.pt")  # the root folder name
    assert faults.torch_payload_digest(tmp_path / "a.pt") == faults.torch_payload_digest(tmp_path / "b.pt")
    assert faults.torch_payload_digest(tmp_path / "a.pt") != faults.torch_payload_digest(tmp_path / "c.pt")
    assert faults.torch_payload_digest(tmp_path / "nothing.pt") is None
