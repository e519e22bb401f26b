"""Corrupt inputs on purpose: every kind of file a stage reads, damaged, and the stage re-run.

A *try* takes a copy of a finished tiny pipeline (the tiny params of
``tests/pipeline/conftest.py``, built once through :func:`tests.support.faults.stage_folder`
plus one eval run), damages one file (seeded: which scene, image, length, byte), re-runs
the stage through the real command line (``cnnps run-stage NAME``, in this process:
:func:`cnnps.pipeline.cli.main`, whose ``sys.exit`` status is the process's), and judges
the result by the case's action:

- ``stop`` (a downstream stage reading another stage's damaged output): exit status 2,
  exactly one ``cnnps: error:`` line on stderr that names the damaged file (its full
  path) and the fix (``cnnps run-stage`` of the stage that owns the file, and "delete"
  when that stage cannot find the damage by itself), and the stage's output folder
  exactly as before the run (every file's bytes and mtime: nothing half-written, nothing
  removed). With ``check_fix`` the fix is then applied as the line says (delete, re-run
  the owner, re-run the stage) and every stage's outputs must equal the undamaged ones;
- ``redo`` (the stage owns the damaged file as its own cached output): exit status 0,
  the stage's output folder identical to the undamaged one
  (:func:`tests.support.faults.hash_outputs`, timing fields left out) and only the
  damaged part rewritten: every file the case does not name as redone keeps its mtime.

A try counts as *detected* only when every check of its action holds. Inputs of the
render stage written by the meshes and materials stages are checked by decoding (those
stages keep no per-file checksums); everything else by the checksums the stages record.

:func:`corruption_cases` runs every kind and returns
``{kind: {"stage", "tried", "detected", "action"}}`` (the fault benchmark,
``benchmarks/pipeline/fault_matrix.py``, recorded in ``benchmarks/results/faults.json``); :func:`run_try` runs one try and returns a
:class:`TryResult` with the reason of a failure.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from pathlib import Path
from typing import Callable

import numpy as np

from tests.support import faults

ERROR_PREFIX = "cnnps: error:"


# ----------------------------------------------------------------------------- damage


def _rewrite(path: Path, data: bytes) -> None:
    """Replace ``path`` by ``data`` as a new file (never in place: the copies of a try
    may share inodes with the pristine pipeline through hard links)."""
    path.unlink()
    path.write_bytes(data)


def truncate(path: Path, rng: np.random.Generator) -> str:
    data = path.read_bytes()
    n = int(rng.integers(0, len(data)))
    _rewrite(path, data[:n])
    return f"truncated to {n} of {len(data)} bytes"


def flip_byte(path: Path, rng: np.random.Generator, lo: int = 0, hi: int | None = None) -> str:
    data = bytearray(path.read_bytes())
    hi = len(data) if hi is None else min(hi, len(data))
    at = int(rng.integers(lo, hi))
    bit = int(rng.integers(0, 8))
    data[at] ^= 1 << bit
    _rewrite(path, bytes(data))
    return f"bit {bit} of byte {at} of {len(data)} flipped"


def nonfinite_exr(path: Path, rng: np.random.Generator) -> str:
    """Write NaN, +Inf or -Inf into a few pixels of an EXR (a valid EXR file)."""
    from cnnps.io.images import read_exr, write_exr

    img = read_exr(path)
    value = [np.nan, np.inf, -np.inf][int(rng.integers(0, 3))]
    k = int(rng.integers(1, 4))
    for _ in range(k):
        r, c = int(rng.integers(0, img.shape[0])), int(rng.integers(0, img.shape[1]))
        img[r, c, int(rng.integers(0, img.shape[2]))] = value
    path.unlink()
    write_exr(path, img)
    return f"{k} pixel channel(s) set to {value}"


def nonfinite_npy(path: Path, rng: np.random.Generator) -> str:
    arr = np.load(path)
    flat = arr.reshape(-1)
    at = int(rng.integers(0, flat.size))
    flat[at] = np.nan
    path.unlink()
    np.save(path, arr)
    return f"element {at} set to NaN"


def edit_json(path: Path, rng: np.random.Generator, indent: int | None, edits: list[tuple[str, Callable]]) -> str:
    """Change one field (chosen by ``rng`` among ``edits``) and write the file back in its
    own layout, as an editor would."""
    obj = json.loads(path.read_text())
    name, fn = edits[int(rng.integers(0, len(edits)))]
    fn(obj)
    text = json.dumps(obj, indent=indent) + ("\n" if path.read_text().endswith("\n") else "")
    path.unlink()
    path.write_text(text)
    return f"edited: {name}"


def _set(key, value):
    def fn(obj):
        obj[key] = value
    return fn


def _bump(key, by=1):
    def fn(obj):
        obj[key] = obj[key] + by
    return fn


SCENE_EDITS = [
    ("light_intensity 1 -> 2", _set("light_intensity", 2.0)),
    ("view_id renamed", lambda o: o.__setitem__("view_id", o["view_id"] + "-x")),
    ("n_lights + 1", _bump("n_lights")),
    ("environment_strength 0 -> 0.05", _set("environment_strength", 0.05)),
]


def _shard_split_swap(obj):
    s = obj["shards"][0]
    s["split"] = "val" if s["split"] == "train" else "train"


MANIFEST_EDITS = [
    ("a shard moved to the other split", _shard_split_swap),
    ("train_rows + 1000", _bump("train_rows", 1000)),
    ("a shard's rows + 1", lambda o: o["shards"][0].__setitem__("rows", o["shards"][0]["rows"] + 1)),
    ("w 32 -> 16", _set("w", 16)),
]

MARKER_EDITS = [
    ("rows + 10", _bump("rows", 10)),
    ("a shard's rows + 1", lambda o: o["shards"][0].__setitem__("rows", o["shards"][0]["rows"] + 1)),
    ("lights - 1", _bump("lights", -1)),
]


# ----------------------------------------------------------------------------- the cases


@dataclass
class Damage:
    """What a case did: the damaged file, how, (redo) which files may be rewritten (globs
    relative to the stage's output folder), and (stop) what the fix deletes first."""

    path: Path
    how: str
    redone: tuple[str, ...] = ()
    delete_first: Path | None = None


@dataclass
class Case:
    kind: str
    stage: str  # the stage re-run after the damage
    action: str  # "stop" | "redo"
    damage: Callable[[Path, np.random.Generator], Damage]  # (data_dir, rng) -> Damage
    what: str  # one line for the report
    fix: tuple[str, ...] = ()  # stop: the stages the fix re-runs, in order (the owner first)


def _pick(rng: np.random.Generator, items: list):
    items = sorted(items)
    return items[int(rng.integers(0, len(items)))]


def _scene(data: Path, rng) -> Path:
    return _pick(rng, [p for p in (data / "render").iterdir() if (p / "scene.json").is_file()])


def _exr(data: Path, rng) -> Path:
    return _pick(rng, list(_scene(data, rng).glob("*.exr")))


def _marker_of(data: Path, scene: Path) -> Path:
    return data / "extract" / f"scene-{scene.name}.json"


def _needs_extract(data: Path, scene: Path) -> None:
    """Make the extract stage read ``scene`` again (as after a change of its params):
    its marker goes (the rest of data/extract stays as it is)."""
    _marker_of(data, scene).unlink()


def _legacy(scene: Path) -> None:
    """Turn ``scene.json`` into one written before checksums (no ``files``, no ``checksum``)."""
    meta = json.loads((scene / "scene.json").read_text())
    meta.pop("files", None)
    meta.pop("checksum", None)
    (scene / "scene.json").unlink()
    (scene / "scene.json").write_text(json.dumps(meta, indent=2) + "\n")


def _shard(data: Path, rng) -> Path:
    return _pick(rng, list((data / "extract").glob("shard-*.parquet")))


def _scene_of_shard(shard: Path) -> str:
    return shard.name[len("shard-"):].rsplit("-", 1)[0]


# -- render: its own outputs (redo) -------------------------------------------------------


def _render_exr(damage_fn):
    def fn(data, rng):
        p = _exr(data, rng)
        how = damage_fn(p, rng)
        return Damage(p, how, (f"{p.parent.name}/{p.name}", f"{p.parent.name}/scene.json"))
    return fn


def _render_mask(data, rng):
    p = _scene(data, rng) / "mask.png"
    return Damage(p, truncate(p, rng), tuple(f"{p.parent.name}/{n}" for n in ("mask.png", "normal_gt.npy", "scene.json")))


def _render_scene_json(data, rng):
    s = _scene(data, rng)
    return Damage(s / "scene.json", edit_json(s / "scene.json", rng, 2, SCENE_EDITS), (f"{s.name}/*",))


# -- render: inputs of the meshes and materials stages (stop) --------------------------


def _material_file(pattern: str, damage_fn):
    def fn(data, rng):
        sdir = _pick(rng, [p for p in (data / "materials").iterdir() if (p / "material.json").is_file()])
        p = _pick(rng, list(sdir.glob(pattern)))
        return Damage(p, damage_fn(p, rng), delete_first=sdir)
    return fn


def _mesh_truncated(data, rng):
    p = _pick(rng, list((data / "meshes").glob("*/mesh.ply")))
    return Damage(p, truncate(p, rng), delete_first=p.parent)


# -- extract: the render stage's outputs (stop) ----------------------------------------


def _extract_exr(damage_fn, legacy: bool = False):
    def fn(data, rng):
        p = _exr(data, rng)
        if legacy:
            _legacy(p.parent)
        how = damage_fn(p, rng)
        _needs_extract(data, p.parent)
        return Damage(p, how + (" (scene.json without checksums)" if legacy else ""), delete_first=p if legacy else None)
    return fn


def _extract_render_file(name: str):
    def fn(data, rng):
        s = _scene(data, rng)
        how = truncate(s / name, rng)
        _needs_extract(data, s)
        return Damage(s / name, how)
    return fn


def _extract_scene_json(data, rng):
    s = _scene(data, rng)
    return Damage(s / "scene.json", edit_json(s / "scene.json", rng, 2, SCENE_EDITS))


# -- extract: its own outputs (redo); train: the same files (stop) -------------------------


def _shard_damage(damage_fn, redo: bool):
    def fn(data, rng):
        p = _shard(data, rng)
        how = damage_fn(p, rng)
        sid = _scene_of_shard(p)
        return Damage(p, how, (f"shard-{sid}-*.parquet", f"scene-{sid}.json", "manifest.json") if redo else ())
    return fn


def _shard_deleted(redo: bool):
    def fn(data, rng):
        p = _shard(data, rng)
        p.unlink()
        sid = _scene_of_shard(p)
        return Damage(p, "deleted", (f"shard-{sid}-*.parquet", f"scene-{sid}.json", "manifest.json") if redo else ())
    return fn


def _manifest_edited(redo: bool):
    def fn(data, rng):
        p = data / "extract" / "manifest.json"
        return Damage(p, edit_json(p, rng, 1, MANIFEST_EDITS), ("manifest.json",) if redo else ())
    return fn


def _marker_edited(data, rng):
    p = _pick(rng, list((data / "extract").glob("scene-*.json")))
    sid = p.name[len("scene-"):-len(".json")]
    return Damage(p, edit_json(p, rng, 1, MARKER_EDITS), (f"shard-{sid}-*.parquet", f"scene-{sid}.json", "manifest.json"))


# -- train's model.pt: train (redo), eval (stop) ---------------------------------------------


TRAIN_FINISH = ("model.pt", "model.pt.sha256", "metrics.json", "plots/*")  # what a finished train rewrites


def _model_damage(damage_fn, redo: bool = False, sidecar: bool = True, members_only: bool = False):
    def fn(data, rng):
        p = data / "train" / "model.pt"
        if not sidecar:
            (data / "train" / "model.pt.sha256").unlink()
        if members_only:  # inside a zip member's data (the pickle or a tensor), not zip bookkeeping
            import zipfile

            with zipfile.ZipFile(p) as z:
                members = sorted((i.header_offset, i.compress_size, i.filename) for i in z.infolist() if i.file_size)
            offset, size, name = members[int(rng.integers(0, len(members)))]
            raw = p.read_bytes()
            # the data of a member starts after its local header: 30 bytes + name + extra field
            start = offset + 30 + int.from_bytes(raw[offset + 26:offset + 28], "little") + int.from_bytes(
                raw[offset + 28:offset + 30], "little")
            how = flip_byte(p, rng, start, start + size) + f" (member {name.split('/', 1)[-1]})"
        else:
            how = damage_fn(p, rng)
        if not sidecar:
            how += " (no model.pt.sha256)"
        return Damage(p, how, TRAIN_FINISH if redo else ())
    return fn


def _testset_exr(data, rng):
    cap = _pick(rng, [p for p in (data / "eval" / "testset").iterdir() if (p / "scene.json").is_file()])
    p = _pick(rng, list(cap.glob("*.exr")))
    how = truncate(p, rng)
    return Damage(p, how, (f"testset/{cap.name}/{p.name}", f"testset/{cap.name}/scene.json", "metrics.json",
                           "report.md", "pictures/*"))


CASES: list[Case] = [
    # render: its own outputs (a damaged image of its cache is rendered again)
    Case("exr-truncated", "render", "redo", _render_exr(truncate), "an EXR of a rendered scene truncated"),
    Case("exr-nan-inf", "render", "redo", _render_exr(nonfinite_exr), "NaN / Inf written into an EXR"),
    Case("exr-byte-flipped", "render", "redo", _render_exr(flip_byte), "one bit of an EXR flipped"),
    Case("png-truncated", "render", "redo", _render_mask, "a rendered mask.png truncated"),
    Case("scene-json-edited", "render", "redo", _render_scene_json, "scene.json edited by hand"),
    # render: inputs written by meshes / materials
    Case("material-png-truncated", "render", "stop", _material_file("mask.png", truncate),
         "the materials stage's mask.png truncated", ("materials", "render")),
    Case("material-npy-truncated", "render", "stop", _material_file("*.npy", truncate),
         "a material map (.npy) truncated", ("materials", "render")),
    Case("material-npy-nan", "render", "stop", _material_file("[bmrs]*.npy", nonfinite_npy),
         "NaN written into a material parameter map", ("materials", "render")),
    Case("mesh-truncated", "render", "stop", _mesh_truncated, "a view's mesh.ply truncated",
         ("meshes", "materials", "render")),
    # extract: the render stage's outputs
    Case("exr-truncated", "extract", "stop", _extract_exr(truncate), "an EXR truncated", ("render", "extract")),
    Case("exr-nan-inf", "extract", "stop", _extract_exr(nonfinite_exr), "NaN / Inf written into an EXR",
         ("render", "extract")),
    Case("exr-byte-flipped", "extract", "stop", _extract_exr(flip_byte), "one bit of an EXR flipped",
         ("render", "extract")),
    Case("exr-nan-inf-legacy", "extract", "stop", _extract_exr(nonfinite_exr, legacy=True),
         "NaN / Inf in an EXR of a folder rendered before checksums (decoder + finite check)", ("render", "extract")),
    Case("png-truncated", "extract", "stop", _extract_render_file("mask.png"), "a rendered mask.png truncated",
         ("render", "extract")),
    Case("npy-truncated", "extract", "stop", _extract_render_file("normal_gt.npy"), "normal_gt.npy truncated",
         ("render", "extract")),
    Case("scene-json-edited", "extract", "stop", _extract_scene_json, "scene.json edited by hand",
         ("render", "extract")),
    # extract: its own outputs
    Case("shard-truncated", "extract", "redo", _shard_damage(truncate, True), "a Parquet shard truncated"),
    Case("shard-byte-flipped", "extract", "redo", _shard_damage(flip_byte, True), "one bit of a shard flipped"),
    Case("shard-deleted", "extract", "redo", _shard_deleted(True), "a shard the manifest names deleted"),
    Case("marker-edited", "extract", "redo", _marker_edited, "a scene marker (scene-<id>.json) edited by hand"),
    Case("manifest-edited", "extract", "redo", _manifest_edited(True), "manifest.json edited by hand"),
    # train: the extract stage's outputs
    Case("shard-truncated", "train", "stop", _shard_damage(truncate, False), "a Parquet shard truncated",
         ("extract", "train")),
    Case("shard-byte-flipped", "train", "stop", _shard_damage(flip_byte, False), "one bit of a shard flipped",
         ("extract", "train")),
    Case("shard-deleted", "train", "stop", _shard_deleted(False), "a shard the manifest names deleted",
         ("extract", "train")),
    Case("manifest-edited", "train", "stop", _manifest_edited(False), "manifest.json edited by hand",
         ("extract", "train")),
    # train: its own model.pt
    Case("model-byte-flipped", "train", "redo", _model_damage(flip_byte, redo=True), "one bit of model.pt flipped"),
    # eval: the train stage's model.pt, and its own test set
    Case("model-byte-flipped", "eval", "stop", _model_damage(flip_byte), "one bit of model.pt flipped",
         ("train", "eval")),
    Case("model-byte-flipped-no-sidecar", "eval", "stop", _model_damage(flip_byte, sidecar=False, members_only=True),
         "one bit flipped in a zip member of model.pt, without model.pt.sha256 (weights digest + CRC-32)",
         ("train", "eval")),
    Case("model-truncated", "eval", "stop", _model_damage(truncate), "model.pt truncated", ("train", "eval")),
    Case("testset-exr-truncated", "eval", "redo", _testset_exr, "an EXR of the cached test set truncated"),
]


def case_id(case: Case) -> str:
    return f"{case.stage}/{case.kind}"


# ----------------------------------------------------------------------------- running


_BASELINES: dict[str, Path] = {}


def baseline(root: str | Path | None = None) -> Path:
    """A folder whose ``data/`` holds every stage's outputs (meshes ... eval) on the tiny
    params; built once per process (upstream of eval by :mod:`tests.support.faults`)."""
    key = str(root)
    if key in _BASELINES:
        return _BASELINES[key]
    if root is None:
        root = Path(tempfile.mkdtemp(prefix="cnnps-corruption-"))
        import atexit

        atexit.register(shutil.rmtree, root, True)
    root = Path(root) / "baseline"
    if root.exists():
        shutil.rmtree(root)
    params_path, data_dir = faults.stage_folder(root, "eval")
    code, err = run_cli(params_path, "eval")
    if code != 0:
        raise AssertionError(f"cnnps run-stage eval failed on the pristine pipeline (exit {code}):\n{err[-3000:]}")
    _BASELINES[key] = root
    return root


def _copy(src: str, dst: str) -> None:
    # the training checkpoints are big and no case writes them in place: hard links
    if f"{os.sep}checkpoints{os.sep}" in src:
        try:
            os.link(src, dst)
            return
        except OSError:
            pass
    shutil.copy2(src, dst)


def work_copy(base: Path, dest: Path) -> tuple[Path, Path]:
    """A fresh copy of the baseline pipeline at ``dest``: (params_path, data_dir).

    The eval stage's ``metrics.json`` and ``report.md`` record absolute paths (the model,
    the captures); in the copy they are rewritten to the copy's folder, as if the
    pipeline had run there, so a re-run that reproduces them is recognised."""
    if dest.exists():
        shutil.rmtree(dest)
    params_path, data_dir = faults.write_stage_params(dest)
    shutil.copytree(base / "data", data_dir, symlinks=True, copy_function=_copy)
    old, new = str(base / "data"), str(data_dir)
    for p in [data_dir / "eval" / "metrics.json", data_dir / "eval" / "report.md"]:
        if p.is_file():
            text = p.read_text()
            p.unlink()
            p.write_text(text.replace(old, new))
    return params_path, data_dir


def run_cli(params_path: Path, stage: str) -> tuple[int, str]:
    """``cnnps run-stage STAGE --params PARAMS`` in this process: (exit status, stderr).

    With one torch thread, as the stage subprocesses that built the upstream outputs
    (``OMP_NUM_THREADS=1``, :mod:`tests.support.faults`): a training step's float
    rounding depends on the thread count, and whatever an earlier test left in this
    process must not decide whether a re-run reproduces the baseline."""
    import torch

    from cnnps.pipeline.cli import main

    err = io.StringIO()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                main(["run-stage", stage, "--params", str(params_path)])
                code = 0
            except SystemExit as exc:
                code = 0 if exc.code is None else (exc.code if isinstance(exc.code, int) else 1)
    finally:
        torch.set_num_threads(threads)
    return code, err.getvalue()


def _state(out: Path) -> dict[str, tuple[str, int]]:
    """{relative path: (sha256 of the bytes, mtime_ns)} of every file under ``out``."""
    from cnnps.infra.hashing import file_sha256

    if not out.is_dir():
        return {}
    return {p.relative_to(out).as_posix(): (file_sha256(p), p.stat().st_mtime_ns)
            for p in sorted(out.rglob("*")) if p.is_file()}


@dataclass
class TryResult:
    case: str  # stage/kind
    seed: int
    action: str
    damaged: str  # the file, relative to data/
    how: str
    exit_status: int
    detected: bool
    reason: str = ""  # why not, when not detected
    error_line: str = ""
    rewritten: list[str] = field(default_factory=list)  # redo: files the rerun rewrote
    fixed: bool | None = None  # stop, with check_fix: the fix the line names restored every output

    def as_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if v not in ("", [], None)}


