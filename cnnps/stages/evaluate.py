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
from pathlib import Path

from cnnps.infra.errors import ConfigError, InputError
from cnnps.stages.eval_params import Params, Rig  # noqa: F401 (Rig: part of the stage's settings)
from cnnps.stages.eval_report import format_table, write_report
from cnnps.stages.eval_scoring import capture_metrics, columns_precision, method_columns, model_path_of, score_all
from cnnps.stages.eval_testset import build_rig_twins, build_testset


def check_inputs(params: Params, data_dir: Path) -> None:
    """Checks on named files, before any stage runs (called by cnnps.pipeline.config)."""
    from cnnps.io.capture import FILENAMES_FILE, is_capture_folder

    for c in params.real_captures:
        p = Path(c)
        if not is_capture_folder(p):
            raise ConfigError(f"eval.real_captures: {p} is not a capture folder (no {FILENAMES_FILE} and no images)")


def stage_columns(params: Params, data_dir: Path) -> tuple[dict, Path]:
    """(:func:`method_columns`, model path): ``params.model`` (default the train stage's
    ``model.pt``) loaded and verified with every other column; a damaged file is one line
    naming it and the fix."""
    model_path = model_path_of(params, data_dir)
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
    model_path_of(params, data_dir)
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
