"""``--precision auto``: the probe's maps, its choice rule, and its cache."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from cnnps.models import precision_cache as pc
from cnnps.models import precision_probe as pp
from cnnps.models.network import CNNPS


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    return CNNPS(w=32).eval()


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CNNPS_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / pc.CACHE_FILE


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

    def fake(model, device, precision, maps, batches, floor, stoppable=True, passes=None, with_normals=True):
        a = np.radians(error_deg[precision])
        normals = (np.cos(a) * truth + np.sin(a) * perp).astype(np.float32)
        return pp.Trial(float(rates[precision]), batches[-1], {batches[-1]: rates[precision]}, normals)

    monkeypatch.setattr(pp, "_time_candidate", fake)
    monkeypatch.setattr(pp, "bf16_available", lambda device: True)


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
    def fake(model, device, precision, maps, batches, floor, stoppable=True, passes=None, with_normals=True):
        if precision == "fp32":
            return pp.Trial(3000.0, 256, {256: 3000.0}, pp.make_predictor(model, device, "fp32", 256)(maps))
        return pp.Trial(9000.0, 64, {64: 9000.0}, None, "warm-up 0.90 s over the 0.50 s budget")

    monkeypatch.setattr(pp, "_time_candidate", fake)
    monkeypatch.setattr(pp, "bf16_available", lambda device: True)
    choice = pp.probe(net, torch.device("cpu"))
    assert choice.precision == "fp32" and "stopped: warm-up 0.90 s" in choice.reason


def test_a_machine_too_slow_for_the_budget_still_gets_fp32(net, monkeypatch):
    # every candidate looks slower than the per-pass budget (a slow or loaded machine):
    # the reference must still run to the end; it used to be stopped too, and the probe
    # then crashed on its missing normals
    monkeypatch.setattr(pp, "PROBE_BUDGET_S", 1e-9)
    monkeypatch.setattr(pp, "bf16_available", lambda device: True)
    monkeypatch.setattr(pp, "BATCH_SIZES", (16,))  # bf16 stops after its first (slow on AVX2) call
    choice = pp.probe(net, torch.device("cpu"))
    assert choice.precision == "fp32"
    assert choice.error_change_deg == {"fp32": 0.0} and "bf16" in choice.reason and "stopped" in choice.reason


def test_real_probe_is_quick_and_returns_a_candidate(net, cache):
    choice = pp.probe(net, torch.device("cpu"))
    assert choice.precision in pp.CANDIDATES
    assert set(choice.rates) >= {"fp32", "bf16"} and choice.rates["fp32"] > 0
    assert choice.batch_size in pp.BATCH_SIZES and set(choice.batch_rates["fp32"]) == {str(b) for b in pp.BATCH_SIZES}
    if not pp.bf16_available(torch.device("cpu")):  # AVX2 alone: bf16 is not even tried
        assert choice.rates["bf16"] is None and "bf16 skipped (no bf16 kernels" in choice.reason
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
    assert len(keys) == 2 and all(pc.cpu_signature() in k and torch.__version__ in k for k in keys)
    cache.write_text("{not json")  # a damaged cache is ignored and rewritten
    assert not pp.choose_precision(net, torch.device("cpu"), "a" * 64).cached and len(calls) == 3
    assert json.loads(cache.read_text())["version"] == pc.CACHE_VERSION


@pytest.mark.parametrize("rate_by_threads, pick", [({2: 3000.0, 1: 2250.0}, 2),  # the AVX2 EPYC: 2 threads win
                                                     ({2: 3000.0, 1: 3400.0}, 1),  # hyperthreads that only contend
                                                     ({2: 3000.0, 1: 3100.0}, 2)])  # within 5 %: all CPUs
def test_threads_are_chosen_by_timing_the_pick(net, monkeypatch, cache, rate_by_threads, pick):
    _, truth = pp.probe_maps()
    monkeypatch.setattr(pp, "thread_candidates", lambda: [2, 1])

    def fake(model, device, precision, maps, batches, floor, stoppable=True, passes=None, with_normals=True):
        rate = rate_by_threads[torch.get_num_threads()] * (1.0 if precision == "fp32" else 0.1)
        return pp.Trial(rate, batches[-1], {batches[-1]: rate}, truth.copy())

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


# -- load, cache age and the rate a run reports ----------------------------------------------


def _passes(share_by_threads: dict, walls=(0.10, 0.11)) -> list:
    """Timed passes of fp32 at each thread count whose threads got ``share`` of their CPUs."""
    return [pp.TimedPass("fp32", t, 384, w, w * t * share) for t, share in share_by_threads.items() for w in walls]


@pytest.mark.parametrize("passes, loaded, said", [
    (_passes({2: 0.99, 1: 1.0}), False, None),  # a quiet 2-CPU machine: each thread keeps its CPU busy
    (_passes({2: 0.49, 1: 1.0}), True, "2 threads got 49% of their CPUs' time"),  # a job on the other core
    (_passes({2: 0.98, 1: 0.70}), True, "1 thread got 70%"),
    (_passes({2: 1.0}, walls=(0.10, 0.20)), True, "fp32 at 2 threads: passes 2.00x apart"),  # load came or went
    ([pp.TimedPass("fp32", None, 384, 0.01, 0.001)] * 2, False, None),  # a GPU: CPU time says nothing
    ([], False, None),
])
def test_load_is_judged_from_the_cpu_time_the_timed_threads_got(passes, loaded, said):
    note = pp.judge_load(passes)
    assert (note is not None) == loaded
    if said:
        assert said in note


class FakeClocks:
    """Wall and CPU clocks for the real probe: every timed call lasts ``step`` seconds and
    its threads get ``share_by_threads[threads]`` of their CPUs, whatever this machine does."""

    def __init__(self, share_by_threads: dict, step: float = 0.05):
        self.share, self.step, self.wall, self.cpu = share_by_threads, step, 0.0, 0.0

    def wall_clock(self) -> float:
        self.wall += self.step / 2
        return self.wall

    def cpu_clock(self) -> float:
        t = torch.get_num_threads()
        self.cpu += self.step / 2 * t * self.share[t]
        return self.cpu


@pytest.fixture
def two_threads(monkeypatch):
    monkeypatch.setattr(pp, "thread_candidates", lambda: [2, 1])
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("shares, loaded", [({2: 1.0, 1: 1.0}, False), ({2: 0.5, 1: 1.0}, True)])
def test_the_real_probe_records_its_passes_and_a_loaded_one_is_not_cached(net, cache, monkeypatch, two_threads,
                                                                           shares, loaded):
    clocks = FakeClocks(shares)
    monkeypatch.setattr(pp, "wall_clock", clocks.wall_clock)
    monkeypatch.setattr(pp, "cpu_clock", clocks.cpu_clock)
    choice = pp.choose_precision(net, torch.device("cpu"), "d" * 64)
    # every pass took the same time: the tie keeps fp32 and all CPUs
    assert choice.precision == "fp32" and choice.threads == 2
    assert choice.cpu_share == {"2": pytest.approx(shares[2]), "1": pytest.approx(shares[1])}
    assert choice.under_load is loaded and ("not cached" in choice.reason) is loaded
    assert choice.age_seconds is None and not choice.cached
    stored = json.loads(cache.read_text())["choices"] if cache.exists() else {}
    assert (choice.key in stored) is not loaded


def test_a_probe_under_load_serves_its_run_only(net, cache, monkeypatch):
    calls = []

    def loaded(model, device, precision, maps, batches, floor, stoppable=True, passes=None, with_normals=True):
        calls.append(precision)
        passes += _passes({torch.get_num_threads(): 0.48})
        rate = {"fp32": 3000.0, "bf16": 300.0}[precision]
        return pp.Trial(rate, batches[-1], {batches[-1]: rate}, pp.probe_maps()[1])

    monkeypatch.setattr(pp, "_time_candidate", loaded)
    monkeypatch.setattr(pp, "bf16_available", lambda device: True)
    first = pp.choose_precision(net, torch.device("cpu"), "e" * 64)
    assert first.under_load and not first.cached and "under load" in first.reason and "48%" in first.reason
    assert not cache.exists()
    n = len(calls)
    again = pp.choose_precision(net, torch.device("cpu"), "e" * 64)  # nothing cached: probed again
    assert again.under_load and not again.cached and len(calls) == 2 * n


def test_a_cached_answer_has_an_age_and_expires(net, cache, monkeypatch):
    clock = {"now": 1.9e9}
    monkeypatch.setattr(pp, "now", lambda: clock["now"])
    _fake_timings(monkeypatch, {"fp32": 3806.0, "bf16": 7711.0}, {"fp32": 2.0, "bf16": 2.0})
    first = pp.choose_precision(net, torch.device("cpu"), "f" * 64)
    assert not first.cached and first.probed_at == clock["now"] and first.age_seconds is None
    assert not first.under_load
    clock["now"] += 3 * 86400
    again = pp.choose_precision(net, torch.device("cpu"), "f" * 64)
    assert again.cached and again.age_seconds == pytest.approx(3 * 86400) and again.probed_at == first.probed_at
    clock["now"] = first.probed_at + pc.CACHE_MAX_AGE_S + 1
    later = pp.choose_precision(net, torch.device("cpu"), "f" * 64)
    assert not later.cached and later.age_seconds is None and "30.0 days old" in later.reason
    assert json.loads(cache.read_text())["choices"][later.key]["probed_at"] == clock["now"]
    clock["now"] -= 3600  # the clock went back past the probe: no age to trust
    assert not pp.choose_precision(net, torch.device("cpu"), "f" * 64).cached


def test_a_cache_of_the_previous_format_is_probed_again(net, cache, monkeypatch):
    _fake_timings(monkeypatch, {"fp32": 3806.0, "bf16": 7711.0}, {"fp32": 2.0, "bf16": 2.0})
    key = pc.cache_key(torch.device("cpu"), "g" * 64)
    cache.parent.mkdir(parents=True)
    cache.write_text(json.dumps({"version": 1, "choices": {key: {"precision": "fp32", "reason": "old", "threads": 1}}}))
    choice = pp.choose_precision(net, torch.device("cpu"), "g" * 64)
    assert not choice.cached and choice.precision == "bf16"
    assert json.loads(cache.read_text())["version"] == pc.CACHE_VERSION


def test_a_run_far_slower_than_the_probe_drops_the_cached_answer(net, cache, monkeypatch, two_threads):
    calls = []
    real = pp.probe
    monkeypatch.setattr(pp, "probe", lambda *a, **k: calls.append(1) or real(*a, **k))
    _fake_timings(monkeypatch, {"fp32": 3000.0, "bf16": 300.0}, {"fp32": 2.0, "bf16": 2.0})
    choice = pp.choose_precision(net, torch.device("cpu"), "h" * 64)
    assert choice.threads == 2 and choice.thread_rates["2"] == 3000.0 and len(calls) == 1
    assert not pc.report_rate(choice.key, 1500.0)  # half the probe's rate: kept
    assert not pc.report_rate(choice.key, 3500.0)
    for nonsense in (0.0, -1.0, float("nan"), float("inf"), None, "fast"):
        assert not pc.report_rate(choice.key, nonsense)
    assert not pc.report_rate("another machine", 1.0)
    assert pp.choose_precision(net, torch.device("cpu"), "h" * 64).cached and len(calls) == 1
    assert pc.report_rate(choice.key, 1499.0)  # under half: dropped, the next run probes again
    assert choice.key not in json.loads(cache.read_text())["choices"]
    assert not pc.report_rate(choice.key, 1.0)  # nothing left to drop
    assert not pp.choose_precision(net, torch.device("cpu"), "h" * 64).cached and len(calls) == 2


def test_the_rate_of_a_gpu_run_does_not_drop_its_answer(cache):
    key = "some GPU | torch x | cuda | model 0123"
    cache.parent.mkdir(parents=True)
    entry = {"precision": "bf16", "reason": "probe", "rates": {"fp32": 9e4, "bf16": 2e5}, "threads": None,
             "probed_at": 1.9e9, "device": "cuda"}
    cache.write_text(json.dumps({"version": pc.CACHE_VERSION, "choices": {key: entry}}))
    assert not pc.report_rate(key, 10.0)
    assert key in json.loads(cache.read_text())["choices"]
    cpu_key = "some CPU | torch x | cpu | model 0123"
    cache.write_text(json.dumps({"version": pc.CACHE_VERSION, "choices": {cpu_key: {**entry, "device": "cpu"}}}))
    assert pc.report_rate(cpu_key, 0.4 * 2e5)  # no thread rates: the pick's rate is the yardstick


# -- a fair trial: kernel creation is not judged, each precision at its own best batch --------


class SimulatedCPU:
    """A CPU as the probe's clocks see it: a call of a candidate's network costs
    ``creation_s[precision]`` the first time it meets a batch shape (oneDNN creating its
    kernels), then ``maps / rate(precision, batch)`` seconds; its threads keep their CPUs
    busy (a quiet machine). The normals it answers are the probe's true ones."""

    def __init__(self, rate, creation_s):
        self.rate, self.creation_s, self.wall, self.cpu, self.seen = rate, creation_s, 0.0, 0.0, set()
        self.built = 0  # predictors made (each folds the network once)
        self.truth = pp.probe_maps()[1]

    def wall_clock(self) -> float:
        return self.wall

    def cpu_clock(self) -> float:
        return self.cpu

    def predictor(self, model, device, precision, batch_size):
        def run(maps):
            dt = 0.0
            for start in range(0, len(maps), run.batch_size):
                b = min(run.batch_size, len(maps) - start)
                if (precision, b) not in self.seen:
                    self.seen.add((precision, b))
                    dt += self.creation_s[precision]
                dt += b / self.rate(precision, b)
            self.wall += dt
            self.cpu += dt * torch.get_num_threads()
            return self.truth[:len(maps)] if len(maps) <= len(self.truth) else np.resize(self.truth, (len(maps), 3))

        run.batch_size = batch_size  # the probe sets it per batch size, as MapPredictor's
        self.built += 1
        return run


