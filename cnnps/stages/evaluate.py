"""The ``eval`` stage: score the trained model on a held-out synthetic test set.

The test set follows the spirit of CyclesPSTest: a sphere and two strongly non-convex
procedural shapes that training never sees (their own seeds), covered with
``superpixels`` superpixels of the Specular and the Metallic material categories drawn
from ``ranges`` (its own BSDF ranges, the paper's by default: a fixed yardstick whatever
``materials.ranges`` trains on), lit by 17 and by 305 uniform (not jittered) lights. It
is built with the synthesis library
(:mod:`cnnps.synth`: meshes, superpixel materials, :func:`cnnps.synth.capture_render.render_capture`)
under ``data_dir/eval/testset/`` and cached there like any stage output (unchanged
captures are not re-rendered). Blender (bpy, the ``cnnps[render]`` extra) is needed only
to render captures that are not cached yet; without it that is one line (ConfigError),
and a stage with only ``real_captures`` never needs it.

Every capture (synthetic ones and the optional ``real_captures``, DiLiGenT layout) is
scored on the same pixels (mask pixels with a ground-truth normal,
:func:`cnnps.ps.metrics.score_normals`) by:

- CNN-PS with each ``rotations`` K (default K=1 and K=10), column ``cnn_k<K>``,
- every other solver of the registry (:data:`cnnps.api.solvers.SOLVERS`), by its name,
- the least-squares Lambertian baseline (:class:`cnnps.ps.least_squares.LeastSquaresSolver`).

Each column's normals are ``cnnps predict --method <solver>``'s, computed by its own steps
(:func:`cnnps.api.prediction_steps.capture_normals_by`: the solver prepared from the registry,
the camera and light model from theirs, the pixel stack, the tile loop): with
``saturated: exclude`` (the default, as ``cnnps predict``) an observation with a channel
at 0.99 of an integer format's maximum is missing for every method (float renders have
none), and the network's maps get the Lambertian fill of ``sparse_fill``. A colour model
(4 input channels) is refused as ``cnnps predict`` refuses it: both read the grey values.
:func:`score_real` scores the real
captures alone (what ``cnnps score`` runs): the same numbers as this stage. Real
captures are scored as the DiLiGenT benchmark scores its objects: its rule
(:data:`cnnps.io.capture.DILIGENT_RULES`: bearPNG without its first 20 images) is
applied to them, and their sparse subsets are drawn from the images it leaves.

Outputs (the report and pictures are replaced together at the end):

- ``data_dir/eval/metrics.json``: per capture and method the error statistics
  (``mean_deg``, ``median_deg``, ...), plus a ``summary`` (mean over synthetic captures),
  ``summary_real`` (mean over the real captures from all their images, except
  ``real_exclude_from_mean``), ``summary_real_subsets`` (the same per subset image count),
  and ``by_lights`` / ``by_lights_nonconvex`` (per light count, all
  test shapes / all but the sphere: means and each CNN's ratio to least squares, the
  columns ``dvc exp show`` compares experiments by);
- ``data_dir/eval/report.md``: a Markdown table and, per capture, input image,
  predicted normals, ground truth and error maps (PNGs in ``data_dir/eval/pictures/``).

Damaged inputs: the model is loaded (and verified: weights SHA-256, zip CRCs and, for the
train stage's ``model.pt``, its ``model.pt.sha256``; :mod:`cnnps.models.checkpoint`)
before anything is rendered or written, and a damaged one stops the stage with one line
naming the file and the fix. Test captures are cached render folders: a damaged one is
re-rendered (:mod:`cnnps.synth.capture_render`); a real capture with an unreadable or
non-finite image stops the stage, naming it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np

from cnnps.infra.errors import ConfigError, InputError
from cnnps.infra.machine import Device
from cnnps.infra.options import Count, Range, UnitFraction, check_fields
from cnnps.ps.sparse_fill import SparseFill
from cnnps.stages.eval_report import (  # noqa: F401 (format_table: part of this stage's API)
    LAMBERTIAN,
    PICTURE_MIN_SIZE,
    format_table,
    input_picture,
    method_name,
    rig_minus_ortho,
    summarize,
    summarize_by_lights,
    write_report,
)
from cnnps.stages.eval_testset import (  # noqa: F401 (part of this stage's API)
    SPHERE,
    TEST_SEED_OFFSET,
    build_rig_twins,
    build_testset,
    rig_name,
    test_mesh,
    testset_plan,
)
from cnnps.synth.bsdf import MaterialRanges, checked_categories, checked_ranges


@dataclass(frozen=True)
class Rig:
    """The rig of the test set's twins (``eval.rig``): a pinhole camera with ``fov_deg``
    across the image and, with ``light_distance`` d, point lights d object radii from the
    object's centre (None: the distant lights of the orthographic captures). The default,
    3 radii, is 1.5 object sizes: an LED ring or dome as near as rigs build them. ``size``:
    the twins' image size; None renders them so that the object spans as many pixels as
    in its orthographic capture (:func:`cnnps.stages.eval_testset.twin_size`), so that
    ``rig_minus_ortho`` measures the rig and not a smaller object."""

    fov_deg: float = 40.0
    light_distance: float | None = 3.0
    size: int | None = None  # pixels across; None: the object spans as many as in the orthographic capture

    def __post_init__(self):
        if self.size is not None and self.size < 8:
            raise ConfigError(f"eval.rig.size must be >= 8 pixels (or null), got {self.size}")
        if not 0 < self.fov_deg < 120:
            raise ConfigError(f"eval.rig.fov_deg must be in (0, 120), got {self.fov_deg}")
        if self.light_distance is not None and not 1 < self.light_distance < 5:
            raise ConfigError(f"eval.rig.light_distance must be in (1, 5) object radii, got {self.light_distance}")

    @property
    def suffix(self) -> str:
        return f"fov{self.fov_deg:g}" + ("" if self.light_distance is None else f"-point{self.light_distance:g}")


@dataclass(frozen=True)
class Params:
    """Parameters of the eval stage (``eval:`` in params.yaml).

    ``test_shapes``: ``sphere`` and/or procedural kinds (:data:`cnnps.synth.procedural.PROCEDURAL_KINDS`);
    ``synthetic: false`` skips the synthetic test set (real captures only).
    ``categories``: the test set's material categories; ``ranges``: their BSDF ranges, a
    :class:`cnnps.synth.bsdf.MaterialRanges` or per-category overrides of the defaults as
    ``materials.ranges`` takes them (``{"metallic": {"roughness": [0.1, 0.5]}}``); the
    test set's own, not ``materials.ranges``: editing what training draws from leaves the
    yardstick as it is.
    ``real_captures``: capture folders (DiLiGenT layout) also scored; without ground
    truth only their pictures are made. ``real_subsets``: image counts n; each real
    capture is scored again from n of its images, drawn by the seeded rule of
    :func:`cnnps.io.capture.subset_drop` (named ``<capture>-<n>``).
    ``real_exclude_from_mean``: folder names of real captures scored and reported but left
    out of ``summary_real`` / ``summary_real_subsets`` (e.g. a capture kept for reference
    beside a group that is averaged). ``real_pixels``: score each real capture (and its
    subsets) on a seeded random sample of that many of its mask pixels, the same pixels for
    every model and subset (:func:`pixel_sample`; 0 = every pixel): a quick, paired
    comparison of checkpoints, not the benchmark's number. ``saturated``: "exclude" leaves saturated observations
    out, as ``cnnps predict`` does by default; "keep" uses them as stored. ``precision``:
    the network's ("auto": the measured pick of ``cnnps predict --precision auto``).
    ``model``: checkpoint;
    default ``<data_dir>/train/model.pt``. ``rig``: also render every test capture again
    through that rig (:class:`Rig`; named ``<capture>-<rig>``, e.g. ``bowl-specular-17-fov40-point1.5``)
    and score the twins as ``cnnps predict`` treats rig captures; ``summary_rig`` and
    ``rig_minus_ortho`` in metrics.json say what the rig costs.
    """

    synthetic: bool = True
    test_shapes: tuple[str, ...] = (SPHERE, "bowl", "holed")
    superpixels: Count = 100
    categories: tuple[str, ...] = ("specular", "metallic")
    ranges: MaterialRanges = field(default_factory=MaterialRanges)  # the test set's BSDF ranges (not materials')
    light_sets: tuple[int, ...] = (17, 305)
    size: Annotated[int, Range(ge=8)] = 64  # pixels
    samples: Count = 16
    rotations: tuple[int, ...] = (1, 10)
    real_captures: tuple[str, ...] = ()
    real_subsets: tuple[int, ...] = ()
    real_exclude_from_mean: tuple[str, ...] = ()
    real_pixels: Annotated[int, Range(ge=0)] = 0  # 0 = every mask pixel; N = a seeded sample of N (pixel_sample)
    rig: Rig | None = None
    # point-light captures: "known" = the median depth a render records in scene.json, as a
    # measured --distance; "estimated" = found from the images, as without --distance
    rig_distance: Literal["known", "estimated"] = "known"
    model: str | None = None
    device: Device = "auto"
    batch_size: Annotated[int, Range(ge=0)] = 0  # maps per network call (0 = the inference default: 256 on a CPU, 4096 on CUDA)
    lambertian_shadow_threshold: UnitFraction | None = None
    sparse_fill: SparseFill = "auto"  # CNN, as `cnnps predict --sparse-fill` (cnnps.ps.sparse_fill)
    saturated: Literal["exclude", "keep"] = "exclude"  # as `cnnps predict --saturated`
    precision: Literal["auto", "fp32", "bf16"] = "fp32"  # the network's; auto as `cnnps predict --precision`
    seed: Annotated[int, Range(ge=0)] = 0

    def __post_init__(self):
        for name in ("test_shapes", "categories", "light_sets", "rotations", "real_captures", "real_subsets",
                     "real_exclude_from_mean"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        object.__setattr__(self, "ranges", checked_ranges("eval", self.ranges))
        if self.synthetic:
            if not self.test_shapes:
                raise ConfigError("eval.test_shapes is empty (set eval.synthetic: false to score real captures only)")
            from cnnps.synth.procedural import PROCEDURAL_KINDS

            for s in self.test_shapes:
                if s != SPHERE and s not in PROCEDURAL_KINDS:
                    raise ConfigError(f"eval.test_shapes: unknown shape {s!r} (choose from {SPHERE}, {', '.join(PROCEDURAL_KINDS)})")
            if len(set(self.test_shapes)) != len(self.test_shapes):
                raise ConfigError(f"eval.test_shapes: duplicates in {list(self.test_shapes)}")
            object.__setattr__(self, "categories", checked_categories("eval", self.categories))
            if not self.light_sets:
                raise ConfigError("eval.light_sets is empty")
            for n in self.light_sets:
                if n < 3:
                    raise ConfigError(f"eval.light_sets: each light count must be >= 3, got {n}")
        if not self.synthetic and not self.real_captures:
            raise ConfigError("eval: nothing to evaluate (eval.synthetic is false and eval.real_captures is empty)")
        if self.real_subsets and not self.real_captures:
            raise ConfigError("eval.real_subsets needs eval.real_captures (the captures to draw the images from)")
        from cnnps.io.capture import MIN_IMAGES

        if any(n < MIN_IMAGES for n in self.real_subsets):
            raise ConfigError(f"eval.real_subsets: each image count must be >= {MIN_IMAGES}, got {list(self.real_subsets)}")
        names = [Path(c).name for c in self.real_captures]
        for name in self.real_exclude_from_mean:
            if name not in names:
                raise ConfigError(f"eval.real_exclude_from_mean: {name!r} is not the folder name of one of "
                                  f"eval.real_captures ({', '.join(names) or 'none'})")
        check_fields(self, "eval.")  # the declared ranges and choices (size, samples, device, ...)
        if not self.rotations or any(k < 1 for k in self.rotations):
            raise ConfigError(f"eval.rotations must be a non-empty list of integers >= 1, got {list(self.rotations)}")


def check_inputs(params: Params, data_dir: Path) -> None:
    """Checks on named files, before any stage runs (called by cnnps.pipeline.config)."""
    from cnnps.io.capture import FILENAMES_FILE, is_capture_folder

    for c in params.real_captures:
        p = Path(c)
        if not is_capture_folder(p):
            raise ConfigError(f"eval.real_captures: {p} is not a capture folder (no {FILENAMES_FILE})")


# --------------------------------------------------------------------------- scoring


def _model_path(params: Params, data_dir: Path) -> Path:
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


# --------------------------------------------------------------------------- stage


def stage_columns(params: Params, data_dir: Path) -> tuple[dict, Path]:
    """(:func:`method_columns`, model path): ``params.model`` (default the train stage's
    ``model.pt``) loaded and verified with every other column; a damaged file is one line
    naming it and the fix."""
    model_path = _model_path(params, data_dir)
    fix = ("rerun `cnnps run-stage train` (it rewrites model.pt from its last checkpoint)"
           if params.model is None else "replace it with an intact copy")
    return method_columns(params, model_path, fix=fix), model_path


def real_capture_list(params: Params) -> list[tuple]:
    """[(name, folder, "real"[, drop])]: each of ``real_captures`` (named by its folder),
    then its ``real_subsets`` (``<name>-<n>``, drawn by :func:`cnnps.io.capture.subset_drop`
    with ``params.seed`` from the images :data:`cnnps.io.capture.DILIGENT_RULES` leave). An InputError names a
    folder that is not there."""
    from cnnps.io.capture import DILIGENT_RULES, benchmark_drop, subset_drop

    captures: list[tuple] = []
    for c in params.real_captures:
        p = Path(c)
        if not p.is_dir():
            raise InputError(c, "capture folder not found")
        captures.append((p.name, p, "real"))
        rule = benchmark_drop(p, DILIGENT_RULES) if params.real_subsets else []
        captures += [(f"{p.name}-{n}", p, "real", subset_drop(p, n, params.seed, exclude=rule))
                     for n in params.real_subsets]
    return captures


def _check_names(captures) -> None:
    names = [c[0] for c in captures]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ConfigError(f"eval: two captures are named {dup!r}; rename one folder")


def score_real(params: Params, data_dir: Path = Path("data")) -> dict:
    """The real captures of ``params`` (``real_captures``, ``real_subsets``) scored by
    ``params.model`` exactly as the eval stage scores them, nothing written: what
    ``cnnps score`` runs.

    Returns the metrics of :func:`capture_metrics` (``captures``: per capture and subset
    ``n_images``, ``pixels``, ``scored_pixels`` and ``methods`` {``cnn_k<K>`` |
    ``lambertian``: ``mean_deg``, ``median_deg``, ...}; ``summary_real``;
    ``summary_real_subsets``) plus ``precision``, the network's.

    Example: ``score_real(Params(synthetic=False, real_captures=("ballPNG",),
    real_subsets=(10,), rotations=(10,), model="model.pt"))["captures"]["ballPNG-10"]``.
    """
    t0 = time.perf_counter()
    captures = real_capture_list(params)  # missing folders first, before the model loads
    _check_names(captures)
    columns, model_path = stage_columns(params, Path(data_dir))
    results = score_all(captures, columns, params)
    return capture_metrics(results, list(columns), params, str(model_path), t0, precision=columns_precision(columns))


def run(params: Params, data_dir: Path) -> None:
    t0 = time.perf_counter()
    data_dir = Path(data_dir)
    out_dir = data_dir / "eval"
    _model_path(params, data_dir)
    real = real_capture_list(params)  # fail before rendering anything
    columns, model_path = stage_columns(params, data_dir)  # the model loaded before anything is rendered or written

    captures: list[tuple] = []
    if params.synthetic:
        captures += [(p.name, p, "synthetic") for p in build_testset(params, data_dir)]
        if params.rig is not None:
            captures += [(p.name, p, "rig") for p in build_rig_twins(params, data_dir)]
    captures += real
    _check_names(captures)

    results = score_all(captures, columns, params)
    metrics = capture_metrics(results, list(columns), params, str(model_path), t0, precision=columns_precision(columns))
    write_report(out_dir, results, metrics)
    print(format_table(metrics))
    print(f"eval: report {out_dir / 'report.md'}")
