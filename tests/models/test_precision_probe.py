"""``--precision auto``: the probe's maps, its choice rule, and its cache."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from cnnps.models import precision_probe as pp
from cnnps.models.network import CNNPS


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    return CNNPS(w=32).eval()


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CNNPS_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / pp.CACHE_FILE


def test_probe_maps_are_seeded_observation_maps_with_known_normals():
    maps, normals = pp.probe_maps(64)
    again, _ = pp.probe_maps(64)
    assert maps.shape == (64, 32, 32) and maps.dtype == np.float32 and np.array_equal(maps, again)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    assert np.all(normals[:, 2] >= np.cos(np.radians(75)) - 1e-6)
    np.testing.assert_allclose(maps.reshape(64, -1).max(axis=1), 1.0, atol=1e-6)  # each map scaled to 1
    assert not np.array_equal(maps, pp.probe_maps(64, seed=1)[0])


def _fake_timings(monkeypatch, rates: dict, error_deg: dict):
    """Candidates run at ``rates`` maps/s; each of their normals is the true one tilted by
    exactly ``error_deg`` degrees (so their mean error is that many degrees)."""
    _, truth = pp.probe_maps()
    truth = truth.astype(np.float64)
    perp = np.cross(truth, [1.0, 0.0, 0.0])
    perp /= np.linalg.norm(perp, axis=1, keepdims=True)

    def fake(predictor, maps, floor, stoppable=True):
        a = np.radians(error_deg[predictor.precision])
        return float(rates[predictor.precision]), (np.cos(a) * truth + np.sin(a) * perp).astype(np.float32)

    monkeypatch.setattr(pp, "_time_candidate", fake)


@pytest.mark.parametrize(
    "rates, error_deg, pick",
    [
        ({"fp32": 3806.0, "bf16": 7711.0}, {"fp32": 2.0, "bf16": 2.03}, "bf16"),  # the AMD EPYC with AVX-512 BF16
        ({"fp32": 6531.0, "bf16": 3962.0}, {"fp32": 2.0, "bf16": 2.0}, "fp32"),  # the Intel Xeon: bf16 slower
        ({"fp32": 3806.0, "bf16": 7711.0}, {"fp32": 2.0, "bf16": 2.2}, "fp32"),  # faster but not exact enough
        ({"fp32": 4000.0, "bf16": 4100.0}, {"fp32": 2.0, "bf16": 2.0}, "fp32"),  # within 5 %: a tie keeps fp32
    ],
)
def test_the_pick_is_the_fastest_exact_enough_path(net, monkeypatch, rates, error_deg, pick):
    _fake_timings(monkeypatch, rates, error_deg)
    choice = pp.probe(net, torch.device("cpu"))
    assert choice.precision == pick
    assert choice.error_change_deg["bf16"] == pytest.approx(error_deg["bf16"] - error_deg["fp32"], abs=1e-3)
    assert f"bf16 {rates['bf16']:,.0f} maps/s" in choice.reason and "\n" not in choice.reason


def test_a_candidate_stopped_early_is_never_picked(net, monkeypatch):
    monkeypatch.setattr(pp, "_time_candidate", lambda p, maps, floor, stoppable=True: (
        (3000.0, p.net(torch.from_numpy(maps[:, None])).detach().numpy()) if p.precision == "fp32" else (9000.0, None)))
    choice = pp.probe(net, torch.device("cpu"))
    assert choice.precision == "fp32" and "stopped" in choice.reason


def test_a_machine_too_slow_for_the_budget_still_gets_fp32(net, monkeypatch):
    # every candidate looks slower than the per-pass budget (a slow or loaded machine):
    # the reference must still run to the end; it used to be stopped too, and the probe
    # then crashed on its missing normals
    monkeypatch.setattr(pp, "PROBE_BUDGET_S", 1e-9)
    choice = pp.probe(net, torch.device("cpu"))
    assert choice.precision == "fp32"
    assert choice.error_change_deg == {"fp32": 0.0} and "bf16" in choice.reason and "stopped" in choice.reason


def test_real_probe_is_quick_and_returns_a_candidate(net, cache):
    choice = pp.probe(net, torch.device("cpu"))
    assert choice.precision in pp.CANDIDATES
    assert set(choice.rates) >= {"fp32", "bf16"} and choice.rates["fp32"] > 0
    assert choice.probe_seconds > 0  # its duration is a benchmark figure (~1 s on 2 idle cores), not a test bound
    assert "fp32" in choice.error_change_deg and choice.error_change_deg["fp32"] == 0.0


def test_choice_is_cached_per_machine_torch_and_model(net, cache, monkeypatch):
    calls = []
    real = pp.probe

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(pp, "probe", counting)
    _fake_timings(monkeypatch, {"fp32": 3806.0, "bf16": 7711.0}, {"fp32": 2.0, "bf16": 2.0})
    first = pp.choose_precision(net, torch.device("cpu"), "a" * 64)
    assert not first.cached and first.precision == "bf16" and len(calls) == 1
    again = pp.choose_precision(net, torch.device("cpu"), "a" * 64)
    assert again.cached and again.precision == "bf16" and again.reason == first.reason and len(calls) == 1
    pp.choose_precision(net, torch.device("cpu"), "b" * 64)  # another model: probed again
    assert len(calls) == 2
    keys = json.loads(cache.read_text())["choices"]
    assert len(keys) == 2 and all(pp.cpu_signature() in k and torch.__version__ in k for k in keys)
    cache.write_text("{not json")  # a damaged cache is ignored and rewritten
    assert not pp.choose_precision(net, torch.device("cpu"), "a" * 64).cached and len(calls) == 3
    assert json.loads(cache.read_text())["version"] == pp.CACHE_VERSION


@pytest.mark.parametrize("rate_by_threads, pick", [({2: 3000.0, 1: 2250.0}, 2),  # the AVX2 EPYC: 2 threads win
                                                     ({2: 3000.0, 1: 3400.0}, 1),  # hyperthreads that only contend
                                                     ({2: 3000.0, 1: 3100.0}, 2)])  # within 5 %: all CPUs
def test_threads_are_chosen_by_timing_the_pick(net, monkeypatch, cache, rate_by_threads, pick):
    _, truth = pp.probe_maps()
    monkeypatch.setattr(pp, "thread_candidates", lambda: [2, 1])

    def fake(predictor, maps, floor, stoppable=True):
        rate = rate_by_threads[torch.get_num_threads()] * (1.0 if predictor.precision == "fp32" else 0.1)
        return rate, truth.copy()

    monkeypatch.setattr(pp, "_time_candidate", fake)
    before = torch.get_num_threads()
    try:
        choice = pp.choose_precision(net, torch.device("cpu"), "c" * 64)
        assert choice.precision == "fp32" and choice.threads == pick and torch.get_num_threads() == pick
        assert choice.thread_rates == {"2": rate_by_threads[2], "1": rate_by_threads[1]}
        assert f": {pick} threads" in choice.reason
        torch.set_num_threads(1 if pick == 2 else 2)
        again = pp.choose_precision(net, torch.device("cpu"), "c" * 64)  # from the cache: threads set again
        assert again.cached and again.threads == pick and torch.get_num_threads() == pick
    finally:
        torch.set_num_threads(before)
