"""The model shipped in ``cnnps/models/weights/``: where it is, how it was made, is it intact.

``cnnps_default.pt`` is a checkpoint (half-precision weights, see
:mod:`cnnps.models.checkpoint`); ``cnnps_default.json`` is its provenance: preset, data hash,
commit, validation error, date, and the file's SHA-256, which :func:`shipped_model_path`
checks before the model is used. Earlier models kept beside it (``cnnps_v5.pt`` with
``cnnps_v5.json``) are checked the same way when a path names them (:func:`verify_if_shipped`).
"""

from __future__ import annotations

import datetime as _dt
import json
import subprocess
from pathlib import Path

from cnnps.infra.atomic import write_text
from cnnps.infra.errors import CnnpsError
from cnnps.infra.hashing import file_sha256

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_NAME = "cnnps_default"


def weights_path(name: str = DEFAULT_NAME) -> Path:
    return WEIGHTS_DIR / f"{name}.pt"


def provenance_path(name: str = DEFAULT_NAME) -> Path:
    return weights_path(name).with_suffix(".json")


def read_provenance(weights: Path) -> dict:
    """The provenance record next to ``weights`` (same name, ``.json``)."""
    path = Path(weights).with_suffix(".json")
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise CnnpsError(f"{path}: provenance file of the shipped model is missing (reinstall cnnps)") from None
    except json.JSONDecodeError as exc:
        raise CnnpsError(f"{path}: provenance file is damaged ({exc})") from None


def verify_shipped(weights: str | Path) -> Path:
    """Check shipped weights against the SHA-256 recorded in their provenance; return the path."""
    path = Path(weights)
    if not path.is_file():
        raise CnnpsError(
            f"{path}: no shipped model: train one with `cnnps run-stage train` (or `dvc repro`) "
            "and pass --model data/train/model.pt, or use --method lambertian"
        )
    expected = read_provenance(path).get("sha256")
    actual = file_sha256(path)
    if expected != actual:
        raise CnnpsError(
            f"{path}: shipped model is damaged (SHA-256 {actual[:12]}... does not match {str(expected)[:12]}... "
            f"recorded in {path.with_suffix('.json').name}); restore it with `git checkout -- {path}` or reinstall"
        )
    return path


def shipped_model_path(name: str = DEFAULT_NAME) -> Path:
    """Path of the verified shipped weights."""
    return verify_shipped(weights_path(name))


def is_shipped(path: str | Path) -> bool:
    """Whether ``path`` is a weights file of this folder: the default or a named earlier model
    (``cnnps_v5.pt``), each with its provenance record beside it."""
    p = Path(path)
    return p.suffix == ".pt" and p.resolve().parent == WEIGHTS_DIR.resolve()


def verify_if_shipped(path: str | Path) -> Path:
    """``path``, its SHA-256 checked first when it is one of the shipped files (:func:`is_shipped`)."""
    return verify_shipped(path) if is_shipped(path) else Path(path)


def trained_min_lights(model_path: str | Path, meta: dict) -> int | None:
    """The fewest lights the model's training maps had: the checkpoint's ``meta``, else, for
    shipped weights whose checkpoint does not record it, their provenance record."""
    if meta.get("min_lights") is not None:
        return int(meta["min_lights"])
    path = Path(model_path)
    if path.with_suffix(".json").is_file():
        value = read_provenance(path).get("min_lights")
        return None if value is None else int(value)
    return None


def _git_commit(repo: Path) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def ship(checkpoint: str | Path, provenance: dict, name: str = DEFAULT_NAME) -> Path:
    """Copy a trained checkpoint into ``cnnps/models/weights`` (float16 weights) with its provenance."""
    from cnnps.models.checkpoint import load_checkpoint, save_checkpoint

    model, config, meta = load_checkpoint(checkpoint, "cpu")
    out = save_checkpoint(weights_path(name), model, config, {**meta, "shipped_from": str(checkpoint)}, half=True)
    record = {
        "file": out.name,
        "sha256": file_sha256(out),
        "bytes": out.stat().st_size,
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "commit": _git_commit(WEIGHTS_DIR),
        "config": config,
        "train_meta": meta,
        **provenance,
    }
    if meta.get("min_lights") is not None:  # what `cnnps predict` warns below (see trained_min_lights)
        record["min_lights"] = int(meta["min_lights"])
    write_text(provenance_path(name), json.dumps(record, indent=2, sort_keys=True) + "\n")
    return out


def main(argv: list[str] | None = None) -> None:
    """``python -m cnnps.models.shipped CHECKPOINT --preset NAME [--manifest PATH] [--note TEXT] [--init-provenance JSON]``"""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m cnnps.models.shipped", description=main.__doc__)
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--preset", required=True)
    ap.add_argument("--manifest", type=Path, help="extract manifest.json of the training data (hashed)")
    ap.add_argument("--note", default="")
    ap.add_argument("--init-provenance", type=Path,
                    help="provenance JSON of the model the training started from (train.init), kept as 'init'")
    args = ap.parse_args(argv)
    record = {"preset": args.preset, "note": args.note}
    if args.init_provenance:
        record["init"] = json.loads(args.init_provenance.read_text())
    if args.manifest:
        manifest = json.loads(args.manifest.read_text())
        record["data"] = {
            "manifest_sha256": file_sha256(args.manifest),
            "total_rows": manifest.get("total_rows"),
            "train_rows": manifest.get("train_rows"),
            "val_rows": manifest.get("val_rows"),
            "train_scenes": len(manifest.get("train_scenes", [])),
            "val_scenes": len(manifest.get("val_scenes", [])),
        }
    out = ship(args.checkpoint, record)
    print(f"shipped {out} ({out.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
