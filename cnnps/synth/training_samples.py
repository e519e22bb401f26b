"""Training samples from a rendered capture: per-pixel light subsets, augmentations and
the rotated observation-map rows (the rules, distributions, order of operations and random
streams are in :mod:`cnnps.stages.extract`'s docstring).

- per-pixel light subsets: :mod:`cnnps.synth.light_subsets` (its rule, settings and draws);
- :func:`add_ambient`: the ambient offset augmentation (real attached shadows are not black);
- sensor and capture realism: :func:`draw_capture_effects` makes a scene's draws
  (:class:`CaptureEffects`: per-light intensity mis-calibration :func:`light_gains`,
  light-direction error :func:`perturb_directions`, black level, saturation level, bit
  depth), :func:`apply_capture_effects` applies them, with ambient and noise
  (:func:`add_noise`, :func:`saturate`, :func:`quantize`), to a chunk of pixels;
- :func:`build_rows`: maps and normals for every rotation angle about z, built by the same
  :func:`cnnps.ps.obsmap.observation_maps_multi` that prediction uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cnnps.ps.obsmap import observation_maps_multi
from cnnps.ps.rotation import rotate_z


def add_ambient(rng: np.random.Generator, I: np.ndarray, mask: np.ndarray, ambient_max: float) -> np.ndarray:
    """``I + a * max(I over the pixel's chosen lights)`` with one ``a ~ U(0, ambient_max)``
    per pixel (row), added to every light: real attached shadows are not black (ambient
    light and the black level; docs/extract.md), while rendered ones are exactly 0.
    I: (P, m); mask: (P, m) chosen lights."""
    a = rng.uniform(0.0, ambient_max, size=(I.shape[0], 1))
    top = chosen_max(I, mask)[:, None]
    return I + (a * top).astype(I.dtype)


def chosen_max(I: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(P,) ``max(np.where(mask, I, 0), axis=1)`` (the pixel's brightest chosen value, or 0),
    computed as the cheaper ``(I * mask).max`` unless a value is not finite."""
    if I.shape[1] == 0:
        return np.zeros(I.shape[0], I.dtype)
    with np.errstate(invalid="ignore"):
        top = (I * mask).max(axis=1)
    if not np.isfinite(top).all():  # inf * False = nan: the exact, slower form
        top = np.where(mask, I, 0.0).max(axis=1)
    return top


def build_rows(
    intensities: np.ndarray,
    normals: np.ndarray,
    lights: np.ndarray,
    light_mask: np.ndarray,
    angles: np.ndarray,
    w: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Maps (R, P, w, w) float16 and normals (R, P, 3) float32 for every rotation angle:
    rotation r uses lights and normals rotated about z by ``angles[r]``."""

    # one call for all angles: the masked values are shared, only the cells move
    rot_lights = np.stack([rotate_z(lights, a) for a in angles])
    maps = observation_maps_multi(intensities, rot_lights, w, light_mask=light_mask, dtype=np.float16)
    rot_normals = np.empty((len(angles), len(normals), 3), np.float32)
    for r, a in enumerate(angles):
        rot_normals[r] = rotate_z(normals, a)
    return maps, rot_normals


# -- sensor and capture realism ------------------------------------------------------------

# Random streams of the augmentations: NumPy generators seeded [scene_seed, stream] (per
# scene) or [scene_seed, stream, chunk] (per pixel); 0 and 1 are the pixel order and the
# cones and light subsets (cnnps.stages.extract).
STREAM_AMBIENT = 2  # per pixel (chunk c): ambient offset
STREAM_GAIN = 3  # per scene: intensity mis-calibration (one factor a light)
STREAM_DIRECTION = 4  # per scene: light-direction error (one rotation a light)
STREAM_BLACK = 5  # per scene: black level
STREAM_NOISE = 6  # per pixel (chunk c): read and shot noise
STREAM_SATURATION = 7  # per scene: saturation level
STREAM_QUANTIZE = 8  # per scene: bit depth
STREAM_SPARSE = 9  # per pixel (chunk c): sparse pixels and their subset sizes


def stream(scene_seed: int, index: int, chunk: int | None = None) -> np.random.Generator:
    """The generator of one augmentation stream of a scene (and chunk)."""
    return np.random.default_rng([scene_seed, index] if chunk is None else [scene_seed, index, chunk])


@dataclass(frozen=True)
class CaptureEffects:
    """A scene's draws of the capture augmentations (the default: all off).

    ``gain`` (m,) float32: factor of each light's intensity (mis-calibration);
    ``lights`` (m, 3): directions written into the maps (None = as rendered);
    ``black``: offset added to every value; ``full_scale`` E: the clip level (None = no
    clipping); ``bits``: quantise to ``E / (2**bits - 1)`` steps (None = off); the
    per-pixel parameters ``ambient_max`` and ``noise_max``; ``saturated_fraction`` and
    ``direction_angles_deg`` (m,) are what was drawn, kept for reports and tests.
    """

    gain: np.ndarray | None = None
    lights: np.ndarray | None = None
    black: float = 0.0
    full_scale: float | None = None
    bits: int | None = None
    ambient_max: float = 0.0
    noise_max: float = 0.0
    saturated_fraction: float = 0.0
    direction_angles_deg: np.ndarray | None = None

    @property
    def changes_values(self) -> bool:
        """True when :func:`apply_capture_effects` changes any intensity."""
        return bool(
            self.gain is not None or self.black or self.full_scale is not None or self.bits
            or self.ambient_max or self.noise_max
        )


def light_gains(rng: np.random.Generator, m: int, intensity_error: float) -> np.ndarray:
    """(m,) float32 factors ``max(1 + e, 0)``, ``e ~ N(0, intensity_error)`` per light: the
    light's true intensity differed from the recorded one by that factor, so the image
    divided by the recorded intensity is off by it."""
    e = rng.normal(0.0, intensity_error, size=m)
    return np.maximum(1.0 + e, 0.0).astype(np.float32)


def perturb_directions(rng: np.random.Generator, lights: np.ndarray, error_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Turn each unit direction by an angle ``theta ~ |N(0, error_deg)|`` (half-normal: mean
    0.798 ``error_deg``, median 0.674 ``error_deg``) towards a uniformly random direction
    perpendicular to it (a rotation about a random axis perpendicular to the light, so the
    angle between the old and the new direction is exactly ``theta``).

    Returns (turned (m, 3) float64 unit vectors, theta (m,) degrees). Draws: ``theta``
    (m normals), then the azimuths (m uniforms)."""
    L = np.asarray(lights, dtype=np.float64)
    L = L / np.linalg.norm(L, axis=1, keepdims=True)
    m = len(L)
    theta = np.abs(rng.standard_normal(m)) * np.radians(error_deg)
    psi = rng.uniform(0.0, 2.0 * np.pi, size=m)
    helper = np.where(np.abs(L[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(L, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(L, e1)
    u = np.cos(psi)[:, None] * e1 + np.sin(psi)[:, None] * e2
    out = np.cos(theta)[:, None] * L + np.sin(theta)[:, None] * u
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out, np.degrees(theta)


def pixel_peaks(I: np.ndarray, rows: np.ndarray, gain: np.ndarray | None = None, block: int = 4096) -> np.ndarray:
    """(len(rows),) float32 brightest value of each pixel ``I[rows]`` over all its lights,
    after ``gain`` (computed in blocks: no (P, m) copy)."""
    out = np.empty(len(rows), np.float32)
    for s in range(0, len(rows), block):
        b = I[rows[s : s + block]]
        if gain is not None:
            b *= gain
        out[s : s + block] = b.max(axis=1) if b.shape[1] else 0.0
    return out


def draw_capture_effects(
    scene_seed: int,
    I: np.ndarray,
    rows: np.ndarray,
    lights: np.ndarray,
    *,
    ambient_max: float = 0.0,
    noise_max: float = 0.0,
    intensity_error: float = 0.0,
    direction_error_deg: float = 0.0,
    black_level_max: float = 0.0,
    saturated_fraction_max: float = 0.0,
    quantize_bits: tuple[int, ...] = (),
) -> CaptureEffects:
    """A scene's :class:`CaptureEffects`, each from its own stream (``STREAM_*``).

    I: (P, m) the scene's rendered pixel values; rows: the pixels that count (valid
    foreground); lights: (m, 3) rendered directions. The scene's full scale E is the
    ``1 - f`` quantile of the pixels' brightest values (all lights, after the gains), with
    ``f ~ U(0, saturated_fraction_max)``; without saturation it is their largest value.
    It is computed only when the black level, saturation or quantisation needs it."""
    m = lights.shape[0]
    gain = light_gains(stream(scene_seed, STREAM_GAIN), m, intensity_error) if intensity_error else None
    written, angles = None, None
    if direction_error_deg:
        written, angles = perturb_directions(stream(scene_seed, STREAM_DIRECTION), lights, direction_error_deg)
    full_scale, black, bits, frac = None, 0.0, None, 0.0
    if black_level_max or saturated_fraction_max or quantize_bits:
        peaks = pixel_peaks(I, rows, gain)
        if saturated_fraction_max:
            frac = float(stream(scene_seed, STREAM_SATURATION).uniform(0.0, saturated_fraction_max))
            E = float(np.quantile(peaks, 1.0 - frac)) if len(peaks) else 0.0
        else:
            E = float(peaks.max()) if len(peaks) else 0.0
        if not (np.isfinite(E) and E > 0):
            E = 1.0  # a dark scene: every pixel is dropped anyway
        if black_level_max:
            black = float(stream(scene_seed, STREAM_BLACK).uniform(0.0, black_level_max)) * E
        if quantize_bits:
            choices = tuple(quantize_bits)
            bits = int(choices[stream(scene_seed, STREAM_QUANTIZE).integers(len(choices))])
        if saturated_fraction_max or quantize_bits:
            full_scale = E
    return CaptureEffects(
        gain=gain, lights=written, black=black, full_scale=full_scale, bits=bits, ambient_max=ambient_max,
        noise_max=noise_max, saturated_fraction=frac, direction_angles_deg=angles,
    )


def add_noise(rng: np.random.Generator, I: np.ndarray, mask: np.ndarray, noise_max: float) -> np.ndarray:
    """Read and shot noise relative to each pixel's range: per pixel (row)
    ``s_read, s_shot ~ U(0, noise_max)`` (drawn as ``rng.uniform(0, noise_max, (P, 2))``),
    ``peak`` the pixel's brightest chosen value; every value v gets Gaussian noise of
    variance ``(s_read * peak)**2 + s_shot**2 * peak * v`` (drawn as
    ``rng.standard_normal((P, m), float32)``), so the noise std is ``s_read * peak`` on a
    black value and ``peak * sqrt(s_read**2 + s_shot**2)`` at the peak. The result is
    clipped at 0. I: (P, m) float32 (not modified); mask: (P, m) chosen lights."""
    P, m = I.shape
    s = rng.uniform(0.0, noise_max, size=(P, 2))
    z = rng.standard_normal((P, m), dtype=np.float32)
    peak = chosen_max(I, mask)
    read2 = ((s[:, 0] * peak) ** 2).astype(np.float32)[:, None]
    shot2 = (s[:, 1] ** 2 * peak).astype(np.float32)[:, None]
    var = np.maximum(I, 0.0, dtype=np.float32)
    var *= shot2
    var += read2
    np.sqrt(var, out=var)
    var *= z
    var += I
    return np.maximum(var, 0.0, out=var)


def saturate(I: np.ndarray, level: float) -> np.ndarray:
    """Values above ``level`` clipped to it (in place)."""
    return np.minimum(I, np.float32(level), out=I)


def quantize(I: np.ndarray, full_scale: float, bits: int) -> np.ndarray:
    """Values rounded (to nearest) to the grid ``k * full_scale / (2**bits - 1)``, k =
    0 .. 2**bits - 1, after clipping to [0, full_scale] (a fixed-point image holds nothing
    else). In place."""
    levels = float(2**bits - 1)
    np.clip(I, 0.0, np.float32(full_scale), out=I)
    I *= np.float32(levels / full_scale)
    np.rint(I, out=I)
    I *= np.float32(full_scale / levels)
    return I


def apply_capture_effects(
    I: np.ndarray, mask: np.ndarray, fx: CaptureEffects, scene_seed: int, chunk: int
) -> np.ndarray:
    """The value augmentations of one chunk of pixels, in capture order: gains
    (mis-calibration) -> ambient -> black level -> noise -> saturation -> quantisation.
    I: (P, m) float32 rendered values (returned unchanged, the same object, when ``fx``
    changes no value); mask: (P, m) the pixels' chosen lights."""
    if not fx.changes_values:
        return I
    src = I
    if fx.gain is not None:
        I = I * fx.gain
    if fx.ambient_max:
        I = add_ambient(stream(scene_seed, STREAM_AMBIENT, chunk), I, mask, fx.ambient_max)
    if fx.black:
        I = I + np.float32(fx.black)
    if fx.noise_max:
        I = add_noise(stream(scene_seed, STREAM_NOISE, chunk), I, mask, fx.noise_max)
    if fx.full_scale is not None:
        if I is src:
            I = np.array(I, dtype=np.float32)  # the steps below work in place
        I = saturate(I, fx.full_scale)  # a fixed-point image clips at its full scale too
        if fx.bits:
            I = quantize(I, fx.full_scale, fx.bits)
    return I
