"""What a prediction writes: its record (``prediction.json``) and the files of OUT_DIR.

OUT_DIR is written whole, by one writer at a time (:mod:`cnnps.infra.output_folder`): a
prediction holds OUT_DIR's lock from its start (a second one is refused at once, one line
naming the folder and the holder, exit status 2) and writes its files into a work folder
beside OUT_DIR that replaces OUT_DIR by a rename at the end, so OUT_DIR holds the earlier
complete outputs or the new ones, never a mix, whatever stops a run (an error, SIGKILL).
The files: ``normal.npy`` (H x W x 3 float32 unit normals in the capture frame,
zeros outside the mask), ``normal.png`` ((n + 1) / 2), ``prediction.json`` (the record);
``confidence.npy`` (H x W float32 in [0, 1], 0 outside the mask) and ``confidence.png``
when the method measures it;
with ground truth ``error.png`` and ``metrics.json``; with a surface ``depth.npy``,
``depth.png`` and ``surface.ply`` (:func:`cnnps.io.surface.write_surface_outputs`);
``report.html``, a page of all of these (:mod:`cnnps.io.report`), unless told not to.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cnnps.infra.errors import CnnpsError, ConfigError, InputError
from cnnps.infra.output_folder import OutputFolder
from cnnps.io.capture import LIGHT_INTENSITIES_FILE, MASK_FILE


@dataclass
class Prediction:
    """What :func:`cnnps.predict` returns.

    normals: (H, W, 3) float32 unit normals (x right, y up, z toward the camera), zeros
        outside the mask. mask: (H, W) bool. record: what ``prediction.json`` records
        (method, model, rotations, precision and how it was chosen, sparse fill, image
        types, saturated observations, tiling, seconds, notes, notices, warnings).
    errors: (H, W) float64 angular errors in degrees where scored (0 elsewhere) and
    stats: ``mean_deg``, ``median_deg``, ... when ground truth was given, else None.
    depth: under point lights, (H, W) float64 depth along the optical axis found by the
    rounds (the unit of the light positions, NaN outside the mask), else None.
    confidence: (H, W) float32 in [0, 1], how far each normal can be trusted (1 the most;
    0 outside the mask; :mod:`cnnps.ps.confidence`, its measure in ``record["confidence"]``),
    or None when the method has no measure (the network with one rotation).
    """

    normals: np.ndarray
    mask: np.ndarray
    record: dict
    errors: np.ndarray | None = None
    stats: dict | None = None
    depth: np.ndarray | None = None
    confidence: np.ndarray | None = None

    @property
    def notes(self) -> list[str]:
        return list(self.record.get("notes", []))

    @property
    def warnings(self) -> list[str]:
        return list(self.record.get("warnings", []))

    def _repr_html_(self) -> str:
        """The report page (:func:`cnnps.io.report.notebook_html`), for a notebook."""
        from cnnps.io.report import notebook_html

        return notebook_html(self.normals, self.mask, self.record, confidence=self.confidence, errors=self.errors,
                             stats=self.stats, depth=self.depth)


DEPTH_FILES = ("depth.npy", "depth.png", "surface.ply")
CONFIDENCE_FILES = ("confidence.npy", "confidence.png")
OUTPUT_FILES = ("normal.npy", "normal.png", "prediction.json", "error.png", "metrics.json") + CONFIDENCE_FILES + DEPTH_FILES + (
    "report.html", MASK_FILE, LIGHT_INTENSITIES_FILE)  # made from the photos (cnnps.api.capture_estimates)


def check_out_dir(out_dir: Path, capture_dir: Path, *inputs: Path) -> None:
    """Refuse OUT_DIRs whose replacement would destroy something that is not ours: the
    capture folder or another input folder (``inputs``), or a folder holding one."""
    out = out_dir.resolve()
    for folder, what in [(capture_dir, "the capture folder"), *((d, "an input folder") for d in inputs)]:
        cap = Path(folder).resolve()
        if out == cap or out in cap.parents:
            raise InputError(out_dir, f"output folder must not be {what} or contain it")
    if out.exists():
        if not out.is_dir():
            raise InputError(out_dir, "exists and is not a folder")
        foreign = [p.name for p in out.iterdir() if p.name not in OUTPUT_FILES]
        if foreign:
            raise InputError(
                out_dir,
                f"exists and holds files that are not predict outputs (e.g. {sorted(foreign)[0]!r}); "
                "choose a new or empty folder",
            )


def make_record(solver, camera, found, stack, *, n_images: int, image_size, options: dict,
                dropped: list[int] | None = None) -> dict:
    """What ``prediction.json`` records about a run (without its timing and notes):
    the method and what the solver says of itself, the camera, the lights, the pixels and
    how they were read (with RAW photos among the images, ``"raw"`` holds
    :func:`cnnps.io.raw.raw_settings`). ``found``: :class:`cnnps.api.normals.CaptureNormals`."""
    from cnnps.io.capture import SATURATION_LEVEL
    from cnnps.io.raw import RAW_KIND, raw_settings

    linearize, saturated = options["linearize"], options["saturated"]
    own = solver.record(found.counts.solver, n_images, found.lights.get("model") != "point")
    confidence = found.counts.confidence
    return {
        "method": solver.name,
        **own,  # what the solver says of itself, in its own words and order (the network: model, rotations, ...)
        "camera": camera.record(),
        "lights": found.lights,
        "confidence": None if confidence is None else {
            **(solver.confidence_record() or {}),
            "median": round(float(np.median(confidence[found.normal.any(axis=2)])), 4)},
        "grey": options["grey"],
        "n_images": n_images,
        **({} if dropped is None else {"dropped": dropped}),
        "pixels": stack.P,
        "image_size": list(image_size),
        "image_types": dict(sorted(stack.kinds.items())),
        **({"raw": raw_settings()} if RAW_KIND in stack.kinds else {}),
        "linearize": linearize or "none",
        "linearize_chosen": linearize is not None,
        "saturated": saturated,
        "saturation_level": SATURATION_LEVEL if saturated == "exclude" else None,
        "saturated_observations": int(stack.n_saturated),
        "saturated_pixels": int(found.counts.saturated_pixels),
        "tile_pixels": int(options["tile_pixels"]),
        "pixel_stack": "disk" if stack.on_disk else "memory",
    }


def notices(linearize, kinds: dict) -> list[str]:
    """The one-line notice for 8-bit images read without a chosen ``linearize``."""
    from cnnps.io.srgb import UNCHOSEN_8BIT_NOTE

    return [UNCHOSEN_8BIT_NOTE] if linearize is None and kinds.get("uint8") else []


def scale_warning(lights: dict) -> list[str]:
    """A warning when the point-light scale search found no minimum inside its range."""
    from cnnps.ps.near_field import SCALE_RANGE

    search = lights.get("scale_search") or {}
    if not search.get("at_bound"):
        return []
    return [f"point lights: the scale search ended at the edge of its range ({lights['start_distance']:.4g}; it tries "
            f"{SCALE_RANGE[0]:.2g}-{SCALE_RANGE[1]:g} x the lights' median distance from the camera): depth and normals "
            "may be far off; measure the object's distance along the optical axis and pass --distance"]


def finish_record(record: dict, *, t0: float, t_load: float, notes: list[str], linearize,
                  warnings: list[str]) -> dict:
    """``record`` with its seconds (since ``t0``), load seconds, notes, notices (from
    ``linearize`` and the image types) and warnings."""
    record["seconds"] = round(time.perf_counter() - t0, 3)
    record["load_seconds"] = round(t_load, 3)
    record["notes"] = list(notes)
    record["notices"] = notices(linearize, record["image_types"])
    record["warnings"] = list(warnings)
    return record


def surface_writer():
    """``cnnps.io.surface.write_surface_outputs``, imported before any heavy work."""
    try:
        from cnnps.io.surface import write_surface_outputs
    except ImportError as exc:
        raise ConfigError(f"--depth needs cnnps.io.surface, which failed to import ({exc})") from None
    return write_surface_outputs


def score(normal, normal_gt, mask, source, notes: list[str]):
    """:func:`cnnps.ps.metrics.score_normals`, with a note when mask pixels lack ground truth."""
    from cnnps.ps.metrics import score_normals

    result = score_normals(normal, normal_gt, mask, source)
    n_pixels = int(mask.sum())
    if result.scored.sum() < n_pixels:
        notes.append(f"{n_pixels - int(result.scored.sum())} mask pixels have no ground truth; not scored")
    return result


def _jsonable(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def dumps(obj) -> str:
    """``obj`` as indented JSON (numpy values and paths included), newline-terminated."""
    return json.dumps(obj, indent=2, default=_jsonable) + "\n"


def normal_picture(normal: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``normal_to_rgb`` in bands of rows (it works in float64: 2x the normals' size)."""
    from cnnps.io.visualize import normal_to_rgb

    H, W = mask.shape
    rgb = np.empty((H, W, 3), dtype=np.uint8)
    band = max(1, (1 << 20) // max(1, W))
    for r in range(0, H, band):
        rgb[r : r + band] = normal_to_rgb(normal[r : r + band], mask[r : r + band])
    return rgb


def made_files(capture, estimated: dict) -> dict:
    """{capture file writer: value} for what :mod:`cnnps.api.capture_estimates` made, in a
    capture's own formats: the mask; the intensities when no image was dropped (else they
    would not match the folder's filenames.txt; prediction.json holds them either way)."""
    from cnnps.io.capture import write_light_intensities, write_mask

    out = {}
    if "mask" in estimated:
        out[write_mask] = capture.mask
    if "intensities" in estimated and not capture.dropped:
        out[write_light_intensities] = capture.intensities
    return out


def write_outputs(out: OutputFolder, normal, mask, record: dict, scored, write_surface, finish,
                  confidence: np.ndarray | None = None, report: bool = True, made: dict | None = None) -> None:
    """normal.npy, normal.png, confidence.npy + .png with a ``confidence`` map, error.png +
    metrics.json with a score, the surface files with ``write_surface``, the capture files
    of ``made`` ({writer(folder, value): value}: what was made from the photos,
    :func:`made_files`), prediction.json (``finish(record)`` completes it first), then
    report.html with ``report``; all at once (:meth:`OutputFolder.replace`: ``out`` must
    be held)."""
    from cnnps.io.images import write_png
    from cnnps.io.visualize import confidence_picture, score_picture

    with out.replace() as tmp:
        for write, value in (made or {}).items():
            write(tmp, value)
        np.save(tmp / "normal.npy", normal)
        write_png(tmp / "normal.png", normal_picture(normal, mask))
        if confidence is not None:
            np.save(tmp / "confidence.npy", confidence)
            write_png(tmp / "confidence.png", confidence_picture(confidence, mask))
        if scored is not None:
            write_png(tmp / "error.png", score_picture(scored))
            (tmp / "metrics.json").write_text(dumps({**scored.stats, **record}))
        if write_surface is not None:
            try:
                record["depth"] = write_surface(tmp, normal, mask)
            except ValueError as exc:
                raise CnnpsError(f"--depth: {exc}") from exc
        finish(record)
        (tmp / "prediction.json").write_text(dumps(record))
        if report:
            from cnnps.io.report import write_report

            write_report(tmp, normal, mask, json.loads(dumps(record)), confidence=confidence,
                         errors=None if scored is None else scored.errors, scored=None if scored is None else scored.scored,
                         stats=None if scored is None else scored.stats,
                         depth=np.load(tmp / DEPTH_FILES[0]) if write_surface is not None else None)
