"""tools/short_study.py: which checkpoints each weight variant takes, and their weighted mean."""

from __future__ import annotations

import pytest
import torch

from tools.short_study import arm_table, average_weights, variant_weights


def test_variants_take_the_newest_the_tail_and_a_decaying_weight():
    v = variant_weights([250, 500, 750, 1000], swa_from=600, half_life=250)
    assert v["last"] == {1000: 1.0}
    assert v["swa"] == {750: 1.0, 1000: 1.0}  # the checkpoints from swa_from on, equally
    assert v["ema"] == pytest.approx({1000: 1.0, 750: 0.5, 500: 0.25, 250: 0.125})  # halves each half-life
    assert variant_weights([250, 500], swa_from=900, half_life=100)["swa"] == {500: 1.0}  # none that late: the last


def test_the_weighted_mean_matches_by_hand():
    states = {1: {"a": torch.tensor([1.0, 2.0])}, 2: {"a": torch.tensor([3.0, 6.0])}}
    mean = average_weights([1, 2], [1.0, 3.0], states.__getitem__)
    assert torch.allclose(mean["a"], torch.tensor([2.5, 5.0], dtype=torch.float64))


def test_the_arm_table_means_seeds_and_ranks_proxies(tmp_path):
    import json

    def row(proxy, dev):
        return {"proxy_mean": proxy, "ball": proxy + 1, "lean_40-55": 0.0, "dev_real": dev}

    rows = {"r1": {"last": row(2.0, 8.0), "ema": row(1.5, 7.5)}, "r2": {"last": row(3.0, 9.0), "ema": row(2.5, 8.5)}}
    for name, r in rows.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "short_scores.json").write_text(json.dumps({"rows": r}))
    t = arm_table({"a": ["r1", "r2", "r3"]}, tmp_path)
    assert t["missing"] == ["r3"]
    assert t["arms"]["a"]["last"]["dev_real"] == (8.5, 0.5, 2)  # mean, half the range, seeds
    assert t["arms"]["a"]["ema"]["proxy_mean"] == (2.0, 0.5, 2)
    assert t["predicts_dev_real"]["proxy_mean"]["spearman"] == pytest.approx(1.0)  # dev-real = proxy + 6 here
    assert "lean_40-55" not in t["predicts_dev_real"]  # constant: no correlation
