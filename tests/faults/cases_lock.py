"""Two runs on one data folder, and a full disk: the cases behind tests/faults/test_concurrent_runs.py,
tests/faults/test_disk_full.py and benchmarks/pipeline/fault_matrix.py (:func:`concurrent_and_enospc_cases`).

Concurrent runs. A *holder* process runs the real ``cnnps run-stage STAGE`` command line
(:func:`cnnps.pipeline.cli.main`) with the stage's work replaced by "say so, then sleep"
(``python -m tests.faults.cases_lock hold PARAMS STAGE``), so it holds the data folder's
lock for as long as the test needs; a second, real ``python -m cnnps run-stage ...`` (or
``cnnps demo``) on the same folder must exit 2 at once with one line naming the holder's
PID (:func:`refusal_case`).

Disk full (:func:`enospc_case`). The stage runs once to completion (tiny params, upstream
stages done: :func:`tests.support.faults.stage_folder`), then a parameter changes so that
it must rewrite its outputs (:data:`REWRITE`), and it runs again, through the real command
line (``python -m cnnps run-stage``, i.e. :func:`cnnps.pipeline.cli.main`), with too little
room, at one of two points (:data:`ENOSPC_POINTS`): "full" (no room when it starts) or
"fills" (room for part of the rewrite: :data:`FILLS_FREE`). Two ways to run out:

- ``tmpfs`` (where the machine allows it: an unprivileged user + mount namespace, ``unshare
  -rm``): the stage's output folder is bind-mounted from a tmpfs that a filler file (beside
  it, on the same tmpfs) leaves that many bytes free, so the kernel itself answers ENOSPC
  part-way through a write, in whatever library writes (OpenEXR, libpng, torch's zip
  writer, Parquet, numpy, trimesh);
- ``inject`` (elsewhere): the write layer (:func:`cnnps.infra.atomic.publish_mode`, called
  once a temporary file or folder under the stage folder is written, before its rename; the
  shard writer calls it too) truncates that temporary to half its bytes and raises
  ``OSError(ENOSPC)`` at its ``fail_at``-th call (:func:`install_enospc`, in the stage's
  process: ``python -m tests.faults.cases_lock inject ...``).

Then: (a) exit status 2 and one line ``cnnps: error: ...No space left on device`` (no
traceback); (b) the output folder is hashed before and after: ``previous_intact`` (every
byte the same, temporary files aside); every file that changed is classified
(``superseded``: already its complete new version, or removed as a complete run removes
it; ``lost``: a previous output the failed run deleted; ``partial``: a file under a final
name that is neither its old bytes nor a whole new file; ``leftover``: a new marker the
re-run removes, e.g. render's ``.pending.json``); temporary files left behind are listed;
and the stage is re-run without the fault: it must complete and leave no temporary file.
What a failed rewrite may lose by design is :data:`LOST_BY_DESIGN`.
"""

from __future__ import annotations

import errno
import fnmatch
import functools
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from tests.support import faults as F

STAGES = F.STAGES

# Each stage meets a full disk at two points (ENOSPC_POINTS), after a parameter change that
# makes it rewrite its outputs (REWRITE; keys change):
# - "full": the disk is full when the rewrite starts (0 bytes free);
# - "fills": there is room for part of the rewrite, so the disk fills in the middle of it
#   (FILLS_FREE: bytes left free, from the stage's outputs before the run).
# render: more lights, so the in-place rewrite of a capture needs more room than the one it
# replaces. train "fills" continues the run (max_steps 4 -> 6: same run key, so the
# checkpoints stay) and the disk fills in the step-6 checkpoint.
REWRITE: dict[tuple[str, str], dict] = {
    ("meshes", "full"): {"seed": 1},
    ("meshes", "fills"): {"seed": 1},
    ("materials", "full"): {"superpixels": 6},
    ("materials", "fills"): {"superpixels": 6},
    ("render", "full"): {"lights": 16},
    ("render", "fills"): {"lights": 16},
    ("extract", "full"): {"rotations": 2},
    ("extract", "fills"): {"rotations": 2},
    ("train", "full"): {"optimiser": {"lr": 0.002}},
    ("train", "fills"): {"max_steps": 6},
    ("eval", "full"): {"samples": 2},
    ("eval", "fills"): {"samples": 2},
}
ENOSPC_POINTS = ("full", "fills")
PAGE = 4096