def run_try(case: Case, seed: int, base: Path, work: Path, check_fix: bool = True) -> TryResult:
    """Damage one file of a copy of ``base`` (seeded), re-run the case's stage, judge it
    (and, for a stop with ``check_fix``, apply the fix its error line names)."""
    from cnnps.infra.hashing import derive_seed64

    params_path, data = work_copy(base, work)
    out = data / faults.OUTPUT_DIRS[case.stage]
    pristine_all = {s: faults.hash_outputs(data, s) for s in faults.STAGES}
    pristine = pristine_all[case.stage]
    rng = np.random.default_rng(derive_seed64("corrupt", case.stage, case.kind, seed))
    dmg = case.damage(data, rng)
    before = _state(out)
    code, err = run_cli(params_path, case.stage)
    after = _state(out)
    lines = [ln for ln in err.splitlines() if ln.startswith(ERROR_PREFIX)]
    res = TryResult(case_id(case), seed, case.action, dmg.path.relative_to(data).as_posix(), dmg.how, code,
                    False, error_line=lines[0] if lines else "")
    if case.action == "stop":
        if code != 2:
            res.reason = f"exit status {code}, expected 2" + (f": {lines[-1]}" if lines else "")
        elif len(lines) != 1:
            res.reason = f"{len(lines)} error lines, expected 1"
        elif str(dmg.path) not in lines[0]:
            res.reason = "the error line does not name the damaged file"
        elif f"cnnps run-stage {case.fix[0]}" not in lines[0]:
            res.reason = f"the error line does not name the fix (`cnnps run-stage {case.fix[0]}`)"
        elif dmg.delete_first is not None and "delete" not in lines[0]:
            res.reason = "the error line does not say to delete the damaged file first"
        elif after != before:
            changed = sorted(set(before) ^ set(after) | {k for k in set(before) & set(after) if before[k] != after[k]})
            res.reason = f"the stage changed its outputs before stopping: {changed[:5]}"
        else:
            res.detected = True
        if res.detected and check_fix:
            res.fixed, why = _apply_fix(case, dmg, params_path, data, pristine_all)
            if not res.fixed:
                res.detected = False
                res.reason = f"the fix did not restore the outputs: {why}"
        return res
    # redo
    rewritten = sorted(k for k in after if before.get(k) != after[k])
    res.rewritten = rewritten
    if code != 0:
        res.reason = f"exit status {code}, expected 0" + (f": {lines[-1]}" if lines else "")
        return res
    diff = faults.differences(pristine, faults.hash_outputs(data, case.stage))
    if diff:
        res.reason = f"outputs differ from the undamaged ones: {diff[:5]}"
        return res
    extra = [k for k in rewritten if not any(fnmatchcase(k, g) for g in dmg.redone)]
    if extra:
        res.reason = f"rewrote more than the damaged part: {extra[:5]}"
        return res
    rel = dmg.path.relative_to(out).as_posix()
    if rel not in rewritten:
        res.reason = "the damaged file was not rewritten"
        return res
    res.detected = True
    return res


