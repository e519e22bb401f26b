"""Corrupt inputs: every kind of file a stage reads is damaged, and the stage notices.

Each case (:data:`tests.faults.cases_corruption.CASES`) damages one file of a finished
tiny pipeline and re-runs one stage through ``cnnps run-stage``: a stage that owns the
damaged file redoes exactly the damaged part (outputs identical to the undamaged ones);
a stage reading another stage's damaged file stops with one line naming the file and
the fix, exit status 2, its outputs untouched. CI runs every kind once (seed 0, about
20 s after the shared baseline pipeline is built); the full matrix (several seeds per
kind) is :func:`tests.faults.cases_corruption.corruption_cases`.
"""

from __future__ import annotations

import pytest

from tests.faults import cases_corruption as cc

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


def test_every_kind_of_the_issue_is_covered():
    """Issue 14's list: truncated EXR and PNG, NaN / Inf in an EXR, truncated and flipped
    shards, a flipped model.pt, a deleted file a manifest names, hand-edited scene.json and
    manifest.json; and every stage that reads such a file."""
    ids = {cc.case_id(c) for c in cc.CASES}
    for needed in ["extract/exr-truncated", "extract/png-truncated", "extract/exr-nan-inf",
                   "train/shard-truncated", "train/shard-byte-flipped", "eval/model-byte-flipped",
                   "train/shard-deleted", "extract/scene-json-edited", "train/manifest-edited",
                   "render/exr-truncated", "render/scene-json-edited", "render/material-png-truncated",
                   "render/material-npy-truncated", "extract/shard-truncated", "extract/manifest-edited"]:
        assert needed in ids
    assert {c.action for c in cc.CASES} == {"stop", "redo"}
    assert len(ids) == len(cc.CASES)


def test_summary_counts_tries_per_kind():
    results = [cc.TryResult("train/shard-truncated", s, "stop", "extract/x", "", 2, s != 1) for s in range(3)]
    results.append(cc.TryResult("render/exr-truncated", 0, "redo", "render/a/000.exr", "", 0, True))
    assert cc.summarize(results) == {
        "shard-truncated@train": {"stage": "train", "tried": 3, "detected": 2, "action": "stop"},
        "exr-truncated@render": {"stage": "render", "tried": 1, "detected": 1, "action": "redo"},
    }
