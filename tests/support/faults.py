"""Fault injection helpers shared by ``tests/faults/`` and ``benchmarks/pipeline/fault_matrix.py``.

A *stage folder* is a folder holding ``params.yaml`` (the tiny pipeline params of
``tests/pipeline/conftest.py``: one 16x16 scene pair, one worker, so every run is
deterministic), ``meshes_in/ball.obj`` and ``data/`` with every stage *upstream* of the
one under test already done. Upstream outputs are built once per process (in a temporary
template folder, by real ``cnnps run-stage`` subprocesses) and copied.

API (stable: the lock and checksums helpers import it):

- :func:`stage_folder` ``(tmp_path, stage) -> (params_path, data_dir)``
- :func:`hash_outputs` ``(data_dir, stage) -> {relative path: sha256}`` over every file of
  the stage's output folder (hidden files included: a temporary file left behind is a
  difference), with the documented exclusions of :data:`EXCLUDED_FIELDS`
- :func:`run_stage` ``(params_path, stage, data_dir=None) -> CompletedProcess``
- :func:`kill_stage_at` ``(params_path, stage, seconds) -> bool``: start the stage in its own
  process group, SIGKILL the whole group after ``seconds``; True when it was still running

The kill matrix: :func:`kill_matrix` ``(work, stage, seeds, window=...)`` runs the stage
uninterrupted (:func:`reference_run`: hashes and duration), then per seed restores the
same data folder, kills the stage at a seeded moment (:func:`kill_moments`), re-runs it
and compares (:class:`KillResult`: identical / different (which files) / rerun-failed).
Everything runs at the same data path, so paths a stage writes into its outputs agree.
Stages run as ``python -m cnnps run-stage`` with ``OMP_NUM_THREADS=MKL_NUM_THREADS=1``
(unless set) and ``TQDM_DISABLE=1``, stderr to a temporary file.
A ``.pt`` file that differs only in the name of its zip's root folder (``torch.save(obj,
path)`` names it after the file, i.e. an atomic write's random temporary name) is flagged
by :func:`torch_payload_digest` (``KillResult.note``): a byte difference all the same.

Exclusions (:data:`EXCLUDED_FIELDS`). Only JSON *fields* are excluded, never whole files;
a file with an excluded field is hashed as its JSON with those fields removed (keys
sorted), every other file by its bytes. Each excluded field records how long a run took or
what the *last* run did, not what the outputs are:

- render ``<scene>/scene.json`` and eval ``testset/<capture>/scene.json``:
  ``render_seconds`` (wall time) and ``images_rendered_last_run`` (a resumed render renders
  only the missing images, so this count is smaller after a kill);
- extract ``scene-<id>.json``: ``seconds`` (wall time of the scene's extraction);
- train ``metrics.json``: ``samples_per_s``, ``seconds`` (speed and time split of the last call) and
  ``precision_source`` (how the last call got the run's precision: a probe, this machine's
  cached answer or, resumed, the checkpoint; the choice itself, ``precision_choice``, is
  compared);
- eval ``metrics.json``: ``seconds`` (wall time).

A record with an excluded field that carries a ``checksum`` of its own content
(:func:`cnnps.infra.hashing.json_checksum`) is also hashed without that entry, but only
when the entry is valid for the record as written: it hashes the excluded fields too,
so it must change with them, while a wrong checksum still shows as a difference.
"""

from __future__ import annotations

import atexit
import fnmatch
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from cnnps.stages import STAGES

REPO = Path(__file__).resolve().parents[2]
OUTPUT_DIRS = {s: s for s in STAGES}  # data_dir/<folder> each stage writes (and only it)

# (stage, glob of the path relative to the stage's output folder) -> JSON fields left out
EXCLUDED_FIELDS: dict[tuple[str, str], tuple[str, ...]] = {
    ("render", "*/scene.json"): ("render_seconds", "images_rendered_last_run"),
    ("extract", "scene-*.json"): ("seconds",),
    ("train", "metrics.json"): ("samples_per_s", "seconds", "precision_source"),
    ("eval", "metrics.json"): ("seconds",),
    ("eval", "testset/*/scene.json"): ("render_seconds", "images_rendered_last_run"),
}

