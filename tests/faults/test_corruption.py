"""Corrupt inputs: every kind of file a stage reads is damaged, and the stage notices.

Each case (:data:`tests.faults.cases_corruption.CASES`) damages one file of a finished
tiny pipeline and re-runs one stage through ``cnnps run-stage``: a stage that owns the
damaged file redoes exactly the damaged part (outputs identical to the undamaged ones);
a stage reading another stage's damaged file stops with one line naming the file and
the fix, exit status 2, its outputs untouched. CI runs every kind once (seed 0, about
20 s after the shared baseline pipeline is built); the full matrix (several seeds per
kind) is :func:`tests.faults.cases_corruption.corruption_cases`.

Two more checks of the same pipeline: every file a stage hands on to another carries a
checksum record that matches it (what the stops rely on), and a stop seen from a
separate ``python -m cnnps`` process is the same one line and exit status 2.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.faults import cases_corruption as cc
from tests.support import faults

pytestmark = [pytest.mark.faults, pytest.mark.blender]  # the baseline pipeline renders

CI_SEED = 0


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    return cc.baseline(tmp_path_factory.mktemp("corruption"))


@pytest.mark.parametrize("case", cc.CASES, ids=cc.case_id)
def test_corruption_is_detected(case, baseline, tmp_path):
    res = cc.run_try(case, CI_SEED, baseline, tmp_path / "work")
    print(res.as_dict())
    assert res.detected, f"{res.case} ({res.how}) not detected: {res.reason}"


def test_every_file_a_stage_hands_on_carries_a_matching_checksum(baseline):
    """What lets a stage find damage it did not write: in a finished pipeline, every file
    of a rendered scene (training and test set) is named in its ``scene.json`` with its
    size and SHA-256, every shard in ``manifest.json``, each scene marker and those
    records carry a checksum of their own content, and ``model.pt`` has its
    ``model.pt.sha256``; every record matches the file as written. (The meshes and
    materials stages keep no checksums: the render stage decodes their files.)"""
    from cnnps.infra.hashing import check_file_record, file_sha256, json_checksum_ok
    from cnnps.io.shards import MANIFEST_INDENT, load_manifest, shard_problem
    from cnnps.models.checkpoint import read_checkpoint
    from cnnps.stages.extract_scene import MARKER_INDENT, MARKER_TIMINGS
    from cnnps.io.capture import SCENE_INDENT
    from cnnps.synth.render.rendered_folder import SCENE_TIMINGS, folder_problems

    data = baseline / "data"
    scenes = [d for root in (data / "render", data / "eval" / "testset") for d in sorted(root.iterdir()) if d.is_dir()]
    assert len(scenes) >= 3, scenes
    for folder in scenes:
        meta = json.loads((folder / "scene.json").read_text())
        assert json_checksum_ok(meta, indent=SCENE_INDENT, skip=SCENE_TIMINGS) is True, folder
        on_disk = {p.name for p in folder.iterdir() if p.is_file()} - {"scene.json"}
        assert set(meta["files"]) == on_disk, f"{folder}: files without a record: {sorted(on_disk - set(meta['files']))}"
        assert all({"bytes", "sha256"} <= set(r) for r in meta["files"].values()), folder
        assert folder_problems(folder, meta) == [], folder

    extract = data / "extract"
    manifest = load_manifest(extract)
    assert json_checksum_ok(manifest, indent=MANIFEST_INDENT) is True
    shards = {s["file"]: s for s in manifest["shards"]}
    assert set(shards) == {p.name for p in extract.glob("shard-*.parquet")}
    for name, record in shards.items():
        assert {"bytes", "sha256"} <= set(record) and shard_problem(extract / name, record) is None, name
    markers = sorted(extract.glob("scene-*.json"))
    assert len(markers) == len(manifest["scenes"]) > 0
    for marker in markers:
        rec = json.loads(marker.read_text())
        assert json_checksum_ok(rec, indent=MARKER_INDENT, skip=MARKER_TIMINGS) is True, marker
        for s in rec["shards"]:
            assert check_file_record(extract / s["file"], s) is None, (marker, s["file"])

    model = data / "train" / "model.pt"
    assert (data / "train" / "model.pt.sha256").read_text() == f"{file_sha256(model)}  model.pt\n"
    read_checkpoint(model)  # checks the sidecar and every zip member's CRC-32


def test_a_stop_from_the_command_line_is_one_line_and_exit_status_2(baseline, tmp_path):
    """The tries above call the command line in this process; here ``python -m cnnps
    run-stage`` runs as its own process on a damaged input: exit status 2 and stderr is
    the one ``cnnps: error:`` line naming the damaged file and the fix, no traceback."""
    (case,) = [c for c in cc.CASES if cc.case_id(c) == "extract/exr-truncated"]
    params_path, data = cc.work_copy(baseline, tmp_path / "work")
    dmg = case.damage(data, np.random.default_rng(CI_SEED))
    res = faults.run_stage(params_path, case.stage)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2, res.stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith(cc.ERROR_PREFIX), res.stderr[-3000:]
    assert str(dmg.path) in lines[0] and f"cnnps run-stage {case.fix[0]}" in lines[0], lines[0]
