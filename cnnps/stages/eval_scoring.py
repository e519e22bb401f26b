"""The eval stage's scoring: each method's normals on a capture's scored pixels (the
solvers of the registry, CNN-PS at each K, least squares), a seeded pixel sample for
``cnnps score --pixels``, the metrics over captures and light counts, and the shipped
model scored beside a trained one."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cnnps.infra.errors import InputError
from cnnps.stages.eval_params import Params
from cnnps.stages.eval_report import (
    LAMBERTIAN,
    input_picture,
    method_name,
    rig_minus_ortho,
    summarize,
    summarize_by_lights,
    write_report,
)
from cnnps.stages.eval_testset import (
    SPHERE,
)


def model_path_of(params: Params, data_dir: Path) -> Path:
    path = Path(params.model) if params.model is not None else Path(data_dir) / "train" / "model.pt"
    if not path.is_file():
        raise InputError(path, "model not found (run the train stage first, or set eval.model)")
    return path


def pixel_sample(mask: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """A (H, W) bool mask holding ``n`` of ``mask``'s True pixels, drawn without
    replacement by ``numpy.random.default_rng(seed)``; ``mask`` itself when it holds ``n``
    or fewer (or ``n`` is 0). The draw depends only on ``mask``, ``n`` and ``seed``, so every
    model and image subset of a capture is scored on the same pixels.

    Example: ``pixel_sample(np.ones((4, 4), bool), 5).sum() == 5``.
    """
    mask = np.asarray(mask, dtype=bool)
    idx = np.flatnonzero(mask)
    if n <= 0 or n >= idx.size:
        return mask
    keep = np.random.default_rng(seed).choice(idx, size=n, replace=False)
    out = np.zeros(mask.size, dtype=bool)
    out[keep] = True
    return out.reshape(mask.shape)


def evaluate_capture(capture_dir: Path, columns: dict, params: Params, drop=None, pixels: int = 0) -> dict:
    """Normals by every column for one capture; errors where there is ground truth.

    ``columns``: {method name: prepared :class:`cnnps.ps.solver.Solver`}
    (:func:`method_columns`: ``cnn_k<K>`` per ``rotations`` K, every other registered
    solver by its name, ``lambertian``). Each column's normals are computed exactly as
    ``cnnps predict --method <its solver>`` computes them
    (:func:`cnnps.api.prediction_steps.capture_normals_by`: the camera and light model from their
    registries, the pixel stack with ``params.saturated``, the tile loop), the capture's
    pixels read once for all columns. ``drop``: image indices to leave out
    (:func:`cnnps.io.capture.scan_capture`). ``pixels``: score only a seeded sample of that
    many mask pixels (:func:`pixel_sample` with ``params.seed``; 0 = all).

    Rig captures are scored as ``cnnps predict`` treats them: with ``intrinsics.txt`` the
    pinhole camera gives each pixel its view; with ``light_positions.txt`` every column runs
    the rounds of normals and depth of the ``point`` light model (from the median depth a
    render's ``scene.json`` records, as a measured ``--distance``, unless ``rig_distance``
    is "estimated" or there is none: then the scale is estimated, as without
    ``--distance``), and with ``depth_gt.npy`` the last depth is scored too
    (``depth_median_rel_error`` beside each method's angular errors).

    Returns ``{"capture", "n_images", "pixels", "scored_pixels", "normals": {method: (H,W,3)},
    "errors": {method: (H,W)}, "scores": {method: GroundTruthScore}, "methods": {method: stats},
    "mask", "gt", "scored", "input"}`` (scores, errors, stats and scored only with ground truth).
    """
    from cnnps.api.prediction_steps import capture_normals_by
    from cnnps.io.capture import read_scene, scan_capture
    from cnnps.ps.metrics import score_normals

    cap = scan_capture(capture_dir, drop=drop)
    if pixels:
        cap.mask = pixel_sample(cap.mask, pixels, params.seed)
    opts = prediction_options(params)
    if cap.light_positions is not None and params.rig_distance == "known":
        opts["distance"] = (read_scene(capture_dir) or {}).get("median_depth")
    found = capture_normals_by(cap, columns, opts)
    normals = {m: f.normal for m, f in found.items()}

    out = {
        "capture": str(capture_dir),
        "n_images": cap.n_images,
        "pixels": cap.n_pixels,
        "normals": normals,
        "errors": {},
        "scores": {},
        "methods": {},
        "mask": cap.mask,
        "gt": cap.normal_gt,
        "input": input_picture(cap),
    }
    if cap.normal_gt is not None:
        for m, n in normals.items():
            score = score_normals(n, cap.normal_gt, cap.mask, capture_dir)
            out["scores"][m] = score
            out["errors"][m] = score.errors
            out["methods"][m] = score.stats
        out["scored"] = score.scored
        out["scored_pixels"] = int(score.scored.sum())
    if cap.depth_gt is not None and out["methods"]:
        gt = cap.depth_gt
        for m, f in found.items():
            if f.depth is not None:
                rel = np.abs(f.depth[cap.mask] - gt[cap.mask]) / gt[cap.mask]
                out["methods"][m]["depth_median_rel_error"] = float(np.median(rel))
    return out


def prediction_options(params: Params) -> dict:
    """:func:`cnnps.predict`'s options, checked and completed with its defaults, as the
    eval stage's ``params`` set them (``device``, ``precision``, ``batch_size``,
    ``saturated``, ``sparse_fill``): what every column's solver and the capture's camera,
    light model and pixel stack are made with."""
    from cnnps.api.prediction_options import check_options, with_defaults

    return check_options(with_defaults({"device": params.device, "precision": params.precision,
                                        "batch_size": params.batch_size or None, "saturated": params.saturated,
                                        "sparse_fill": params.sparse_fill}))


def method_columns(params: Params, model_path: Path, *, fix: str = "replace it with an intact copy") -> dict:
    """{column name: prepared solver}: the network (``cnn`` with ``model_path``) once per
    ``params.rotations`` K (``cnn_k<K>``), every other solver of the registry
    (:data:`cnnps.api.solvers.SOLVERS`) by its name with :func:`cnnps.predict`'s defaults,
    and least squares (``lambertian``, with ``lambertian_shadow_threshold``) last, each
    prepared as ``cnnps predict --method NAME`` prepares it. A damaged model is one line
    naming the file and ``fix``."""
    from cnnps.api.solvers import SOLVERS, prepare_solver

    base = prediction_options(params)
    wanted = [(method_name(k), {"method": "cnn", "model": str(model_path), "rotations": int(k)})
              for k in params.rotations]
    wanted += [(name, {"method": name}) for name in SOLVERS if name not in ("cnn", LAMBERTIAN)]
    wanted.append((LAMBERTIAN, {"method": LAMBERTIAN, "shadow_threshold": params.lambertian_shadow_threshold}))
    try:
        return {name: prepare_solver({**base, **own}) for name, own in wanted}
    except InputError as exc:  # the checkpoint, named
        raise InputError(exc.path, f"{exc.problem}; {fix}") from None


def columns_precision(columns: dict) -> str | None:
    """The network's precision among prepared ``columns`` (what its record says), or None."""
    for solver in columns.values():
        precision = solver.record({}, 0, True).get("precision")
        if precision is not None:
            return precision
    return None