ARCHIVE_NAME_ONLY = "torch archive name only (same tensors; torch.save named the zip's root folder after the temporary file)"
CHECKSUM = "checksum"  # a record's self-checksum entry (cnnps.infra.hashing.json_checksum)
STAGE_TIMEOUT_S = 900  # one tiny stage on a loaded 2-core machine takes seconds; this only stops a hang


def tiny_params_dict(mesh_dir: Path, data_dir: Path) -> dict:
    """The tiny pipeline params (tests/pipeline/conftest.py) with an absolute data folder."""
    from tests.pipeline.conftest import tiny_params

    params = tiny_params(Path(mesh_dir))
    params["data_dir"] = str(data_dir)
    return params


def write_stage_params(root: Path) -> tuple[Path, Path]:
    """``root/params.yaml`` + ``root/meshes_in/ball.obj``; returns (params_path, data_dir)."""
    from tests.support.meshes import write_tiny_mesh

    root = Path(root)
    mesh_dir = root / "meshes_in"
    if not (mesh_dir / "ball.obj").is_file():
        write_tiny_mesh(mesh_dir / "ball.obj")
    data_dir = root / "data"
    params_path = root / "params.yaml"
    params_path.write_text(yaml.safe_dump(tiny_params_dict(mesh_dir, data_dir), sort_keys=False))
    return params_path, data_dir


# ----------------------------------------------------------------------------- running


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("OMP_NUM_THREADS", "1")  # deterministic and polite on a shared machine
    env.setdefault("MKL_NUM_THREADS", "1")
    env["TQDM_DISABLE"] = "1"  # no progress bars in captured output
    return env


def stage_command(params_path: Path, stage: str, data_dir: Path | None = None) -> list[str]:
    cmd = [sys.executable, "-m", "cnnps", "run-stage", stage, "--params", str(params_path)]
    if data_dir is not None:
        cmd += ["--data-dir", str(data_dir)]
    return cmd


def run_stage(params_path: str | Path, stage: str, data_dir: str | Path | None = None,
              timeout: float = STAGE_TIMEOUT_S) -> subprocess.CompletedProcess:
    """``python -m cnnps run-stage STAGE --params PARAMS`` to completion (output captured)."""
    params_path = Path(params_path)
    return subprocess.run(
        stage_command(params_path, stage, None if data_dir is None else Path(data_dir)),
        cwd=params_path.parent, env=_env(), capture_output=True, text=True, timeout=timeout, check=False,
    )


def start_stage(params_path: str | Path, stage: str, data_dir: str | Path | None = None) -> subprocess.Popen:
    """Start the stage in a new session (its own process group: killpg reaches every child).

    Its stderr goes to an unnamed temporary file (``proc.stderr``; :func:`stderr_of`), not
    a pipe, so a chatty stage never blocks on a full pipe nobody reads."""
    params_path = Path(params_path)
    err = tempfile.TemporaryFile()  # noqa: SIM115 - outlives this function: proc.stderr
    try:
        proc = subprocess.Popen(
            stage_command(params_path, stage, None if data_dir is None else Path(data_dir)),
            cwd=params_path.parent, env=_env(), stdout=subprocess.DEVNULL, stderr=err,
            start_new_session=True,
        )
    except BaseException:
        err.close()
        raise
    proc.stderr = err
    return proc


def stderr_of(proc: subprocess.Popen) -> str:
    """What a :func:`start_stage` process wrote to stderr (after it exited); closes the file."""
    f = proc.stderr
    if f is None or f.closed:
        return ""
    f.seek(0)
    text = f.read().decode(errors="replace")
    f.close()
    return text


def kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL ``proc``'s whole process group (it leads it: started with start_new_session)."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def params_data_dir(params_path: str | Path) -> Path:
    """The data folder a params file names (relative to its folder, the stage's cwd)."""
    params_path = Path(params_path)
    d = Path((yaml.safe_load(params_path.read_text()) or {}).get("data_dir", "data"))
    return d if d.is_absolute() else params_path.parent / d


def has_output_file(data_dir: Path, stage: str) -> bool:
    """Whether the stage's output folder holds a file yet (hidden temporaries included)."""
    out = Path(data_dir) / OUTPUT_DIRS[stage]
    try:
        return any(p.is_file() for p in out.rglob("*"))
    except OSError:  # a folder renamed or removed while walking it
        return False


def kill_stage_at(params_path: str | Path, stage: str, seconds: float, data_dir: str | Path | None = None,
                  after_first_output: bool = False) -> bool:
    """Run the stage; SIGKILL its process group ``seconds`` after the start (or, with
    ``after_first_output``, after the first file appeared in its output folder).

    Returns True when it was killed, False when it had already exited (then it must have
    succeeded: a failure raises AssertionError with its stderr).
    """
    proc = start_stage(params_path, stage, data_dir)
    try:
        if after_first_output:
            out_data = Path(data_dir) if data_dir is not None else params_data_dir(params_path)
            while proc.poll() is None and not has_output_file(out_data, stage):
                time.sleep(0.01)
        proc.wait(timeout=max(0.0, seconds))
    except subprocess.TimeoutExpired:
        kill_group(proc)
        stderr_of(proc)
        return True
    err = stderr_of(proc)
    kill_group(proc)  # any straggler of the group
    assert proc.returncode == 0, f"stage {stage} failed before its kill moment (exit {proc.returncode}):\n{err[-3000:]}"
    return False


def check_run(params_path: Path, stage: str, data_dir: Path | None = None) -> subprocess.CompletedProcess:
    """:func:`run_stage`, failing with the stage's stderr when it does not exit 0."""
    res = run_stage(params_path, stage, data_dir)
    if res.returncode != 0:
        raise AssertionError(f"cnnps run-stage {stage} exited {res.returncode}:\n{res.stderr[-3000:]}")
    return res


# ----------------------------------------------------------------------------- folders


_TEMPLATES: dict[str, Path] = {}  # stage -> a folder whose data/ holds every stage up to and including it
_TEMPLATE_ROOT: Path | None = None


def set_template_root(path: str | Path) -> None:
    """Build the upstream templates under ``path`` (e.g. a pytest session folder) from now on."""
    global _TEMPLATE_ROOT
    _TEMPLATE_ROOT = Path(path)
    _TEMPLATES.clear()


def _template_root() -> Path:
    global _TEMPLATE_ROOT
    if _TEMPLATE_ROOT is None:
        _TEMPLATE_ROOT = Path(tempfile.mkdtemp(prefix="cnnps-faults-"))
        atexit.register(shutil.rmtree, _TEMPLATE_ROOT, True)
    return _TEMPLATE_ROOT


def upstream(stage: str) -> tuple[str, ...]:
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; stages are {', '.join(STAGES)}")
    return STAGES[: STAGES.index(stage)]


def _done_through(stage: str) -> Path:
    """A template folder whose data/ holds the outputs of every stage up to ``stage``."""
    if stage in _TEMPLATES:
        return _TEMPLATES[stage]
    root = _template_root() / f"through-{stage}"
    if root.exists():
        shutil.rmtree(root)  # a build that failed half-way
    before = upstream(stage)
    if before:
        prev = _done_through(before[-1])
        shutil.copytree(prev / "data", root / "data", symlinks=True)
    params_path, _ = write_stage_params(root)
    check_run(params_path, stage)
    _TEMPLATES[stage] = root
    return root


