"""The inputs a model takes, read from the model (its channels and patch size), the checks
of which captures it can run on (patch models: grey maps, shared distant lights, K in 1, 2,
4; colour models: distant lights, no views, no fill), and the maps it takes per rotation:
patch grids turned with the lights by quarter turns, and the grey map followed by R, G, B."""

from __future__ import annotations

import math

import numpy as np

from cnnps.infra.errors import ConfigError
from cnnps.models.network import RGB_CHANNELS


def model_channels(model) -> int:
    """The input channels of a network (or :class:`MapPredictor`): its ``in_channels``, 1
    when it has none (any module mapping (B, 1, w, w) maps to normals)."""
    return int(getattr(model, "in_channels", 1))


def model_patch(model) -> int:
    """The patch size b of a network (or :class:`MapPredictor`): its ``patch``, 1 when it has none."""
    return int(getattr(model, "patch", 1))


def patch_rotations_ok(rotations: int) -> bool:
    """Whether K test-time rotations are all whole quarter turns (K in 1, 2, 4), which a
    patch grid can follow exactly."""
    return int(rotations) in (1, 2, 4)


def check_patch_inputs(patch: int, channels: int = 1, *, rotations: int = 1, per_pixel_lights: bool = False,
                       views: bool = False) -> None:
    """One ConfigError when a network of ``patch`` b > 1 cannot be fed: its b x b maps are
    built for grey models under shared distant lights with an orthographic camera, and
    the test-time rotations must be quarter turns (K in 1, 2, 4)."""
    if patch == 1:
        return
    if channels != 1:
        raise ConfigError(f"a patch model (patch={patch}) of {channels} input channels: patches are built for "
                          "grey models only")
    if per_pixel_lights or views:
        what = "per-pixel lights (point lights)" if per_pixel_lights else "a pinhole camera (per-pixel views)"
        raise ConfigError(f"a patch model (patch={patch}) needs distant lights and an orthographic camera; "
                          f"this capture has {what}")
    if not patch_rotations_ok(rotations):
        raise ConfigError(f"a patch model (patch={patch}) takes 1, 2 or 4 rotations (its patch grid turns by "
                          f"quarter turns only), got {rotations}")


def check_colour_inputs(channels: int, *, per_pixel_lights: bool = False, views: bool = False,
                        fill: bool = False) -> None:
    """One ConfigError when a network of ``channels`` input channels cannot be fed: a
    colour model (:data:`RGB_CHANNELS`: grey, R, G, B) builds its maps under distant
    lights with an orthographic camera and no Lambertian fill; other counts are not built."""
    if channels == 1:
        return
    if channels != RGB_CHANNELS:
        raise ConfigError(f"a model of {channels} input channels: only 1 (grey) or {RGB_CHANNELS} "
                          "(grey, R, G, B) are known")
    if per_pixel_lights or views:
        what = "per-pixel lights (point lights)" if per_pixel_lights else "a pinhole camera (per-pixel views)"
        raise ConfigError(f"an RGB model needs distant lights and an orthographic camera; this capture has {what}: "
                          "use a grey model")
    if fill:
        raise ConfigError("an RGB model needs the capture's own observations, not the Lambertian sparse fill "
                          "(it applies below 50 images); use --sparse-fill off (eval.sparse_fill: off)")