@pytest.fixture
def amx_like(monkeypatch, two_threads):
    """bf16 at 2.4x fp32 at batch 256 (less at 64 and on a single thread), its kernels slow to
    create: a candidate judged on a pass that includes the creation (64 maps in ~0.035 s,
    ~1,800 maps/s) looks slower than fp32."""

    def rate(precision, b):
        if precision == "fp32":
            return 5000.0
        per_thread = 1.0 if torch.get_num_threads() == 2 else 0.6
        return per_thread * (12000.0 if b >= 256 else 9000.0)

    cpu = SimulatedCPU(rate, {"fp32": 0.01, "bf16": 0.03})
    for name in ("wall_clock", "cpu_clock"):
        monkeypatch.setattr(pp, name, getattr(cpu, name))
    monkeypatch.setattr(pp, "make_predictor", cpu.predictor)
    monkeypatch.setattr(pp, "bf16_available", lambda device: True)
    return cpu


def test_bf16_gets_a_fair_trial_at_its_own_best_batch_size(net, cache, amx_like):
    choice = pp.choose_precision(net, torch.device("cpu"), "i" * 64)
    assert choice.precision == "bf16" and choice.batch_size == 256 and choice.threads == 2
    assert choice.rates["bf16"] == pytest.approx(12000.0) and choice.rates["fp32"] == pytest.approx(5000.0)
    assert choice.batch_rates["bf16"] == {"64": pytest.approx(9000.0), "256": pytest.approx(12000.0)}
    assert choice.thread_rates == {"2": pytest.approx(12000.0), "1": pytest.approx(7200.0)}
    # the warm-up calls were slow, the timed calls were not: a quiet machine, so the answer is cached
    assert not choice.under_load and "under load" not in choice.reason
    assert "bf16 12,000 maps/s at batch 256, mean error +0.000 deg vs fp32" in choice.reason
    again = pp.choose_precision(net, torch.device("cpu"), "i" * 64)
    assert again.cached and again.precision == "bf16" and again.batch_size == 256


