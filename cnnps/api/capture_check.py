"""What will hurt a capture's normals, found before predicting: ``cnnps check``.

:func:`check_capture` reads a capture folder the way :func:`cnnps.predict_folder` does
(:func:`cnnps.io.capture.scan_capture` with the same files allowed to be missing), so what
``cnnps predict`` refuses it refuses with the same one line; everything else becomes a
:class:`Finding`, each with what to do about it. Each image is read once:

- **clipped**: the share of the object's pixels with a channel at the saturation level
  (:data:`cnnps.io.capture.SATURATION_LEVEL` of the format's maximum): those observations
  are lost, and with a phone's tone curve the ones near them are bent too;
- **dim**: the object's brightest pixels (their 99th percentile) below :data:`DIM_LEVELS`
  levels of the stored integer format: the quantisation then shows in the normals;
- **moved**: the image's shift against those whose lights are nearest its own (the median
  of :data:`NEIGHBOURS`; similar lights, similar shading: what differs is the frame; phase
  correlation of the two images' gradient magnitudes,
  :func:`skimage.registration.phase_cross_correlation`, to a tenth of a pixel, on the
  object's box with a margin; the smaller of that and the same on a band along the
  object's outline, which stays put while highlights and shadows move): a frame that
  moved mixes pixels;
- **exposure**: the EXIF exposure (time x ISO / f-number squared) of JPEG, TIFF and DNG
  files, when they carry it: differing exposures with a fixed intensities file mean the
  intensities are wrong for some images;
- **lights**: their count and cone (angles from the view axis), or that there are none
  yet (photos before ``cnnps calibrate``: frames are then registered against the most
  alike shots, by the correlation of the object's shading); **intensities**: their spread, or where they will come
  from.

The object's pixels are the folder's ``mask.png``, or the mask made from the photos
(:mod:`cnnps.api.capture_estimates`) when it has none. Every limit is declared once below.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cnnps.api.capture_estimates import (
    IntensitySource,
    Source,
    calibrated_ball,
    exif_intensities,
    made_mask,
    missing_ok,
    wanted,
)
from cnnps.io.exif import exif_exposure

CLIPPED_SHARE = 0.01  # an image with more of the object's pixels clipped than this is reported
DIM_LEVELS = 32  # the object's 99th percentile below this many levels of an integer format: a dim image
SHIFT_PX = 0.6  # a frame shifted by more than this against its neighbours has moved
NEIGHBOURS = 3  # a frame is registered against the images of this many nearest lights
FEW_LIGHTS = 20  # fewer lights than this: CNN-PS's error about doubles at 10 (DiLiGenT, 14.3 against 7.2 deg)
NARROW_CONE_DEG = 20.0  # all lights within this angle of the view: the normals are poorly fixed
EXPOSURE_SPREAD = 0.02  # EXIF exposures differing by more than this (relative) have changed
MIN_REGISTRATION_SIDE = 48  # an object's box smaller than this a side is not registered (too little outline)
REGISTRATION_SIDE = 512  # the object's box is downsampled to at most this many pixels a side to register


@dataclass(frozen=True)
class Finding:
    """One thing that will hurt (``level`` "warning") or that the user should know
    (``level`` "note"): ``kind`` (clipped, dim, moved, exposure, lights, intensities,
    mask), ``images`` (indices into the capture's images, in filenames.txt order less any
    dropped; empty when it is about the whole capture) and one ``message`` line that says
    what to do."""

    kind: str
    level: str
    message: str
    images: tuple[int, ...] = ()


@dataclass
class CaptureCheck:
    """What :func:`check_capture` found: ``findings``; per image (capture order)
    ``clipped`` (share of the object's pixels), ``peak`` (the object's 99th percentile, in
    units of full scale; NaN for float images), ``shift`` ((m, 2) pixels, x right and y
    down, against the frames of the nearest lights), ``exposure`` (EXIF exposure or NaN); ``summary`` lines
    (what the capture is)."""

    findings: list[Finding]
    clipped: np.ndarray
    peak: np.ndarray
    shift: np.ndarray
    exposure: np.ndarray
    summary: list[str] = field(default_factory=list)

    @property
    def warnings(self) -> list[Finding]:
        return [f for f in self.findings if f.level == "warning"]

    def record(self) -> dict:
        """The findings and per-image figures as JSON-ready values."""
        def floats(a):
            return [None if not np.isfinite(v) else round(float(v), 4) for v in np.ravel(a)]

        return {"summary": list(self.summary), "findings": [dataclasses.asdict(f) for f in self.findings],
                "clipped": floats(self.clipped), "peak": floats(self.peak),
                "shift_px": [floats(s) for s in self.shift], "exposure": floats(self.exposure)}


def top_code(capture) -> float:
    """The largest value of the capture's stored integer type (NaN for float images)."""
    from cnnps.io.images import max_code

    top = max_code(capture.read_raw(0).dtype)
    return float("nan") if top is None else float(top)