def _register_template(stage: str, root: Path) -> None:
    """Keep a copy of ``root`` (params.yaml, meshes_in/, data/ done through ``stage``: an
    uninterrupted run) as the upstream template of the next stages, unless there is one."""
    if stage in _TEMPLATES:
        return
    dest = _template_root() / f"through-{stage}"
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(Path(root) / "data", dest / "data", symlinks=True)
    write_stage_params(dest)
    _TEMPLATES[stage] = dest


def stage_folder(tmp_path: str | Path, stage: str) -> tuple[Path, Path]:
    """``tmp_path/params.yaml`` and ``tmp_path/data`` with every stage before ``stage`` done.

    Returns (params_path, data_dir); ``stage``'s own output folder does not exist yet.
    """
    tmp_path = Path(tmp_path)
    before = upstream(stage)
    params_path, data_dir = write_stage_params(tmp_path)
    if data_dir.exists():
        shutil.rmtree(data_dir)
    if before:
        shutil.copytree(_done_through(before[-1]) / "data", data_dir, symlinks=True)
    else:
        data_dir.mkdir(parents=True)
    return params_path, data_dir


def reset_stage(data_dir: Path, stage: str, template_data: Path) -> None:
    """Make ``data_dir`` a copy of ``template_data`` again (the stage's output removed)."""
    if data_dir.exists():
        shutil.rmtree(data_dir)
    shutil.copytree(template_data, data_dir, symlinks=True)
    out = data_dir / OUTPUT_DIRS[stage]
    if out.exists():
        shutil.rmtree(out)


# ----------------------------------------------------------------------------- hashing


def excluded_fields(stage: str, rel: str) -> tuple[str, ...]:
    out: tuple[str, ...] = ()
    for (s, pattern), fields in EXCLUDED_FIELDS.items():
        if s == stage and fnmatch.fnmatchcase(rel, pattern):
            out += fields
    return out


def _checksum_is_valid(obj: dict) -> bool:
    """Whether ``obj["checksum"]`` is the self-checksum the stages write
    (:func:`cnnps.infra.hashing.json_checksum`, over the record as written, at any of the
    indents the stages use)."""
    try:
        from cnnps.infra.hashing import json_checksum
    except ImportError:  # a checkout without checksums: nothing to verify
        return False
    for indent in (2, 1, None):
        try:
            if json_checksum(obj, indent=indent) == obj.get(CHECKSUM):
                return True
        except TypeError:
            return False
    return False


def file_digest(path: Path, drop: tuple[str, ...] = ()) -> str:
    """sha256 of the file's bytes; with ``drop``, of its JSON without those fields (keys
    sorted), and without its ``checksum`` entry when that entry is valid (it hashes the
    dropped fields too, so it changes with them; an invalid one stays in and differs)."""
    data = path.read_bytes()
    if drop:
        try:
            obj = json.loads(data)
        except ValueError:
            obj = None  # not JSON (e.g. torn): hashed by its bytes, so it shows as a difference
        if isinstance(obj, dict):
            valid = CHECKSUM in obj and _checksum_is_valid(obj)
            for f in drop + ((CHECKSUM,) if valid else ()):
                obj.pop(f, None)
            data = json.dumps(obj, sort_keys=True).encode()
    return hashlib.sha256(data).hexdigest()


def hash_outputs(data_dir: str | Path, stage: str) -> dict[str, str]:
    """{path relative to the stage's output folder: sha256} for every file in it (hidden
    ones included), with the JSON fields of :data:`EXCLUDED_FIELDS` left out."""
    root = Path(data_dir) / OUTPUT_DIRS[stage]
    out: dict[str, str] = {}
    if not root.is_dir():
        return out
    for dirpath, dirs, files in os.walk(root):
        dirs.sort()
        for name in sorted(files):
            p = Path(dirpath) / name
            rel = p.relative_to(root).as_posix()
            out[rel] = file_digest(p, excluded_fields(stage, rel))
    return out