def test_a_caller_batch_size_is_the_only_one_timed(net, cache, amx_like):
    choice = pp.probe(net, torch.device("cpu"), batch_size=64)
    assert choice.precision == "bf16" and choice.batch_size == 64
    assert choice.batch_rates == {"fp32": {"64": pytest.approx(5000.0)}, "bf16": {"64": pytest.approx(9000.0)}}
    assert "at batch" not in choice.reason


def test_the_probe_stays_about_a_second_on_a_simulated_cpu(net, cache, amx_like):
    pp.probe(net, torch.device("cpu"))
    assert amx_like.wall < 1.0  # simulated seconds the probe's calls took (fp32 at 5,000 maps/s)
    assert amx_like.built == 3  # one folded network per precision, and one for the thread count


def test_a_batch_size_too_slow_to_win_does_not_stop_the_candidate(net, cache, monkeypatch, two_threads):
    """bf16 far slower than fp32 at batch 64 but faster at 256 (say, kernels that want large
    shapes): batch 64 is left after one timed call, and bf16 still wins at 256."""
    cpu = SimulatedCPU(lambda p, b: 5000.0 if p == "fp32" else (2000.0 if b < 256 else 11000.0),
                       {"fp32": 0.0, "bf16": 0.0})
    for name in ("wall_clock", "cpu_clock"):
        monkeypatch.setattr(pp, name, getattr(cpu, name))
    monkeypatch.setattr(pp, "make_predictor", cpu.predictor)
    monkeypatch.setattr(pp, "bf16_available", lambda device: True)
    choice = pp.probe(net, torch.device("cpu"))
    assert choice.precision == "bf16" and choice.batch_size == 256
    assert choice.batch_rates["bf16"] == {"64": pytest.approx(2000.0), "256": pytest.approx(11000.0)}
