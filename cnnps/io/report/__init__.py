"""``report.html``: one self-contained page of a prediction, opened from disk.

:func:`report_html` makes the page from a prediction's arrays and record
(:mod:`cnnps.io.report.page` says what it shows and how); :func:`write_report` writes it
into a folder being written (``cnnps predict``'s OUT_DIR, inside its atomic write);
:func:`rebuild_report` makes it again from a finished OUT_DIR (``cnnps report``),
written atomically while it holds the folder; :func:`notebook_html` is the page in an
``<iframe srcdoc>`` for a notebook (smaller maps). The page holds everything it shows:
it makes no request, so it opens the same with no network. Large maps are averaged over
blocks to at most :data:`~cnnps.io.report.data.RELIT_SIDE` cells a side (the mesh
:data:`~cnnps.io.report.data.MESH_SIDE` vertices), which keeps a 12-megapixel
prediction's page at a few MB.
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from cnnps.infra.errors import InputError
from cnnps.io.report.data import MESH_SIDE, RELIT_SIDE
from cnnps.io.report.page import page_html

REPORT_FILE = "report.html"
RECORD_FILE = "prediction.json"  # what a predict OUT_DIR holds (cnnps.api.prediction_outputs)
NORMAL_FILE = "normal.npy"
CONFIDENCE_FILE = "confidence.npy"
DEPTH_FILE = "depth.npy"
METRICS_FILE = "metrics.json"
ERROR_PICTURE_FILE = "error.png"
NOTEBOOK_SIDES = (512, 160)  # (maps, mesh) in a notebook

__all__ = ["REPORT_FILE", "report_html", "write_report", "rebuild_report", "notebook_html", "RELIT_SIDE",
           "MESH_SIDE"]


def report_html(normals, mask, record: dict, *, confidence=None, errors=None, scored=None, stats=None,
                depth=None, max_side: int = RELIT_SIDE, mesh_side: int = MESH_SIDE) -> str:
    """The page of one prediction. ``normals`` (H, W, 3) unit normals, zeros off ``mask``
    (H, W bool); ``record``: what ``prediction.json`` holds; ``confidence`` (H, W) in
    [0, 1] or None; ``errors`` (H, W) angular errors in degrees on the ``scored`` pixels
    (default: the mask) and their ``stats`` (``mean_deg``, ...), or None; ``depth``
    (H, W), NaN off the surface (under a pinhole camera, ``record["camera"]["intrinsics"]``
    places its points), or None. ``max_side`` / ``mesh_side``: the longest side of the
    maps / of the mesh on the page."""
    return page_html(normals, mask, record, confidence=confidence, errors=errors, scored=scored, stats=stats,
                     depth=depth, max_side=max_side, mesh_side=mesh_side)


def write_report(folder, normals, mask, record: dict, **views) -> Path:
    """Write :func:`report_html` (``views``: its keyword arguments) as ``folder/report.html``,
    a plain write: the caller's folder is the atomic unit. Returns the path."""
    path = Path(folder) / REPORT_FILE
    path.write_text(report_html(normals, mask, record, **views), encoding="utf-8")
    return path


def notebook_html(normals, mask, record: dict, **views) -> str:
    """The page in an ``<iframe srcdoc>`` (its scripts and styles kept apart from the
    notebook's), maps at most 512 cells a side, the mesh 160 vertices."""
    views.setdefault("max_side", NOTEBOOK_SIDES[0])
    views.setdefault("mesh_side", NOTEBOOK_SIDES[1])
    page = report_html(normals, mask, record, **views)
    return (f'<iframe class="cnnps-report" srcdoc="{html.escape(page, quote=True)}" '
            'style="width:100%;height:900px;border:1px solid #ccc;border-radius:6px"></iframe>')


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot be read as JSON ({exc})") from None


def _check_folder(out_dir: Path) -> None:
    if not out_dir.is_dir():
        raise InputError(out_dir, "not a folder" if out_dir.exists() else "folder not found")


def folder_views(out_dir: Path) -> dict:
    """What :func:`report_html` needs, read from a predict OUT_DIR: the arrays, the record,
    the stats from metrics.json; the per-pixel errors again from the capture's ground
    truth when the capture (``record["capture"]``) can still be read, else error.png's
    picture. InputError naming ``out_dir`` when it is not a predict output folder."""
    out_dir = Path(out_dir)
    _check_folder(out_dir)
    missing = [n for n in (RECORD_FILE, NORMAL_FILE) if not (out_dir / n).is_file()]
    if missing:
        raise InputError(out_dir, f"not a cnnps predict output folder (no {' or '.join(missing)})")
    record = _read_json(out_dir / RECORD_FILE)
    try:
        normals = np.load(out_dir / NORMAL_FILE, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise InputError(out_dir / NORMAL_FILE, f"cannot be read ({exc})") from None
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise InputError(out_dir / NORMAL_FILE, f"is not an H x W x 3 normal map (shape {normals.shape})")
    mask = np.any(normals != 0, axis=2)
    views = {"normals": normals, "mask": mask, "record": record}
    for key, name in (("confidence", CONFIDENCE_FILE), ("depth", DEPTH_FILE)):
        if (out_dir / name).is_file():
            views[key] = np.load(out_dir / name, allow_pickle=False)
    if (out_dir / METRICS_FILE).is_file():
        metrics = _read_json(out_dir / METRICS_FILE)
        views["stats"] = {k: v for k, v in metrics.items() if k.endswith("_deg")}
        views.update(_rescored(record, normals, mask, views["stats"], out_dir))
    return views


def _rescored(record: dict, normals, mask, stats: dict, out_dir: Path) -> dict:
    """The errors and scored pixels again (the capture's ground truth and mask), with
    their full stats; else error.png's picture."""
    from cnnps.io.capture.files import read_mask_file, read_normal_gt
    from cnnps.ps.metrics import score_normals

    capture = Path(str(record.get("capture") or ""))
    try:
        gt = read_normal_gt(capture, mask.shape) if record.get("capture") and capture.is_dir() else None
        if gt is not None:
            capture_mask = read_mask_file(capture, mask.shape, required=False)
            scored = score_normals(normals, gt, mask if capture_mask is None else capture_mask, capture)
            return {"errors": scored.errors, "scored": scored.scored, "stats": scored.stats}
    except (InputError, OSError, ValueError):
        pass
    picture = out_dir / ERROR_PICTURE_FILE
    if picture.is_file():
        import base64

        return {"error_picture_url": "data:image/png;base64," + base64.b64encode(picture.read_bytes()).decode()}
    return {}


def rebuild_report(out_dir) -> Path:
    """Make ``out_dir/report.html`` again from a finished predict OUT_DIR
    (:func:`folder_views`), written atomically (temporary name, then rename), holding the
    folder as one of its writers (:class:`cnnps.infra.output_folder.OutputFolder`:
    FolderBusy at once while a prediction writes it). Returns its path; InputError naming
    ``out_dir`` when it is not a predict output folder."""
    from cnnps.infra.atomic import atomic_path
    from cnnps.infra.output_folder import OutputFolder

    out_dir = Path(out_dir)
    _check_folder(out_dir)  # before the lock, which makes a work folder beside it
    with OutputFolder(out_dir, "cnnps report"):
        views = folder_views(out_dir)
        path = out_dir / REPORT_FILE
        with atomic_path(path) as tmp:
            Path(tmp).write_text(page_html(**views), encoding="utf-8")
    return path