def torch_payload_digest(path: Path) -> str | None:
    """sha256 of a ``torch.save`` zip's members with the archive's root folder name left out
    (None when ``path`` is no zip). ``torch.save(obj, path)`` names that folder after the
    file it writes, which for an atomic write is a random temporary name: two saves of
    the same tensors then differ in bytes; this tells that case from other differences."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            h = hashlib.sha256()
            for info in z.infolist():
                h.update(info.filename.split("/", 1)[-1].encode() + b"\0")
                h.update(z.read(info))
            return h.hexdigest()
    except (OSError, zipfile.BadZipFile):
        return None


def torch_payload_digests(data_dir: str | Path, stage: str) -> dict[str, str | None]:
    root = Path(data_dir) / OUTPUT_DIRS[stage]
    return {p.relative_to(root).as_posix(): torch_payload_digest(p) for p in sorted(root.rglob("*.pt"))} if root.is_dir() else {}


def differences(expected: dict[str, str], got: dict[str, str]) -> list[str]:
    """Paths that differ: ``-path`` missing, ``+path`` extra, ``~path`` other bytes."""
    diff = [f"-{p}" for p in sorted(set(expected) - set(got))]
    diff += [f"+{p}" for p in sorted(set(got) - set(expected))]
    diff += [f"~{p}" for p in sorted(set(expected) & set(got)) if expected[p] != got[p]]
    return diff


# ----------------------------------------------------------------------------- the matrix


@dataclass
class Reference:
    """An uninterrupted run of one stage: its output hashes and how long it took."""

    stage: str
    hashes: dict[str, str]
    seconds: float
    first_output_s: float | None  # when the first file appeared in the stage's output folder (None: never seen)
    torch_payloads: dict[str, str | None] = field(default_factory=dict)  # *.pt: torch_payload_digest


@dataclass
class KillResult:
    stage: str
    seed: int
    kill_at_s: float  # seconds after the start ("run" window) or after the first output file ("writing")
    killed: bool  # False: the stage had finished before the kill moment
    output_at_kill: str  # "none" | "partial": did the stage's output folder hold any file when killed
    files_at_kill: int  # how many (hidden temporaries included)
    outcome: str  # "identical" | "different" | "rerun-failed" | "run-failed" (failed on its own before the kill)
    differences: list[str] = field(default_factory=list)
    rerun_error: str = ""
    note: str = ""  # e.g. "torch archive name only": the differing .pt files hold the same tensors
    window: str = "run"  # how the kill moment was drawn (kill_matrix)

    @property
    def archive_name_only(self) -> bool:
        return self.outcome == "different" and self.note == ARCHIVE_NAME_ONLY

    def as_dict(self) -> dict:
        return {
            "seed": self.seed, "window": self.window, "kill_at_s": round(self.kill_at_s, 3), "killed": self.killed,
            "output_at_kill": self.output_at_kill, "files_at_kill": self.files_at_kill, "outcome": self.outcome,
            **({"differences": self.differences} if self.differences else {}),
            **({"rerun_error": self.rerun_error} if self.rerun_error else {}),
            **({"note": self.note} if self.note else {}),
        }


def reference_run(params_path: Path, stage: str, data_dir: Path) -> Reference:
    """Run the stage uninterrupted (timed, watching when its first output file appears)."""
    t0 = time.perf_counter()
    proc = start_stage(params_path, stage)
    first = None
    while proc.poll() is None:
        if first is None and has_output_file(data_dir, stage):
            first = time.perf_counter() - t0
        time.sleep(0.01)
    seconds = time.perf_counter() - t0
    err = stderr_of(proc)
    if proc.returncode != 0:
        raise AssertionError(f"cnnps run-stage {stage} exited {proc.returncode}:\n{err[-3000:]}")
    return Reference(stage, hash_outputs(data_dir, stage), seconds, first, torch_payload_digests(data_dir, stage))


def kill_moments(stage: str, seeds, duration: float, start: float = 0.0) -> list[tuple[int, float]]:
    """One kill moment per seed, uniform over [start, duration) (seeded by the stage and the seed).

    ``start`` = 0 spreads the kills over the whole run, interpreter start-up and imports
    included (what a user's Ctrl-C / OOM kill sees); ``start`` = the reference's
    ``first_output_s`` puts them all in the stretch where the stage writes its outputs.
    """
    import numpy as np

    from cnnps.infra.hashing import derive_seed64

    start = min(max(0.0, start), duration)
    return [(s, float(np.random.default_rng(derive_seed64("kill", stage, s)).uniform(start, duration))) for s in seeds]


def kill_trial(params_path: Path, stage: str, data_dir: Path, template_data: Path, ref: Reference,
               seed: int, kill_at_s: float, after_first_output: bool = False) -> KillResult:
    """Reset the data folder, kill the stage at ``kill_at_s`` (after the start, or after its
    first output file with ``after_first_output``), re-run it, compare with ``ref``."""
    reset_stage(data_dir, stage, template_data)
    try:
        killed = kill_stage_at(params_path, stage, kill_at_s, data_dir, after_first_output=after_first_output)
    except AssertionError as exc:  # it failed on its own before the kill moment
        line = (str(exc).strip().splitlines() or [""])[-1]
        return KillResult(stage, seed, kill_at_s, False, "none", 0, "run-failed", rerun_error=line[:300])
    out = Path(data_dir) / OUTPUT_DIRS[stage]
    n_files = sum(1 for p in out.rglob("*") if p.is_file()) if out.is_dir() else 0
    state = "partial" if n_files else "none"
    res = run_stage(params_path, stage)
    if res.returncode != 0:
        line = (res.stderr.strip().splitlines() or [""])[-1]
        return KillResult(stage, seed, kill_at_s, killed, state, n_files, "rerun-failed", rerun_error=line[:300])
    diff = differences(ref.hashes, hash_outputs(data_dir, stage))
    note = ""
    if diff and all(d.startswith("~") and d.endswith(".pt") for d in diff):
        got = torch_payload_digests(data_dir, stage)
        if all(ref.torch_payloads.get(d[1:]) is not None and ref.torch_payloads.get(d[1:]) == got.get(d[1:]) for d in diff):
            note = ARCHIVE_NAME_ONLY
    return KillResult(stage, seed, kill_at_s, killed, state, n_files, "different" if diff else "identical", diff, note=note)


WINDOWS = ("run", "writing")


def kill_matrix(work: Path, stage: str, seeds, log=None, window: str | tuple[str, ...] = "run") -> tuple[Reference, list[KillResult]]:
    """Reference run + one kill trial per seed (and per window), all in ``work`` (the same
    data path, so paths written into outputs agree); ``log(result)`` after each trial.

    ``window`` (one or several): "run" = kill moments uniform over the reference's whole
    duration, counted from the start (interpreter start-up included); "writing" = counted
    from the moment the trial's first output file appears, uniform over the stretch from
    the reference's first output file to its end (so start-up time, which varies with the
    machine's load, does not move the kill out of the writing stretch)."""
    windows = (window,) if isinstance(window, str) else tuple(window)
    for w in windows:
        if w not in WINDOWS:
            raise ValueError(f"window must be one of {', '.join(WINDOWS)}, got {w!r}")
    work = Path(work)
    params_path, data_dir = stage_folder(work, stage)
    template = work / "upstream-data"
    if template.exists():
        shutil.rmtree(template)
    shutil.copytree(data_dir, template, symlinks=True)
    ref = reference_run(params_path, stage, data_dir)
    _register_template(stage, work)
    results = []
    for w in windows:
        writing = w == "writing" and ref.first_output_s is not None
        span = ref.seconds - ref.first_output_s if writing else ref.seconds
        for seed, t in kill_moments(stage, seeds, span):
            r = kill_trial(params_path, stage, data_dir, template, ref, seed, t, after_first_output=writing)
            r.window = w
            results.append(r)
            if log is not None:
                log(r)
    return ref, results
