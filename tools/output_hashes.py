"""Hashes of the outputs a refactoring must not move, for the checkout on ``PYTHONPATH``.

Run it once per checkout and compare the two files: a change that only moves code gives
the same hashes, byte for byte::

    PYTHONPATH=/tmp/base .venv/bin/python tools/output_hashes.py --out /tmp/base.json
    PYTHONPATH=.          .venv/bin/python tools/output_hashes.py --out /tmp/head.json
    .venv/bin/python tools/output_hashes.py --compare /tmp/base.json /tmp/head.json

What it hashes (each in a fresh folder under ``--work``, every command run with the
``cnnps`` of ``PYTHONPATH``):

- ``shards``: the tiny pipeline (one mesh, 16 x 16 pictures, 12 lights;
  tests/pipeline/conftest.py) through meshes, materials, render and extract: every
  shard's bytes and the manifest;
- ``pixelwise``: per-pixel batches of :func:`cnnps.synth.pixelwise.generate` at fixed
  seeds (grey with every effect, colour, sparse, narrow lobes);
- ``train``: a 6-step per-pixel training run (checkpoints at steps 3 and 6, a weight
  average): its run key, each checkpoint's tensors and ``model.pt``'s weights;
- ``predict``: ``cnnps predict`` of the shipped model on DiLiGenT BALL (``--shared``) at
  K = 1 and K = 10, fp32: the normals' bytes;
- ``eval``: the eval stage on the tiny pipeline's model: its ``metrics.json`` without times.

Blender (for ``shards`` and ``eval``) and BALL are needed; a part that cannot run says why.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
TIMING_KEYS = {"seconds", "wall_seconds", "elapsed_s", "time_s", "started", "finished", "samples_per_s", "probe_seconds"}


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def tensor_hash(obj) -> str:
    """SHA-256 of a nested structure of tensors and plain values, in key order."""
    import torch

    h = hashlib.sha256()

    def walk(x):
        if isinstance(x, torch.Tensor):
            h.update(x.detach().cpu().contiguous().numpy().tobytes())
        elif isinstance(x, dict):
            for k in sorted(x, key=str):
                h.update(str(k).encode())
                walk(x[k])
        elif isinstance(x, (list, tuple)):
            for v in x:
                walk(v)
        else:
            h.update(repr(x).encode())

    walk(obj)
    return h.hexdigest()


def cnnps(*args, cwd: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "cnnps", *map(str, args)], cwd=cwd, capture_output=True, text=True,
                         env=dict(os.environ, OMP_NUM_THREADS="1"))
    if out.returncode:
        raise SystemExit(f"cnnps {' '.join(map(str, args))} failed:\n{(out.stdout + out.stderr)[-3000:]}")


def tiny_pipeline(work: Path) -> Path:
    """The tiny params of the pipeline tests (tests/pipeline/conftest.py) and their mesh in
    ``work``, written by this repository's tests package in a process of its own (this
    one's ``cnnps`` is the checkout under test); returns the params file."""
    code = ("import sys, yaml; from pathlib import Path; from tests.pipeline.conftest import tiny_params; "
            "from tests.support.meshes import write_tiny_mesh; w = Path(sys.argv[1]); "
            "write_tiny_mesh(w / 'meshes_in' / 'ball.obj'); p = tiny_params(w / 'meshes_in'); "
            "p['data_dir'] = str(w / 'data'); p['eval']['model'] = str(w / 'data' / 'train' / 'model.pt'); "
            "(w / 'params.yaml').write_text(yaml.safe_dump(p, sort_keys=False))")
    subprocess.run([sys.executable, "-c", code, str(work)], check=True, env=dict(os.environ, PYTHONPATH=str(REPO)))
    return work / "params.yaml"


def shards(work: Path) -> dict:
    file = tiny_pipeline(work)
    for stage in ("meshes", "materials", "render", "extract"):
        cnnps("run-stage", stage, "--params", file, cwd=work)
    ex = work / "data" / "extract"
    out = {p.name: sha(p.read_bytes()) for p in sorted(ex.glob("*.parquet"))}
    for p in sorted(ex.glob("*.json")):  # a scene's marker records its time, outside its checksum
        record = {k: v for k, v in json.loads(p.read_text()).items() if k not in TIMING_KEYS}
        out[p.name] = sha(json.dumps(record, sort_keys=True).encode())
    return out


def pixelwise() -> dict:
    import torch

    from cnnps.synth.pixelwise import generate

    try:
        from cnnps.synth.effect_settings import Effects
    except ImportError:  # a checkout from before the generator's split
        from cnnps.synth.pixelwise import Effects

    cases = {
        "grey_effects": dict(effects=Effects(cast_shadow=0.3, interreflection=0.3, ambient=0.05, intensity_error=0.05,
                                             noise=0.01, saturation=0.1, quantisation=0.3, boundary_mix=0.1,
                                             interreflection_share=0.5, ambient_share=0.5, grazing_falloff=0.3)),
        "rgb": dict(rgb=True, effects=Effects(ambient=0.05, noise=0.01)),
        "sparse": dict(sparse_fraction=0.5, cone_max_deg=50.0),
        "narrow": dict(categories=("narrow", "metallic")),
    }
    out = {}
    for name, kw in cases.items():
        maps, normals = generate(64, generator=torch.Generator().manual_seed(7), n_lights=256, **kw)
        out[name] = sha(maps.numpy().tobytes() + normals.numpy().tobytes())
    return out