def _half_largest(out: Path) -> int:
    return _largest_file(out) // 2


def _materials_room(out: Path) -> int:
    # room for half a scene folder: the disk fills among the files of the first scene's
    # temporary folder (a scene is replaced whole, so one that fits leaves room for the next)
    scenes = [d for d in out.iterdir() if d.is_dir() and not d.name.startswith(".")]
    sizes = [sum(-(-p.stat().st_size // PAGE) * PAGE for p in d.rglob("*") if p.is_file()) for d in scenes]
    return min(sizes) // 2 if sizes else 0


FILLS_FREE = {
    "meshes": _half_largest,  # mid-way through the new view's mesh.ply
    "materials": _materials_room,  # among the files of the first scene's temporary folder
    "render": lambda out: 2 * PAGE,  # the first capture: emptied, then more images than fit
    "extract": _half_largest,  # mid-way through the first scene's shard
    "train": _half_largest,  # mid-way through the step-6 checkpoint
    "eval": _half_largest,  # the re-rendered test captures fit; the new pictures do not
}

# Previous outputs a failed rewrite may destroy BY DESIGN, whatever the disk: files no
# longer valid for the new parameters that the stage deletes before writing anything
# (train: the resume checkpoints of another run key), and the one capture the render stage
# rewrites in place (its folder then holds no scene.json: never taken for a finished one).
LOST_BY_DESIGN = {
    ("train", "full"): ("checkpoints/step-*.pt",),  # checkpoints of the old parameters: never resumed from
}


# temporary names of the write layer: atomic_path ``.{stem}.XXXXXXXX.tmp{suffix}``, atomic_dir
# ``.{name}.XXXXXXXX.tmp``, the shard writer ``.shard-...-XXXXXXXX.parquet.tmp``
_TEMP = re.compile(r"^\..+\.tmp(\.[A-Za-z0-9]+)?$")
ERROR_LINE = re.compile(r"^cnnps: error: .*No space left on device")


def is_temp_name(name: str) -> bool:
    return bool(_TEMP.match(name))


def temp_files(root: Path) -> list[str]:
    """Temporary files / folders of the write layer anywhere under ``root`` (relative paths)."""
    root = Path(root)
    out = []
    if not root.exists():
        return out
    for dirpath, dirs, files in os.walk(root):
        for name in sorted(dirs + files):
            if is_temp_name(name):
                out.append((Path(dirpath) / name).relative_to(root).as_posix())
        dirs[:] = [d for d in dirs if not is_temp_name(d)]
    return sorted(out)


def set_params(params_path: Path, stage: str, changes: dict) -> None:
    raw = yaml.safe_load(params_path.read_text())
    raw.setdefault(stage, {}).update(changes)
    params_path.write_text(yaml.safe_dump(raw, sort_keys=False))


# ----------------------------------------------------------------------------- concurrent runs


def _holder_main(params: str, stage: str) -> None:
    """``python -m tests.faults.cases_lock hold PARAMS STAGE``: the real command line, whose
    stage work prints ``writing <pid>`` and sleeps until killed (it holds the lock meanwhile)."""
    from cnnps.pipeline import config as cfg
    from cnnps.pipeline.cli import main

    def work(name, conf, all_params=None):
        print(f"writing {os.getpid()}", flush=True)
        while True:
            time.sleep(60)

    cfg.run_stage = work
    main(["run-stage", stage, "--params", params])


def start_holder(params_path: Path, stage: str = "meshes", timeout: float = 120) -> subprocess.Popen:
    """Start a holder (own process group) and wait until it holds the lock."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.faults.cases_lock", "hold", str(params_path), stage],
        cwd=params_path.parent, env=F._env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,
    )
    line = proc.stdout.readline()  # blocks until the holder is inside the stage (or died)
    if not line.startswith("writing"):
        F.kill_group(proc)
        raise AssertionError(f"the holder did not start: {line!r} {proc.stderr.read()[-2000:]}")
    return proc


def stop(proc: subprocess.Popen) -> None:
    F.kill_group(proc)  # SIGKILL: the lock must not outlive it
    for f in (proc.stdout, proc.stderr):
        if f is not None:
            f.close()


def cnnps_command(params_path: Path, *args: str, env: dict | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cnnps", *args, "--params", str(params_path)],
                          cwd=params_path.parent, env=env or F._env(), capture_output=True, text=True, timeout=timeout)


@dataclass
class Refusal:
    command: str
    holder_pid: int
    returncode: int
    stderr: str
    refused: bool  # exit 2 and one line naming the holder's PID, nothing else on stderr


def refusal_line(data_dir: Path, stage: str, pid: int) -> re.Pattern:
    return re.compile(
        rf"^cnnps: error: {re.escape(str(data_dir))}/ is being written by another run "
        rf"\(cnnps run-stage {stage}, PID {pid} on \S+, since \d{{4}}-\d\d-\d\d \d\d:\d\d:\d\d UTC\); "
        r"wait for it or stop it$"
    )


def refusal_case(params_path: Path, data_dir: Path, holder: subprocess.Popen, holder_stage: str,
                 args: tuple[str, ...]) -> Refusal:
    """Run ``cnnps ARGS --params PARAMS`` while ``holder`` holds the lock."""
    res = cnnps_command(params_path, *args)
    lines = res.stderr.strip().splitlines()
    ok = res.returncode == 2 and len(lines) == 1 and bool(refusal_line(data_dir, holder_stage, holder.pid).match(lines[0]))
    return Refusal(" ".join(("cnnps",) + args), holder.pid, res.returncode, res.stderr, ok)


def dvc_refusal_case(params_path: Path, data_dir: Path, holder: subprocess.Popen, holder_stage: str) -> Refusal:
    """``dvc repro`` of a one-stage pipeline (``cnnps run-stage meshes`` on the same data
    folder) while ``holder`` holds the lock: DVC must fail, its output holding the line."""
    root = params_path.parent
    (root / "dvc.yaml").write_text(
        "stages:\n  meshes:\n"
        f"    cmd: {shlex.join([sys.executable, '-m', 'cnnps', 'run-stage', 'meshes', '--params', params_path.name])}\n"
        "    outs:\n      - data/meshes:\n          cache: false\n          persist: true\n"
    )
    env = F._env()
    env["DVC_NO_ANALYTICS"] = "1"
    if not (root / ".dvc").is_dir():
        init = subprocess.run([sys.executable, "-m", "dvc", "init", "--no-scm", "-q"], cwd=root, env=env,
                              capture_output=True, text=True, timeout=300)
        if init.returncode != 0:
            raise AssertionError(f"dvc init failed: {init.stderr[-2000:]}")
    res = subprocess.run([sys.executable, "-m", "dvc", "repro"], cwd=root, env=env, capture_output=True, text=True,
                         timeout=300)
    out = res.stdout + res.stderr
    line = refusal_line(data_dir, holder_stage, holder.pid)
    ok = res.returncode != 0 and any(line.match(ln) for ln in out.splitlines())
    return Refusal("dvc repro", holder.pid, res.returncode, out, ok)


def concurrent_cases(work: Path, commands=None) -> dict:
    """One holder (``run-stage meshes``) and a second run of each command (default: every
    ``run-stage`` and ``demo --no-dvc``, and ``dvc repro`` where DVC is installed); then
    SIGKILL the holder and check that a new run proceeds. Returns ``{"tried", "refused",
    "after_kill_ok", "cases": [...]}``."""
    import importlib.util

    work = Path(work)
    params_path, data_dir = F.write_stage_params(work)
    data_dir.mkdir(parents=True, exist_ok=True)
    commands = commands or [("run-stage", s) for s in STAGES] + [("demo", "--no-dvc")]
    holder = start_holder(params_path, "meshes")
    cases = []
    try:
        for args in commands:
            cases.append(refusal_case(params_path, data_dir, holder, "meshes", tuple(args)))
        if importlib.util.find_spec("dvc") is not None:
            cases.append(dvc_refusal_case(params_path, data_dir, holder, "meshes"))
    finally:
        stop(holder)
    after = cnnps_command(params_path, "run-stage", "meshes")
    return {
        "tried": len(cases),
        "refused": sum(c.refused for c in cases),
        "after_kill_ok": after.returncode == 0 and not (data_dir / ".cnnps.lock.json").exists(),
        "cases": [{"command": c.command, "refused": c.refused, "returncode": c.returncode,
                   "line": (c.stderr.strip().splitlines() or [""])[-1][:300]} for c in cases],
    }


# ----------------------------------------------------------------------------- disk full


@functools.lru_cache(maxsize=1)
def tmpfs_available() -> bool:
    """Whether this user may mount a tmpfs in a private user + mount namespace (``unshare -rm``)."""
    unshare = shutil.which("unshare")
    if unshare is None or not sys.platform.startswith("linux"):
        return False
    d = tempfile.mkdtemp(prefix="cnnps-tmpfs-probe-")
    try:
        res = subprocess.run([unshare, "-rm", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs '{d}' && touch '{d}/x'"],
                             capture_output=True, timeout=30)
        return res.returncode == 0 and not os.path.exists(os.path.join(d, "x"))
    except (OSError, subprocess.SubprocessError):
        return False
    finally:
        shutil.rmtree(d, ignore_errors=True)


@dataclass
class EnospcResult:
    stage: str
    point: str  # "full" | "fills" (ENOSPC_POINTS)
    mode: str  # "tmpfs" (the kernel's ENOSPC) | "inject" (OSError(ENOSPC) at the write layer)
    fault: str  # where: "free_bytes=N" or "fail_at=N"
    returncode: int
    error_line: str
    clean_stop: bool  # exit 2, one error line ending "No space left on device", no traceback
    previous_intact: bool  # the output folder's bytes are what they were (temporary files aside)
    changed: list[str] = field(default_factory=list)  # files whose bytes or presence changed
    superseded: list[str] = field(default_factory=list)  # changed, and already their complete new version
    lost: list[str] = field(default_factory=list)  # previous outputs the failed run deleted or changed
    partial: list[str] = field(default_factory=list)  # neither old nor a complete new version: half-written
    leftover: list[str] = field(default_factory=list)  # new, not temporary, removed by the re-run (markers)
    temp_after_fault: list[str] = field(default_factory=list)
    temp_after_rerun: list[str] = field(default_factory=list)
    rerun_ok: bool = False
    stderr_tail: str = ""

    def lost_by_design(self) -> bool:
        """Every lost file is one the stage destroys by design (:data:`LOST_BY_DESIGN`)."""
        patterns = LOST_BY_DESIGN.get((self.stage, self.point), ())
        return all(any(fnmatch.fnmatchcase(p, pat) for pat in patterns) for p in self.lost)

    def passed(self) -> bool:
        """The stage stopped cleanly, wrote nothing half, lost nothing but what it drops by
        design, and the re-run completed without leaving a temporary file."""
        return (self.clean_stop and not self.partial and self.lost_by_design() and self.rerun_ok
                and not self.temp_after_rerun)

    def summary(self) -> dict:
        return {"point": self.point, "clean_stop": self.clean_stop, "previous_intact": self.previous_intact,
                "mode": self.mode, "fault": self.fault, "error_line": self.error_line[:300],
                "lost": self.lost, "lost_by_design": self.lost_by_design(), "partial": self.partial,
                "superseded": len(self.superseded), "leftover": self.leftover,
                "temp_after_fault": self.temp_after_fault, "temp_after_rerun": self.temp_after_rerun,
                "rerun_ok": self.rerun_ok}


def _largest_file(root: Path) -> int:
    sizes = [p.stat().st_size for p in Path(root).rglob("*") if p.is_file()]
    return max(sizes, default=0)


def _run_in_tmpfs(params_path: Path, stage: str, data_dir: Path, free_bytes: int, work: Path) -> tuple[int, str, Path]:
    """Run the stage with its output folder on a tmpfs that has ``free_bytes`` free; returns
    (exit status, stderr, a copy of the output folder as the failed run left it)."""
    out = data_dir / F.OUTPUT_DIRS[stage]
    fs = work / "tmpfs"
    after = work / "after"
    for p in (fs, after):
        shutil.rmtree(p, ignore_errors=True)
    fs.mkdir(parents=True)
    used = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    size = used + (64 << 20)
    cmd = shlex.join(F.stage_command(params_path, stage))
    script = f"""
set -e
mount -t tmpfs -o size={size} tmpfs '{fs}'
mkdir '{fs}/out'
cp -a '{out}/.' '{fs}/out/'
mount --bind '{fs}/out' '{out}'
'{sys.executable}' - <<'PY'
import os
st = os.statvfs('{fs}')
room = st.f_bavail * st.f_frsize - {int(free_bytes)}
with open('{fs}/filler', 'wb') as f:
    while room > 0:
        n = min(room, 1 << 20)
        f.write(bytes(n))
        room -= n
PY
set +e
{cmd} 2> '{work}/stderr.txt' > /dev/null
echo $? > '{work}/rc.txt'
mkdir '{after}'
cp -a '{out}/.' '{after}/'
"""
    res = subprocess.run(["unshare", "-rm", "sh", "-c", script], cwd=params_path.parent, env=F._env(),
                         capture_output=True, text=True, timeout=F.STAGE_TIMEOUT_S)
    if res.returncode != 0 or not (work / "rc.txt").is_file():
        raise AssertionError(f"tmpfs set-up failed (exit {res.returncode}): {res.stderr[-2000:]}")
    return int((work / "rc.txt").read_text()), (work / "stderr.txt").read_text(), after


def _run_injected(params_path: Path, stage: str, fail_at: int, out: Path) -> tuple[int, str]:
    """Run the stage in a subprocess (its own interpreter: imports and the patch stay there)
    whose write layer fails with ENOSPC at the ``fail_at``-th publication under ``out``."""
    res = subprocess.run([sys.executable, "-m", "tests.faults.cases_lock", "inject", str(params_path), stage,
                          str(fail_at), str(out)], cwd=params_path.parent, env=F._env(), capture_output=True,
                         text=True, timeout=F.STAGE_TIMEOUT_S)
    return res.returncode, res.stderr


def install_enospc(fail_at: int, root: str | Path) -> dict:
    """Make the ``fail_at``-th publication under ``root`` (1 = the first) of the write layer
    fail with ENOSPC after half of the temporary's bytes: :func:`cnnps.infra.atomic.publish_mode`
    (atomic files and folders, the render stage's build folders, the shard writer).
    Returns the counter ``{"calls": n, "failed": path or None}``. For a process of its own
    (nothing is restored)."""
    root = Path(root).resolve()
    import cnnps.infra.atomic as atomic
    import cnnps.io.shards.writer as shard_writer

    real = atomic.publish_mode
    state = {"calls": 0, "failed": None}

    def publish_mode(tmp, is_dir):
        if not Path(tmp).resolve().is_relative_to(root):
            return real(tmp, is_dir)  # e.g. the lock's record beside the stage folders
        state["calls"] += 1
        if state["calls"] == fail_at:
            tmp = Path(tmp)
            victims = [p for p in tmp.rglob("*") if p.is_file()] if is_dir else [tmp]
            if victims:
                big = max(victims, key=lambda p: p.stat().st_size)
                os.truncate(big, big.stat().st_size // 2)  # the disk filled half-way through
            state["failed"] = str(tmp)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(tmp, is_dir)

    atomic.publish_mode = publish_mode
    shard_writer.publish_mode = publish_mode
    try:
        import cnnps.synth.render.resume as resume

        resume.publish_mode = publish_mode
    except ImportError:  # pragma: no cover
        pass
    return state


def _inject_main(params: str, stage: str, fail_at: str, root: str) -> None:
    install_enospc(int(fail_at), root)
    from cnnps.pipeline.cli import main

    main(["run-stage", stage, "--params", params])


def readable(path: Path) -> bool:
    """Whether ``path`` is a whole file of its kind (read back by its reader)."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".pt":
            import torch

            torch.load(path, map_location="cpu", weights_only=True)
        elif suffix == ".json":
            json.loads(path.read_text())
        elif suffix == ".npy":
            import numpy as np

            np.load(path, allow_pickle=False)
        elif suffix == ".parquet":
            import pyarrow.parquet as pq

            pq.read_table(path)
        elif suffix in (".exr", ".png"):
            from cnnps.io.images import read_image

            read_image(path)
        elif suffix == ".ply":
            import trimesh

            trimesh.load(path, force="mesh")
        else:
            return path.stat().st_size > 0
    except Exception:
        return False
    return True


def _classify(out: Path, before: dict, after: dict, rerun: dict) -> dict[str, list[str]]:
    """The files whose bytes or presence changed, by kind (temporary files left out:
    :func:`temp_files` lists them)."""
    kinds = {"changed": [], "superseded": [], "lost": [], "partial": [], "leftover": []}
    for p in sorted(set(before) | set(after)):
        if before.get(p) == after.get(p) or any(is_temp_name(part) for part in Path(p).parts):
            continue
        kinds["changed"].append(p)
        if p not in after:
            kinds["superseded" if p not in rerun else "lost"].append(p)  # removed as a complete run removes it, or lost
        elif after[p] == rerun.get(p):
            kinds["superseded"].append(p)  # its complete new version
        elif p not in rerun and p not in before:
            kinds["leftover"].append(p)  # a marker of unfinished work the re-run removes
        elif p not in before and p in rerun and readable(out / p):
            kinds["superseded"].append(p)  # new, whole, other bytes (torch names the zip after the temp file)
        elif p in before and p in rerun and readable(out / p):
            kinds["superseded"].append(p)
        else:
            kinds["partial"].append(p)
    return kinds


def completed_stage_folder(work: Path, stage: str) -> tuple[Path, Path]:
    """(params_path, data_dir) in ``work`` with every stage up to and including ``stage``
    done: the upstream folder of the next stage (built once per process, then copied), or
    for the last stage, its upstream folder and one run."""
    i = STAGES.index(stage)
    if i + 1 < len(STAGES):
        return F.stage_folder(work, STAGES[i + 1])
    params_path, data_dir = F.stage_folder(work, stage)
    F.check_run(params_path, stage)
    return params_path, data_dir


def _stderr_lines(err: str) -> list[str]:
    # what a terminal shows: a progress bar's carriage returns start a line over
    return [ln for ln in re.split(r"[\r\n]+", err) if ln.strip()]


def enospc_case(work: Path, stage: str, point: str = "fills", mode: str = "auto",
                prepared: tuple[Path, Path] | None = None) -> EnospcResult:
    """Complete run, parameter change (:data:`REWRITE`), the run that meets a full disk at
    ``point`` ("full" or "fills"), checks, re-run. ``mode``: "tmpfs", "inject" or "auto"
    (tmpfs where available; inject fails the 1st ("full") or the 2nd ("fills") publication
    under the stage's folder).
    ``prepared``: (params_path, data_dir) whose stage already ran (else made in ``work``)."""
    work = Path(work)
    if point not in ENOSPC_POINTS:
        raise ValueError(f"point must be one of {ENOSPC_POINTS}, got {point!r}")
    if mode == "auto":
        mode = "tmpfs" if tmpfs_available() else "inject"
    params_path, data_dir = prepared if prepared is not None else completed_stage_folder(work, stage)
    out = data_dir / F.OUTPUT_DIRS[stage]
    before = F.hash_outputs(data_dir, stage)
    set_params(params_path, stage, REWRITE[(stage, point)])
    if mode == "tmpfs":
        free = 0 if point == "full" else int(FILLS_FREE[stage](out))
        fault = f"tmpfs, {free} bytes free"
        rc, err, after_copy = _run_in_tmpfs(params_path, stage, data_dir, free, work / "enospc")
        shutil.rmtree(out)
        shutil.move(str(after_copy), str(out))
    elif mode == "inject":
        fail_at = 1 if point == "full" else 2
        fault = f"injected at write {fail_at}"
        rc, err = _run_injected(params_path, stage, fail_at, out)
    else:
        raise ValueError(f"mode must be tmpfs, inject or auto, got {mode!r}")
    after = F.hash_outputs(data_dir, stage)
    temp_fault = temp_files(out)
    keep = work / "after-fault"  # the failed run's outputs, for the readability checks below
    shutil.rmtree(keep, ignore_errors=True)
    shutil.copytree(out, keep, symlinks=True)
    lines = _stderr_lines(err)
    # the error from where it starts (a progress bar the stage left open may precede it on its line)
    error_lines = [ln[ln.index("cnnps: error:"):] for ln in lines if "cnnps: error:" in ln]
    error_line = error_lines[-1] if error_lines else (lines[-1] if lines else "")
    clean = (rc == 2 and len(error_lines) == 1 and bool(ERROR_LINE.match(error_line))
             and "Traceback" not in err and lines[-1].endswith(error_line))
    rerun = F.run_stage(params_path, stage)
    kinds = _classify(keep, before, after, F.hash_outputs(data_dir, stage))
    return EnospcResult(
        stage=stage, point=point, mode=mode, fault=fault, returncode=rc, error_line=error_line, clean_stop=clean,
        previous_intact=not kinds["changed"], changed=kinds["changed"], superseded=kinds["superseded"],
        lost=kinds["lost"], partial=kinds["partial"], leftover=kinds["leftover"],
        temp_after_fault=temp_fault, temp_after_rerun=temp_files(out),
        rerun_ok=rerun.returncode == 0, stderr_tail=err[-3000:] if not clean else "",
    )


def concurrent_and_enospc_cases(stages=STAGES, work: Path | None = None, mode: str = "auto",
                                points=ENOSPC_POINTS, log=None) -> dict:
    """The numbers of benchmarks/results/faults.json for this helper, by running the cases::

        {"concurrent_refusals": {"tried": n, "refused": n, "after_kill_ok": bool, "cases": [...]},
         "enospc": {stage: {"tried": n, "clean_stop": bool, "previous_intact": bool,
                            "clean_stops": n, "intact": n, "nothing_lost": bool, "cases": [...]}}}

    ``clean_stop`` / ``previous_intact``: every case of the stage stopped with the one line /
    left the previous outputs byte-identical (temporary files aside); ``nothing_lost``: no
    case left a half-written file or lost a previous output other than by design
    (:data:`LOST_BY_DESIGN`), and every re-run completed leaving no temporary file.
    ``log(name, result_dict)`` is called after each case.
    """
    own = work is None
    work = Path(tempfile.mkdtemp(prefix="cnnps-lock-cases-")) if own else Path(work)
    try:
        concurrent = concurrent_cases(work / "concurrent")
        if log is not None:
            log("concurrent_refusals", concurrent)
        enospc = {}
        for stage in stages:
            results = [enospc_case(work / f"enospc-{stage}-{point}", stage, point, mode=mode) for point in points]
            enospc[stage] = {
                "tried": len(results),
                "clean_stop": all(r.clean_stop for r in results),
                "previous_intact": all(r.previous_intact for r in results),
                "clean_stops": sum(r.clean_stop for r in results),
                "intact": sum(r.previous_intact for r in results),
                "nothing_lost": all(r.passed() for r in results),
                "cases": [r.summary() for r in results],
            }
            if log is not None:
                log(stage, enospc[stage])
        return {"concurrent_refusals": concurrent, "enospc": enospc}
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    if sys.argv[1:2] == ["hold"]:
        _holder_main(*sys.argv[2:4])
    elif sys.argv[1:2] == ["inject"]:
        _inject_main(*sys.argv[2:6])
    elif sys.argv[1:2] == ["cases"]:
        print(json.dumps(concurrent_and_enospc_cases(sys.argv[2:] or STAGES), indent=1))
    else:
        sys.exit("usage: python -m tests.faults.cases_lock hold PARAMS STAGE | inject PARAMS STAGE N ROOT | cases [STAGE...]")