def turn_patch_grids(maps: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(K, n, b, b, ...) with the b x b patch grid of rotation k turned by ``angles[k]``
    (whole quarter turns) counter-clockwise as seen from the camera (x right, y up, grid
    row 0 on top): the cells of :func:`cnnps.ps.patches.quarter_turn_cells`, those
    :func:`cnnps.ps.patches.capture_patches` reads. Other angles raise ValueError."""
    from cnnps.ps.patches import quarter_turn_cells

    maps = np.asarray(maps)
    K, n, b = maps.shape[:3]
    out = np.empty_like(maps)
    for k, a in enumerate(angles):
        cells = quarter_turn_cells(b, float(a))
        out[k] = maps[k].reshape((n, b * b) + maps.shape[4:])[:, cells].reshape(maps.shape[1:])
    return out


def patch_maps(intensities: np.ndarray, lights: np.ndarray, angles: np.ndarray, w: int,
               light_mask: np.ndarray | None = None) -> np.ndarray:
    """(K, n, b^2, w, w) float32 maps of n pixels' b x b patches, ``intensities`` (n, b^2, m)
    each pixel's unturned neighbourhood row by row (``light_mask`` (n, b^2, m): False
    leaves an observation out), under K light sets ``lights`` (K, m, 3), the lights turned
    by ``angles`` (K,), whole quarter turns: rotation k's cells are the neighbourhood's
    turned with its lights (:func:`turn_patch_grids`), their maps those training builds
    (:func:`cnnps.ps.patches.patch_maps` with the lights of rotation k), so each patch is
    :func:`cnnps.ps.patches.capture_patches`'s of the same pixels, bit for bit."""
    from cnnps.ps.patches import patch_maps as cell_maps

    intensities = np.asarray(intensities)
    n, b2, m = intensities.shape
    b = math.isqrt(b2)
    grids = turn_patch_grids(np.broadcast_to(intensities.reshape(n, b, b, m), (len(angles), n, b, b, m)), angles)
    missing = None
    if light_mask is not None:
        masks = np.broadcast_to(np.asarray(light_mask, bool).reshape(n, b, b, m), (len(angles), n, b, b, m))
        missing = ~turn_patch_grids(masks, angles).reshape(len(angles), n, b2, m)
    out = np.empty((len(angles), n, b2, w, w), np.float32)
    for k in range(len(angles)):  # the lights already turned: no further turn (theta 0)
        out[k] = cell_maps(grids[k].reshape(n, b2, m), lights[k], np.zeros(n), w,
                           missing=None if missing is None else missing[k]).reshape(n, b2, w, w)
    return out


def grey_and_colour(intensities, colour, channels: int):
    """(grey (P, m), colour (P, m, 3) or None) as :func:`rotated_normals` takes them."""
    intensities = np.asarray(intensities)
    if channels == 1:
        if colour is not None or intensities.ndim != 2:
            raise ValueError(f"a grey model takes (P, m) grey values, got {intensities.shape}"
                             + (" and colour values" if colour is not None else ""))
        return intensities, None
    if intensities.ndim == 3:
        if colour is not None:
            raise ValueError("give colour values once: (P, m, 3) intensities, or grey ones and colour=")
        colour = intensities
        intensities = intensities.astype(np.float32).mean(axis=2, dtype=np.float32)
    if colour is None:  # a grey capture: R = G = B
        colour = np.broadcast_to(np.asarray(intensities)[..., None], intensities.shape + (3,))
    if np.shape(colour) != intensities.shape + (3,):
        raise ValueError(f"colour must be {intensities.shape + (3,)} to match the grey values, got {np.shape(colour)}")
    return intensities, colour


def colour_maps(grey: np.ndarray, colour: np.ndarray, lights: np.ndarray, w: int,
                light_mask: np.ndarray | None = None) -> np.ndarray:
    """(R, n, 4, w, w) float32 maps of a colour model under R light configurations
    ``lights`` (R, m, 3): channel 0 :func:`cnnps.ps.obsmap.observation_maps_multi` of the
    ``grey`` values (n, m), channels 1-3 :func:`cnnps.ps.obsmap.observation_maps_rgb_multi`
    of ``colour`` (n, m, 3), with the same ``light_mask`` (n, m): the training rule
    (:func:`cnnps.synth.pixelwise.generate` with ``rgb=True``)."""
    from cnnps.ps.obsmap import observation_maps_multi, observation_maps_rgb_multi

    g = observation_maps_multi(grey, lights, w=w, light_mask=light_mask)
    c = observation_maps_rgb_multi(colour, lights, w=w, light_mask=light_mask)
    return np.concatenate([g[:, :, None], c], axis=2)