def evaluate_all(captures, columns: dict, params: Params, out_dir: Path, model_label: str, t0: float | None = None) -> dict:
    """Score ``captures`` ([(name, folder, "synthetic" | "real"[, drop])]); write the report;
    return the metrics (:func:`capture_metrics`). ``columns``: as :func:`evaluate_capture`. ``drop``: image indices left out of that
    capture; a real capture given a ``drop`` is an image subset of its folder
    (``summary_real_subsets``). A real capture without one is scored under the DiLiGenT
    benchmark's rule (:data:`cnnps.io.capture.DILIGENT_RULES`: bearPNG without its first 20 images)."""
    t0 = time.perf_counter() if t0 is None else t0
    results = score_all(captures, columns, params)
    metrics = capture_metrics(results, list(columns), params, model_label, t0)
    write_report(out_dir, results, metrics)
    return metrics


def score_all(captures, columns: dict, params: Params) -> dict[str, dict]:
    """{name: :func:`evaluate_capture`'s result, plus ``kind`` and ``subset`` (a real
    capture's image subset: True when a ``drop`` was given)} for ``captures`` as in
    :func:`evaluate_all`, with a progress bar."""
    from cnnps.infra.progress import progress_bar
    from cnnps.io.capture import DILIGENT_RULES, benchmark_drop

    results: dict[str, dict] = {}
    for name, path, kind, *drop in progress_bar(captures, desc="eval", unit="capture", leave=True):
        subset = kind == "real" and bool(drop) and drop[0] is not None
        given = drop[0] if drop else None
        if kind == "real" and given is None:
            given = benchmark_drop(path, DILIGENT_RULES)  # the real objects are scored as the benchmark scores them
        r = evaluate_capture(path, columns, params, drop=given,
                             pixels=params.real_pixels if kind == "real" else 0)
        r["kind"] = kind
        r["subset"] = subset
        results[name] = r
    return results