def train(work: Path) -> dict:
    import torch

    params = {"seed": 3, "data_dir": str(work / "data"), "meshes": {"procedural": 1},
              "train": {"max_steps": 6, "checkpoint_every": 3, "keep_checkpoints": 5, "val_every": 0, "log_every": 2,
                        "progress": False, "precision": "fp32", "val_max_rows": 64,
                        "optimiser": {"lr": 2e-3, "lr_milestones": [4], "lr_gamma": 0.5, "average_from": 3},
                        "data": {"batch_size": 32},
                        "pixelwise": {"share": 1.0, "w": 16, "lights": 64, "effects": {"ambient": 0.05}},
                        "cpu": {"threads": 1, "step_processes": 1}}}
    file = work / "train.yaml"
    file.write_text(yaml.safe_dump(params, sort_keys=False))
    cnnps("run-stage", "train", "--params", file, cwd=work)
    out = {}
    for ck in sorted((work / "data" / "train" / "checkpoints").glob("step-*.pt")):
        state = torch.load(ck, map_location="cpu", weights_only=False)
        out[ck.name] = {"run_key": state.get("run_key"),
                        "tensors": tensor_hash({k: state[k] for k in ("model", "optim", "torch_rng", "history",
                                                                      "average") if k in state})}
    out["model.pt"] = tensor_hash(torch.load(work / "data" / "train" / "model.pt", map_location="cpu",
                                             weights_only=False))
    return out


def predict(work: Path, shared: Path) -> dict:
    import numpy as np

    ball = shared / "diligent" / "ballPNG"
    if not ball.is_dir():
        return {"skipped": f"{ball}: not here"}
    out = {}
    for k in (1, 10):
        dst = work / f"ball-k{k}"
        cnnps("predict", ball, "--out", dst, "--rotations", k, "--precision", "fp32", "--device", "cpu", cwd=work)
        files = sorted(dst.glob("*.npy"))
        out[f"k{k}"] = {p.name: sha(np.load(p).tobytes()) for p in files}
    return out


def evaluation(work: Path) -> dict:
    file = work / "params.yaml"
    params = yaml.safe_load(file.read_text())
    params["train"]["precision"] = "fp32"
    file.write_text(yaml.safe_dump(params, sort_keys=False))
    cnnps("run-stage", "train", "--params", file, cwd=work)
    cnnps("run-stage", "eval", "--params", file, cwd=work)
    metrics = json.loads((work / "data" / "eval" / "metrics.json").read_text())

    def strip(x):
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k not in TIMING_KEYS}
        if isinstance(x, list):
            return [strip(v) for v in x]
        return x

    text = json.dumps(strip(metrics), sort_keys=True).replace(str(work), "WORK")  # paths name the work folder
    return {"metrics": sha(text.encode())}


def flat(tree: dict, prefix: str = "") -> dict:
    """``{"a": {"b": h}}`` as ``{"a/b": h}``."""
    out = {}
    for k, v in tree.items():
        out.update(flat(v, f"{prefix}{k}/") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path)
    ap.add_argument("--work", type=Path, help="a folder for the runs (default: a new temporary one)")
    ap.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--parts", nargs="+", default=["shards", "pixelwise", "train", "predict", "eval"])
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"), help="compare two files of this script")
    a = ap.parse_args(argv)
    if a.compare:
        x, y = (flat(json.loads(p.read_text())["hashes"]) for p in a.compare)
        differ = [k for k in sorted(set(x) | set(y)) if x.get(k) != y.get(k)]
        for k in sorted(set(x) | set(y)):
            print(f"{k}: {'same' if k not in differ else 'DIFFERENT'}")
        print(f"{len(set(x) | set(y)) - len(differ)} same, {len(differ)} different")
        return 1 if differ else 0
    import cnnps as package

    work = a.work or Path(tempfile.mkdtemp(prefix="cnnps-hashes-"))
    work.mkdir(parents=True, exist_ok=True)
    # parts already in --out (a run cut short) are kept, the rest made
    hashes = json.loads(a.out.read_text())["hashes"] if a.out and a.out.is_file() else {}
    makers = {"shards": lambda: shards(work / "pipe"), "pixelwise": pixelwise, "train": lambda: train(work / "train"),
              "predict": lambda: predict(work / "predict", a.shared), "eval": lambda: evaluation(work / "pipe")}
    for part in ("shards", "pixelwise", "train", "predict", "eval"):
        if part in hashes or (part not in a.parts and not (part == "shards" and "eval" in a.parts)):
            continue
        (work / {"shards": "pipe", "eval": "pipe"}.get(part, part)).mkdir(parents=True, exist_ok=True)
        hashes[part] = makers[part]()
        if a.out:
            a.out.write_text(json.dumps({"cnnps": str(Path(package.__file__).parent), "hashes": hashes}, indent=1) + "\n")
    record = {"cnnps": str(Path(package.__file__).parent), "hashes": hashes}
    text = json.dumps(record, indent=1)
    if a.out:
        a.out.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
