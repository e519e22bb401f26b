"""Faults on purpose: the kill matrix, and the corruption / lock / disk-full cases.

    nice -n 19 .venv/bin/python -m benchmarks.pipeline.fault_matrix [--seeds 10] [--stages meshes,...,eval]
        [--windows run,writing] [--no-others] [--out benchmarks/results/pipeline/fault_matrix.json]

Kill matrix (``tests/support/faults.py``): for each stage, on the tiny pipeline params
(``tests/pipeline/conftest.py``: one mesh, two 16x16 scenes of 12 lights, 4 training
steps, one worker, so every run is deterministic), with every upstream stage done:

1. run ``python -m cnnps run-stage STAGE`` uninterrupted; hash every file of the stage's
   output folder (hidden temporaries included; only the JSON fields listed in
   ``faults.EXCLUDED_FIELDS`` are left out: timings and the last run's image count);
2. for each seed and kill window, restore the same data folder, start the stage in its
   own process group, SIGKILL the whole group at a seeded moment, re-run the stage to
   completion and compare the hashes: ``identical``, ``different`` (which files) or
   ``rerun-failed`` (its last stderr line).

Windows: ``run`` draws the moment uniformly over the uninterrupted run's whole duration
(interpreter start-up and imports included, what a user's kill sees); ``writing`` from
the moment the output folder appeared to the end (the stretch where files are written).

Then ``tests/faults/cases_corruption.py:
corruption_cases()`` and ``tests/faults/cases_lock.py: concurrent_and_enospc_cases()``
are run and their numbers recorded (``--no-others`` skips them).

Results: ``benchmarks/results/pipeline/fault_matrix.json`` with ``kills: {stage: {tried,
killed, identical, differences, ...}}``, ``corruptions``, ``concurrent_refusals`` and
``enospc``. The kill moments are seeded; what
the stage has done by then depends on the machine's load, so ``files_at_kill`` records
what the kill actually interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import json
import tempfile
import traceback
from pathlib import Path

from benchmarks.harness import ROOT, Stopwatch, result_path, write_result
from tests.support import faults


def _load(path: Path, func: str):
    """``func`` of the module at ``path`` (None when the file does not exist)."""
    if not path.is_file():
        return None
    mod = importlib.import_module(".".join(path.relative_to(ROOT).with_suffix("").parts))
    return getattr(mod, func, None)


def kill_summary(stage: str, ref: faults.Reference, results: list[faults.KillResult]) -> dict:
    diffs = sorted({d for r in results for d in r.differences})
    return {
        "tried": len(results),
        "killed": sum(r.killed for r in results),  # the others had finished before their moment
        "killed_while_writing": sum(r.killed and r.files_at_kill > 0 for r in results),
        "identical": sum(r.outcome == "identical" for r in results),
        "different": sum(r.outcome == "different" for r in results),
        "rerun_failed": sum(r.outcome == "rerun-failed" for r in results),
        "run_failed": sum(r.outcome == "run-failed" for r in results),  # failed on its own before the kill
        "differences": diffs,
        "notes": sorted({r.note for r in results if r.note}),
        "uninterrupted_s": round(ref.seconds, 2),
        "first_output_s": None if ref.first_output_s is None else round(ref.first_output_s, 2),
        "output_files": len(ref.hashes),
        "trials": [r.as_dict() for r in results],
    }


def run_kills(stages, seeds, windows, work_root: Path) -> dict:
    out = {}
    for stage in stages:
        sw = Stopwatch().begin()
        work = work_root / stage
        ref, results = faults.kill_matrix(
            work, stage, seeds, window=windows,
            log=lambda r: print(f"  {r.stage:9s} {r.window:7s} seed {r.seed:2d} kill at {r.kill_at_s:6.2f} s "
                                f"({'killed' if r.killed else 'finished first'}, {r.files_at_kill} files): "
                                f"{r.outcome} {' '.join(r.differences)} {r.rerun_error}", flush=True),
        )
        out[stage] = kill_summary(stage, ref, results)
        s = out[stage]
        print(f"{stage}: {s['identical']}/{s['tried']} identical ({s['killed']} killed, "
              f"{s['killed_while_writing']} while writing; uninterrupted {ref.seconds:.1f} s; "
              f"{sw.elapsed:.0f} s)", flush=True)
    return out


def run_others() -> dict:
    """The corruption and lock / disk-full numbers, from the other helpers' case files."""
    res: dict = {}
    here = ROOT / "tests" / "faults"
    for file, func, keys in (
        ("cases_corruption.py", "corruption_cases", None),
        ("cases_lock.py", "concurrent_and_enospc_cases", ("concurrent_refusals", "enospc")),
    ):
        fn = _load(here / file, func)
        if fn is None:
            print(f"{file}: not there (yet); skipped", flush=True)
            continue
        with Stopwatch() as sw:
            try:
                got = fn()
            except Exception as exc:  # noqa: BLE001 - record it, keep the kill numbers
                traceback.print_exc()
                got = {"error": f"{type(exc).__name__}: {exc}"}
        print(f"{file}: {json.dumps(got)[:2000]} ({sw.seconds:.0f} s)", flush=True)
        if keys is None:
            res["corruptions"] = got
        elif "error" in got:
            res["concurrent_refusals"] = res["enospc"] = got
        else:
            for k in keys:
                res[k] = got.get(k)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10, help="kill moments per stage and window")
    ap.add_argument("--stages", default=",".join(faults.STAGES))
    ap.add_argument("--windows", default="run,writing", help="run, writing or both (comma-separated)")
    ap.add_argument("--no-others", action="store_true", help="skip the corruption and lock / ENOSPC cases")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    a = ap.parse_args()
    stages = [s.strip() for s in a.stages.split(",") if s.strip()]
    windows = tuple(w.strip() for w in a.windows.split(",") if w.strip())
    for s in stages:
        faults.upstream(s)  # unknown stage: ValueError now
    whole = Stopwatch().begin()
    with tempfile.TemporaryDirectory(prefix="cnnps-bench-faults-") as tmp:
        faults.set_template_root(Path(tmp) / "templates")
        kills = run_kills(stages, list(range(a.seeds)), windows, Path(tmp) / "kills")
        others = {} if a.no_others else run_others()
    tried = sum(k["tried"] for k in kills.values())
    identical = sum(k["identical"] for k in kills.values())
    result = {
        "params": "tests/pipeline/conftest.py tiny_params (16x16, 12 lights, 1 sample, 4 train steps, workers 1)",
        "kill_windows": list(windows),
        "seeds_per_stage_and_window": a.seeds,
        "excluded_fields": {f"{s}:{g}": list(f) for (s, g), f in faults.EXCLUDED_FIELDS.items()},
        "kills_total": {"tried": tried, "identical": identical},
        "kills": kills,
        "corruptions": others.get("corruptions"),
        "concurrent_refusals": others.get("concurrent_refusals"),
        "enospc": others.get("enospc"),
        "seconds": round(whole.elapsed, 1),
    }
    print(f"kills: {identical}/{tried} identical re-runs")
    write_result(a.out, __spec__.name, a, result)


if __name__ == "__main__":
    main()