def real_summaries(results: dict[str, dict], exclude=()) -> tuple[dict, dict]:
    """(``summary_real``, ``summary_real_subsets``): :func:`summarize` of the real captures
    from all their images, and per image count (a string key) of their subsets, leaving out
    the captures whose folder is named in ``exclude`` (and their subsets)."""
    real = {n: r for n, r in results.items()
            if r.get("kind") == "real" and Path(r["capture"]).name not in set(exclude)}
    counts = sorted({int(r["n_images"]) for r in real.values() if r.get("subset")}, reverse=True)
    return (summarize({n: r for n, r in real.items() if not r.get("subset")}),
            {str(c): summarize({n: r for n, r in real.items() if r.get("subset") and int(r["n_images"]) == c})
             for c in counts})


def capture_metrics(results: dict[str, dict], methods: list[str], params: Params, model_label: str, t0: float,
                    **extra) -> dict:
    """What ``metrics.json`` holds for ``results`` (:func:`score_all`) of the columns
    ``methods``; ``extra`` keys are added (e.g. the network's ``precision``)."""
    summary_real, summary_real_subsets = real_summaries(results, params.real_exclude_from_mean)
    return {
        "model": model_label,
        **extra,
        "methods": methods,
        "summary": summarize({n: r for n, r in results.items() if r["kind"] == "synthetic"}),
        "summary_real": summary_real,
        "summary_real_subsets": summary_real_subsets,
        "real_exclude_from_mean": list(params.real_exclude_from_mean),
        "summary_rig": summarize({n: r for n, r in results.items() if r["kind"] == "rig"}),
        "rig_minus_ortho": rig_minus_ortho(results),
        "by_lights": summarize_by_lights({n: r for n, r in results.items() if r["kind"] == "synthetic"}),
        # test captures are named <shape>-<category>-<lights> (testset_plan): all but the sphere
        "by_lights_nonconvex": summarize_by_lights({n: r for n, r in results.items() if r["kind"] == "synthetic"
                                                    and not n.startswith(f"{SPHERE}-")}),
        "captures": {
            n: {
                "capture": r["capture"],
                "kind": r["kind"],
                **({"subset_of": Path(r["capture"]).name} if r.get("subset") else {}),
                "n_images": r["n_images"],
                "pixels": r["pixels"],
                "scored_pixels": r.get("scored_pixels", 0),
                "methods": r["methods"],
            }
            for n, r in results.items()
        },
        "seconds": round(time.perf_counter() - t0, 2),
    }


def score_shipped(metrics: dict, params: Params, rotations: int = 10) -> dict | None:
    """The shipped model (:mod:`cnnps.models.shipped`) with ``rotations`` K on the synthetic
    captures of an eval run's ``metrics``, scored as the run scored its own model:
    ``{"captures": {name: stats}, "summary": stats, "label": str}`` (what
    :func:`cnnps.stages.eval_report.format_table` shows as its ``shipped`` column); None
    when the run scored no synthetic capture."""
    from cnnps.api.solvers import prepare_solver

    captures = {name: Path(c["capture"]) for name, c in metrics.get("captures", {}).items()
                if c.get("kind") == "synthetic" and c.get("methods")}
    if not captures:
        return None

    from cnnps.models.shipped import read_provenance, shipped_model_path

    path = shipped_model_path()
    name = method_name(int(rotations))
    column = {name: prepare_solver({**prediction_options(params), "model": str(path), "rotations": int(rotations)})}
    scores = {capture: evaluate_capture(folder, column, params)["methods"][name] for capture, folder in captures.items()}
    summary = {"mean_deg": float(np.mean([s["mean_deg"] for s in scores.values()])),
               "median_deg": float(np.mean([s["median_deg"] for s in scores.values()])),
               "captures": len(scores)}
    prov = read_provenance(path)
    note = str(prov.get("note", ""))
    version = note.split(" ", 1)[0] + " " if note.startswith("v") else ""
    label = f"{version}{path.name}, sha256 {str(prov.get('sha256', ''))[:8]}"
    return {"captures": scores, "summary": summary, "label": label}