def _listed(images, limit: int = 8) -> str:
    shown = ", ".join(str(k) for k in images[:limit])
    return shown + (f" and {len(images) - limit} more" if len(images) > limit else "")


def _box(mask: np.ndarray) -> tuple[slice, slice, int]:
    """The mask's bounding box with a 10 % margin, and the integer downsampling step that
    brings it to at most REGISTRATION_SIDE pixels a side."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    H, W = mask.shape
    if rows.size == 0:
        return slice(0, H), slice(0, W), max(1, -(-max(H, W) // REGISTRATION_SIDE))
    pad_r, pad_c = max(4, (rows[-1] - rows[0]) // 10), max(4, (cols[-1] - cols[0]) // 10)
    r0, r1 = max(0, rows[0] - pad_r), min(H, rows[-1] + 1 + pad_r)
    c0, c1 = max(0, cols[0] - pad_c), min(W, cols[-1] + 1 + pad_c)
    step = max(1, -(-max(r1 - r0, c1 - c0) // REGISTRATION_SIDE))
    return slice(r0, r1), slice(c0, c1), step


def _edges(grey: np.ndarray) -> np.ndarray:
    """Gradient magnitude of log brightness: the edges stay where a new light moves the shading."""
    from skimage.filters import sobel

    return sobel(np.log1p(np.maximum(grey, 0) / max(float(np.percentile(grey, 99)), 1e-12)))


def _outline_band(mask: np.ndarray) -> np.ndarray:
    """Where the object's outline is, a few pixels each side: it stays put while the lights
    move shading, highlights and shadows across the object."""
    from scipy.ndimage import binary_dilation, binary_erosion, gaussian_filter

    r = max(2, int(0.03 * max(mask.shape)))
    band = binary_dilation(mask, iterations=r) & ~binary_erosion(mask, iterations=r)
    return gaussian_filter(band.astype(np.float32), r / 2)  # tapered: its own edges must not register


def _shift(ref: np.ndarray, img: np.ndarray, step: int) -> np.ndarray:
    from skimage.registration import phase_cross_correlation

    shift = phase_cross_correlation(ref, img, upsample_factor=10, normalization=None)[0]
    return -np.asarray(shift)[::-1] * step  # (x right, y down) of img against ref, full-size pixels


def _scan(capture, mask: np.ndarray, progress: bool):
    """Per image: clipped share, object peak (full-scale units), and its shift against the
    images of the nearest lights."""
    from cnnps.infra.progress import progress_bar
    from cnnps.io.capture import SATURATION_LEVEL
    from cnnps.io.images import max_code

    m = capture.n_images
    clipped, peak, shift = np.zeros(m), np.full(m, np.nan), np.zeros((m, 2))
    rows, cols, step = _box(mask)
    band = _outline_band(mask[rows, cols][::step, ::step])
    edges, shading = [], []
    for k in progress_bar(range(m), total=m, desc="check", unit="image", disable=not progress):
        raw = capture.read_raw(k)
        top = max_code(raw.dtype)
        obj = raw[mask].astype(np.float64)  # (P, C)
        if top is not None:
            clipped[k] = float((obj >= SATURATION_LEVEL * top).any(axis=1).mean()) if obj.size else 0.0
            peak[k] = float(np.percentile(obj.max(axis=1), 99)) / top if obj.size else 0.0
        grey = raw[rows, cols].astype(np.float64).mean(axis=2)[::step, ::step]
        edges.append(_edges(grey).astype(np.float32))
        shading.append(grey.astype(np.float32))
    if min(edges[0].shape) * step < MIN_REGISTRATION_SIDE:
        return clipped, peak, np.full((m, 2), np.nan)
    if capture.lights is None:  # no lights yet: the most alike shots (the object's shading as a vector)
        F = np.stack([g[mask[rows, cols][::step, ::step]] for g in shading]).astype(np.float64)
        F -= F.mean(axis=1, keepdims=True)
        F /= np.linalg.norm(F, axis=1, keepdims=True) + 1e-12
        near = F @ F.T
    else:
        L = capture.lights / np.linalg.norm(capture.lights, axis=1, keepdims=True)
        near = L @ L.T
    np.fill_diagonal(near, -np.inf)
    edges = [e * band for e in edges]
    for k in range(m):  # the median of three: a frame beside a moved one differs from one of them only
        found = np.array([_shift(edges[j], edges[k], step) for j in np.argsort(-near[k])[:min(NEIGHBOURS, m - 1)]])
        shift[k] = found[np.argsort(np.hypot(*found.T))[len(found) // 2]]
    return clipped, peak, shift


def _light_findings(lights: np.ndarray | None) -> tuple[list[Finding], str]:
    if lights is None:
        return [Finding("lights", "warning", "no light files: cnnps predict needs the lights; photograph a chrome "
                        "ball in the same shots, run cnnps calibrate PHOTOS -o LIGHTS and give --lights LIGHTS")], \
            "lights: none yet (no light_directions.txt)"
    L = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(L[:, 2], -1, 1)))
    m = len(L)
    line = (f"lights: {m}, {angle.min():.0f}-{angle.max():.0f} deg from the view axis "
            f"(median {np.median(angle):.0f} deg)")
    out = []
    if m < FEW_LIGHTS:
        out.append(Finding("lights", "warning", f"only {m} lights: CNN-PS is about twice as far off at 10 lights as "
                           f"at 96 (DiLiGenT); take {FEW_LIGHTS} or more shots, the lamp moved around the object"))
    if angle.max() < NARROW_CONE_DEG:
        out.append(Finding("lights", "warning", f"every light is within {angle.max():.0f} deg of the view axis: the "
                           "normals are poorly fixed; move the lamp further to the side (30-60 deg)"))
    behind = np.flatnonzero(L[:, 2] <= 0)
    if behind.size:
        out.append(Finding("lights", "warning", f"lights {_listed(behind.tolist())} are behind the object's visible "
                           "side (z <= 0): they light nothing the camera sees; check light_directions.txt",
                           tuple(behind.tolist())))
    return out, line


def check_capture(capture_dir, *, drop=None, mask: Source = "auto", intensities: IntensitySource = "auto",
                  lights_dir=None, grey: str = "mean", linearize=None, progress: bool = False) -> CaptureCheck:
    """Check the capture folder ``capture_dir`` for what will hurt its normals (the module
    docstring). ``drop``, ``mask``, ``intensities``, ``lights_dir``, ``grey`` and
    ``linearize`` mean what they mean to :func:`cnnps.predict_folder`; a capture without
    light files yet (photos of the object with the chrome ball beside it, before
    ``cnnps calibrate``) is checked too, with a warning. Raises what predict raises for a
    capture it refuses otherwise (:class:`cnnps.infra.errors.InputError` naming the file,
    ConfigError); writes nothing."""
    from cnnps.infra.options import check_arguments
    from cnnps.io.capture import scan_capture

    sources = check_arguments(check_capture, {"mask": mask, "intensities": intensities})
    capture = scan_capture(Path(capture_dir), drop=drop, grey=grey, linearize=linearize,
                           missing_ok=missing_ok(sources) + ("lights",), lights_dir=lights_dir)
    ball = None if lights_dir is None else calibrated_ball(lights_dir, capture_dir)
    todo = wanted(capture, sources)
    if "mask" in todo:  # made as cnnps predict makes it: from the images as stored when the intensities are made
        base = (dataclasses.replace(capture, intensities=np.ones((capture.n_images, 3))) if "intensities" in todo
                else capture)
        capture = dataclasses.replace(capture, mask=made_mask(base, ball)[0])
    exif = sources["intensities"] == "exif"
    if exif:
        exif_intensities(capture)  # every image has its EXIF exposure, as predict requires
    return inspect_capture(capture, todo, progress, exif=exif)


def inspect_capture(capture, made, progress: bool = False, exif: bool = False) -> CaptureCheck:
    """:func:`check_capture`'s findings for a capture already read, its mask in place;
    ``made``: what is (or will be) made from the photos (``"mask"``, ``"intensities"``:
    :func:`cnnps.api.capture_estimates.wanted`; ``exif``: the intensities from the EXIF
    exposure). Reads every image once."""
    todo = list(made)
    findings: list[Finding] = []
    m, (H, W) = capture.n_images, capture.shape
    kind = capture.paths[0].suffix.lower().lstrip(".") if capture.paths else "arrays"
    summary = [f"capture: {m} images, {W} x {H} pixels ({kind})"]
    if "mask" in todo:
        summary.append(f"mask: made from the photos ({capture.n_pixels} pixels): cnnps predict will make the same one")
        findings.append(Finding("mask", "note", "no mask.png: cnnps predict makes one from the photos and writes it to "
                                "its output folder; look at it, and paint one if it misses part of the object"))
    else:
        summary.append(f"mask: mask.png ({capture.n_pixels} pixels)")
    light_findings, light_line = _light_findings(capture.lights)
    summary.append(light_line)
    findings += light_findings

    clipped, peak, shift = _scan(capture, capture.mask, progress)
    over = np.flatnonzero(clipped > CLIPPED_SHARE)
    if over.size:
        worst = int(over[np.argmax(clipped[over])])
        findings.append(Finding("clipped", "warning", f"{over.size} of {m} images have more than "
                                f"{CLIPPED_SHARE:.0%} of the object clipped (images {_listed(over.tolist())}; most: "
                                f"image {worst}, {clipped[worst]:.1%}): those observations are lost; lower the exposure "
                                "or move the lamp further away", tuple(over.tolist())))
    dim = np.flatnonzero(peak * top_code(capture) < DIM_LEVELS)
    if dim.size:
        findings.append(Finding("dim", "warning", f"{dim.size} of {m} images hold fewer than {DIM_LEVELS} levels "
                                f"on the object (images {_listed(dim.tolist())}): few levels, noisy normals; raise the "
                                "exposure (or use 16-bit or RAW images)", tuple(dim.tolist())))
    size = np.linalg.norm(shift, axis=1)
    moved = np.flatnonzero(np.nan_to_num(size) > SHIFT_PX)
    if moved.size:
        worst = int(moved[np.argmax(size[moved])])
        findings.append(Finding("moved", "warning", f"{moved.size} of {m} frames moved by more than {SHIFT_PX} px "
                                f"against the frames of the nearest lights (images {_listed(moved.tolist())}; most: image {worst}, "
                                f"{size[worst]:.1f} px): fix the camera (a tripod, a remote or timed shutter) and "
                                "take them again", tuple(moved.tolist())))
    summary.append(f"registration: largest shift against the frames of the nearest lights {size.max():.2f} px"
                   if np.isfinite(size).all() else
                   f"registration: skipped (the object's box is under {MIN_REGISTRATION_SIDE} px a side)")

    exposure = np.array([exif_exposure(p) for p in capture.paths]) if capture.paths else np.full(m, np.nan)
    known = np.isfinite(exposure)
    if known.any():
        ratio = exposure[known] / np.median(exposure[known])
        if np.abs(ratio - 1).max() > EXPOSURE_SPREAD:
            summary.append(f"EXIF exposure: differs from shot to shot ({ratio.min():.2f}-{ratio.max():.2f} x the median)")
            if "intensities" in todo:
                findings.append(Finding("exposure", "note", "the EXIF exposure changes from shot to shot: the "
                                        "intensities made from the photos take it out (--intensities exif reads it "
                                        "exactly when the lamp kept its power and distance)"))
            else:
                findings.append(Finding("exposure", "warning", "the EXIF exposure changes from shot to shot, but the "
                                        "intensities come from light_intensities.txt: lock the exposure on the camera, "
                                        "or let cnnps estimate them (--intensities estimate)"))
        else:
            summary.append("EXIF exposure: the same in every shot")
    if "intensities" in todo:
        summary.append("intensities: from the EXIF exposure when predicting (--intensities exif)" if exif else
                       "intensities: estimated from the object when predicting (no light_intensities.txt, or "
                       "--intensities estimate)")
    elif capture.intensities is not None:
        e = capture.intensities.mean(axis=1)
        summary.append(f"intensities: light_intensities.txt, {e.min() / e.mean():.2f}-{e.max() / e.mean():.2f} x "
                       "their mean")
    return CaptureCheck(findings, clipped, peak, shift, exposure, summary)