def _apply_fix(case: Case, dmg: Damage, params_path: Path, data: Path, pristine_all: dict) -> tuple[bool, str]:
    """Do what the error line says (delete, then re-run the owner and the stage); then
    every stage's outputs must equal the undamaged ones. (ok, why not)."""
    if dmg.delete_first is not None:
        if dmg.delete_first.is_dir():
            shutil.rmtree(dmg.delete_first)
        else:
            dmg.delete_first.unlink()
    for stage in case.fix:
        code, err = run_cli(params_path, stage)
        if code != 0:
            lines = [ln for ln in err.splitlines() if ln.startswith(ERROR_PREFIX)]
            return False, f"cnnps run-stage {stage} exited {code}" + (f": {lines[-1]}" if lines else "")
    for stage, expected in pristine_all.items():
        diff = faults.differences(expected, faults.hash_outputs(data, stage))
        if diff:
            return False, f"{stage} outputs differ: {diff[:5]}"
    return True, ""


def run_corruption_cases(seeds=range(3), cases: list[Case] | None = None, root: str | Path | None = None,
                         progress: bool = False, check_fix: bool = True) -> list[TryResult]:
    """Every try of ``cases`` (default: all) x ``seeds``, on one baseline pipeline."""
    base = baseline(root)
    work = base.parent / "work"
    results = []
    for case in CASES if cases is None else cases:
        for seed in seeds:
            r = run_try(case, seed, base, work, check_fix)
            if progress:
                print(f"{r.case} seed {seed}: {'detected' if r.detected else 'NOT DETECTED: ' + r.reason} ({r.how})",
                      flush=True)
            results.append(r)
    shutil.rmtree(work, ignore_errors=True)
    return results


def summarize(results: list[TryResult]) -> dict:
    """``{"<kind>@<stage>": {"stage", "tried", "detected", "action"}}`` of some tries."""
    out: dict[str, dict] = {}
    for r in results:
        stage, kind = r.case.split("/", 1)
        key = f"{kind}@{stage}"
        d = out.setdefault(key, {"stage": stage, "tried": 0, "detected": 0, "action": r.action})
        d["tried"] += 1
        d["detected"] += int(r.detected)
    return out


def corruption_cases(seeds=range(3), root: str | Path | None = None, check_fix: bool = True) -> dict:
    """Run every corruption kind (``seeds``: tries per kind) and return
    ``{"<kind>@<stage>": {"stage", "tried", "detected", "action": "redo" | "stop"}}``.

    A try is detected when the stage redid exactly the damaged part (redo) or stopped
    with one line naming the file and the fix, exit status 2, its outputs untouched
    (stop) and, with ``check_fix``, the fix that line names restored every output.
    About 3 s a try on 2 busy cores, plus ~40 s to build the pipeline once."""
    return summarize(run_corruption_cases(seeds, root=root, check_fix=check_fix))
