"""Batched CNN-PS inference with test-time rotations, device and precision choice.

``predict_normals`` streams pixels: for each chunk of pixels and each of the K rotation
angles theta_k it builds the observation maps under the lights rotated by +theta_k, runs
the network in small batches, and finally rotates each prediction back by -theta_k and
averages (``cnnps.ps.rotation.average_rotated_predictions``). Only one chunk's maps exist
at a time, so memory stays bounded for any image size.

Speed (``docs/performance.md``): a CNNPS model is never run as trained.
On CPU it runs as ``cnnps.models.network.FastCNNPS`` (linear layers folded: fewer
operations; no dropout; no concatenations; ReLU and partial sums fused into oneDNN
convolutions), in fp32 or with its own bf16 weights (precision="bf16"; no autocast); on
CUDA as ``FoldedCNNPS`` (bf16: under autocast); always channels_last,
under ``torch.inference_mode``, CPU batches small enough to stay in the caches
(``DEFAULT_BATCH_CPU`` = 256 maps). Outputs equal the trained network's up to float32
rounding. Any other ``nn.Module`` mapping (B, 1, w, w) maps to (B, 3) normals is run as
given. :class:`MapPredictor` is also what the train stage validates with
(:mod:`cnnps.train.validation`).

Colour models (``in_channels`` = 4, :data:`cnnps.models.network.RGB_CHANNELS`) get per
rotation the grey map and the R, G, B maps of the training rule
(:func:`cnnps.ps.obsmap.observation_maps_rgb_multi`), under distant lights and an
orthographic camera without the Lambertian fill (:func:`cnnps.models.map_inputs.check_colour_inputs`).

Heat-map models (``head`` ``heatmap``, :mod:`cnnps.models.heads`) give each map a
(w, w) heat-map, decoded to a unit normal on the device (:mod:`cnnps.models.heatmap`)
before the K rotations are averaged as any normal is; their spread in degrees is each
pixel's uncertainty. A CNN-PS heat-map model runs as ``FastCNNPS`` as the regression one
does; the U-Net (:mod:`cnnps.models.unet`) runs as built (bf16: under autocast).

Patch models (``patch`` b > 1, :mod:`cnnps.models.patch`) take each pixel's b x b
neighbourhood: (P, b^2, m) grey values, shared distant lights, an orthographic camera,
and K in 1, 2, 4 (:func:`cnnps.models.map_inputs.check_patch_inputs`): under each rotation the patch grid turns
with the lights by whole quarter turns. The cells and their maps are training's
(:func:`cnnps.ps.patches.quarter_turn_cells`, :func:`cnnps.ps.patches.patch_maps`): given
the neighbourhoods with zeros outside the mask, the patches equal
:func:`cnnps.ps.patches.capture_patches`'s bit for bit (``tests/models/test_patch_agreement.py``).
"""

from __future__ import annotations

import copy
import os

import numpy as np
import torch
from torch import nn

from cnnps.infra.errors import CnnpsError
from cnnps.models.devices import resolve_device  # also part of this module's API
from cnnps.models.heads import heat_maps, is_heatmap, model_head
from cnnps.models.heatmap import check_decoding, decode_heatmaps, decode_with_spread
from cnnps.models.map_inputs import (
    check_colour_inputs,
    check_patch_inputs,
    colour_maps,
    grey_and_colour,
    model_channels,
    model_patch,
    patch_maps,
)
from cnnps.models.network import CNNPS, fast_cpu_model, fold_for_inference
from cnnps.models.unet import HeatmapUNet
from cnnps.ps.rotation import average_rotated_predictions, rotate_z, rotation_angles

PRECISIONS = ("fp32", "bf16")
# Maps built at once (all K rotations of PIXEL_CHUNK // K pixels): 4096 x 32 x 32 float32 = 16 MB.
PIXEL_CHUNK = 4096
# Network batch sizes: small batches keep the activations in the CPU caches, which is
# worth more than the per-call overhead (docs/performance.md#inference). GPUs want large batches.
DEFAULT_BATCH_CPU = 256
DEFAULT_BATCH_CUDA = 4096


def check_precision(precision: str) -> str:
    precision = str(precision).strip().lower()
    if precision not in PRECISIONS:
        raise CnnpsError(f"unknown precision {precision!r}: use one of {', '.join(PRECISIONS)}")
    return precision


class MapPredictor:
    """Callable numpy maps (float16 or float32) -> (B, 3) float32 numpy normals: (B, w, w)
    for a 1-channel (grey) model, (B, C, w, w) for a C-channel one (``in_channels``),
    (B, C b^2, w, w) for a patch model (``patch`` b > 1, the layout of
    :mod:`cnnps.models.patch`). A heat-map model's heat-maps are decoded to normals
    (``head``, by ``heatmap_decoding``: ``window`` or ``parabola``,
    :func:`cnnps.models.heatmap.decode_heatmaps`; a regression model ignores it;
    ``spread=`` also gives each map's heat-map spread in degrees).

    Holds the prepared (folded, moved, channels_last, eval mode) copy of the model; the
    caller's model is not modified (nor its train/eval mode), and building the copy draws
    nothing from the global torch RNG.
    """

    def __init__(self, model: nn.Module, device: str | torch.device = "auto", precision: str = "fp32",
                 batch_size: int | None = None, fold: bool = True, heatmap_decoding: str = "window"):
        self.device = resolve_device(device)
        self.heatmap_decoding = check_decoding(heatmap_decoding)
        self.precision = check_precision(precision)
        if batch_size is None:
            batch_size = DEFAULT_BATCH_CUDA if self.device.type == "cuda" else DEFAULT_BATCH_CPU
        if int(batch_size) < 1:
            raise CnnpsError(f"batch size must be >= 1, got {batch_size}")
        self.batch_size = int(batch_size)
        self.w = int(getattr(model, "w", 32))
        self.in_channels = model_channels(model)
        self.patch = model_patch(model)
        self.head = model_head(model)
        # autocast: bf16 anywhere but in FastCNNPS, which holds its own bf16 weights
        self.autocast = self.precision == "bf16"
        if fold and isinstance(model, CNNPS):
            if self.device.type == "cpu":  # folded, concatenation-free, fused oneDNN kernels
                net = fast_cpu_model(model, torch.bfloat16 if self.precision == "bf16" else torch.float32)
                self.autocast = False
            else:
                net = fold_for_inference(model)  # CUDA: the plain folded network (bf16: autocast)
        elif fold and isinstance(model, HeatmapUNet):
            net = model.for_inference()  # its patch layer folded into one convolution
        else:
            net = copy.deepcopy(model)
        self.net = net.to(self.device).eval().to(memory_format=torch.channels_last)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.autocast:
            with torch.autocast(self.device.type, dtype=torch.bfloat16):
                y = self.net(x)
        else:
            y = self.net(x)
        return y.float()

    @torch.inference_mode()
    def __call__(self, maps: np.ndarray, progress=None, spread: np.ndarray | None = None) -> np.ndarray:
        """(B, 3) normals of ``maps``; ``spread`` (B,) float32, optional: filled with each
        heat-map's spread in degrees (:func:`cnnps.models.heatmap.heatmap_spread_deg`;
        ValueError for a regression model, which has none)."""
        if spread is not None and not is_heatmap(self.head):
            raise ValueError("spread= needs a heat-map model; a regression model's spread is rotation_spread")
        maps = np.ascontiguousarray(maps, dtype=np.float32)
        C = self.in_channels * self.patch * self.patch
        want = (self.w, self.w) if C == 1 else (C, self.w, self.w)
        if maps.ndim != 1 + len(want) or maps.shape[1:] != want:
            raise ValueError(f"maps must be (B, {', '.join(map(str, want))}), got {maps.shape}")
        out = np.empty((maps.shape[0], 3), dtype=np.float32)
        x_all = torch.from_numpy(maps)
        if C == 1:
            x_all = x_all.unsqueeze(1)  # (B, 1, w, w): with one channel also channels_last
        for start in range(0, maps.shape[0], self.batch_size):
            x = x_all[start:start + self.batch_size].to(self.device, non_blocking=True)
            x = x.contiguous(memory_format=torch.channels_last)
            y = self._forward(x)
            if is_heatmap(self.head):
                y = heat_maps(self.head, y)  # heatmap-softmax: the softmax of its logits
                if spread is not None:
                    y, s = decode_with_spread(y, self.heatmap_decoding)
                    spread[start:start + x.shape[0]] = s.cpu().numpy()
                else:
                    y = decode_heatmaps(y, self.heatmap_decoding)
            out[start:start + x.shape[0]] = y.cpu().numpy()
            if progress is not None:
                progress.update(x.shape[0])
        return out


def predict_normals(
    model: nn.Module,
    intensities: np.ndarray,
    lights: np.ndarray,
    rotations: int = 10,
    device: str | torch.device = "auto",
    precision: str = "fp32",
    batch_size: int | None = None,
    progress: bool = True,
    pixel_chunk: int = PIXEL_CHUNK,
    sparse_fill: str = "auto",
    views: np.ndarray | None = None,
) -> np.ndarray:
    """Unit normals (P, 3) float32 for P pixels from their (P, m) intensities
    (:func:`rotated_normals` with a :class:`MapPredictor` of ``model``).

    intensities: (P, m), already divided by each light's intensity; for an RGB model
    (``in_channels`` 4) also (P, m, 3), each channel divided by its own intensity (the
    grey map is then their mean's; (P, m) grey values stand for R = G = B); for a patch
    model (``patch`` b > 1) (P, b^2, m), each pixel's b x b neighbourhood row by row, the
    pixel itself at the centre, zeros for a cell outside the mask or the image (the edge
    rule of training, :mod:`cnnps.ps.patches`) (:func:`cnnps.models.map_inputs.check_patch_inputs`).
    lights: (m, 3) unit light directions (camera frame: x right, y up, z to the camera),
    or (P, m, 3) each pixel's own (point lights near the object; never sparse-filled).
    rotations: K test-time rotations (K = 1: none; the paper uses 10).
    device: 'auto' | 'cpu' | 'cuda[:N]'. precision: 'fp32' | 'bf16' (CPU: bf16 weights and
    activations, :class:`~cnnps.models.network.FastCNNPS`; CUDA: autocast).
    batch_size: maps per network call (default ``DEFAULT_BATCH_CPU`` = 256 on CPU,
    ``DEFAULT_BATCH_CUDA`` = 4096 on CUDA).
    sparse_fill: 'auto' | 'on' | 'off': virtual Lambertian observations for sparse captures
    (:mod:`cnnps.ps.sparse_fill`; 'auto' = below ``FILL_BELOW`` = 50 images).
    views: (P, 3) per-pixel view directions of a perspective camera (see
    :func:`rotated_normals`); None = orthographic.
    """
    intensities = np.asarray(intensities, dtype=np.float32)
    lights = np.asarray(lights, dtype=np.float64)
    channels = model_channels(model)
    patch = model_patch(model)
    if patch > 1:
        if intensities.ndim != 3 or intensities.shape[1] != patch * patch:
            raise ValueError(f"a patch model (patch={patch}) takes (P, {patch * patch}, m) intensities, "
                             f"got {intensities.shape}")
        check_patch_inputs(patch, channels, rotations=rotations, per_pixel_lights=np.ndim(lights) == 3)
        intensities = intensities.reshape(-1, intensities.shape[2])  # (P b^2, m): every pixel of every patch
    elif intensities.ndim != 2 and not (channels > 1 and intensities.ndim == 3 and intensities.shape[2] == 3):
        raise ValueError(f"intensities must be (P, m){' or (P, m, 3)' if channels > 1 else ''}, "
                         f"got {intensities.shape}")
    P, m = intensities.shape[:2]
    if lights.shape not in ((m, 3), (P // (patch * patch), m, 3)):
        raise ValueError(f"lights must be ({m}, 3) or ({P}, {m}, 3) to match intensities, got {lights.shape}")
    from cnnps.ps.sparse_fill import lambertian_fill, should_fill

    fill = should_fill(sparse_fill, m) and lights.ndim == 2  # per-pixel lights (point lights): no fill
    check_colour_inputs(channels, per_pixel_lights=lights.ndim == 3, views=views is not None, fill=fill)
    predictor = MapPredictor(model, device=device, precision=precision, batch_size=batch_size)
    light_mask = None
    if fill:
        f = lambertian_fill(intensities, lights, w=predictor.w)
        intensities, lights, light_mask = f.intensities, f.lights, f.light_mask
    if patch > 1:  # back to (P, b^2, m)
        intensities = intensities.reshape(-1, patch * patch, intensities.shape[1])
        light_mask = None if light_mask is None else light_mask.reshape(intensities.shape)
        P = intensities.shape[0]
    bar = None
    if progress:
        from cnnps.infra.progress import progress_bar

        bar = progress_bar(total=P * int(rotations), unit="map", unit_scale=True, desc="cnn-ps", leave=False)
    try:
        return rotated_normals(predictor, intensities, lights, rotations, light_mask=light_mask, progress=bar,
                               pixel_chunk=pixel_chunk, views=views)
    finally:
        if bar is not None:
            bar.close()


def rotated_normals(
    predictor: MapPredictor,
    intensities: np.ndarray,
    lights: np.ndarray,
    rotations: int,
    light_mask: np.ndarray | None = None,
    progress=None,
    pixel_chunk: int = PIXEL_CHUNK,
    read_ahead: int = 1,
    views: np.ndarray | None = None,
    spread: np.ndarray | None = None,
    colour: np.ndarray | None = None,
) -> np.ndarray:
    """(P, 3) float32 normals: K-rotation test-time averaging, pixels in chunks.

    ``intensities`` (P, m): the grey values (each light's intensity divided out). With a
    colour predictor (``in_channels`` 4) each map is (4, w, w): the grey map of
    ``intensities`` and the R, G, B maps (:func:`cnnps.ps.obsmap.observation_maps_rgb_multi`)
    of ``colour`` (P, m, 3) (each channel divided by its light's intensity in it; None:
    R = G = B = the grey values, a grey capture); ``intensities`` may then also be
    (P, m, 3), the colour values, whose mean is the grey. Such a predictor needs distant
    lights and no ``views`` (:func:`cnnps.models.map_inputs.check_colour_inputs`). A chunk then holds about
    ``pixel_chunk`` / 4 maps, so its maps take the grey ones' memory.

    The maps of a chunk's pixels under all K rotated light sets are built in one pass
    (:func:`cnnps.ps.obsmap.observation_maps_multi`: the values are masked and laid out
    once, not K times; identical maps), about ``pixel_chunk`` maps per chunk in all
    (``pixel_chunk // K`` pixels), and ``read_ahead`` chunks ahead in a background thread
    (:func:`cnnps.infra.prefetch.prefetched`; numpy releases the GIL), so building the next
    chunk's maps overlaps the network on this one. ``light_mask`` (P, m): False drops an
    observation (e.g. saturated). ``progress``: a tqdm bar updated per map.

    ``views`` (P, 3): each pixel's unit view direction (toward the camera) under a
    perspective camera (:func:`cnnps.ps.camera.view_directions`). Each pixel's lights are
    then turned by the smallest rotation R that takes its view to +z, the maps are built
    from those (the K rotations about z follow, as for any pixel), and the averaged
    answer is turned back by R^T: exact for isotropic materials, whose reflectance depends
    only on n.l, n.v and l.v. None is the orthographic camera.

    ``lights`` may also be (P, m, 3): each pixel's own light directions (point lights near
    the object, :mod:`cnnps.ps.near_lights`); they are turned by the pixel's view rotation
    the same way. Lights behind a pixel's view plane are left out of its map.

    A patch predictor (``patch`` b > 1) takes ``intensities`` (P, b^2, m) and
    ``light_mask`` (P, b^2, m): each pixel's b x b neighbourhood, row by row (image rows),
    the pixel itself at the centre; under the rotation by theta_k (a quarter turn times q)
    the patch grid turns with the lights, by q quarter turns counter-clockwise as seen
    from the camera (:func:`cnnps.models.map_inputs.turn_patch_grids`), so each rotated input is that of the scene
    turned about z (:func:`cnnps.models.map_inputs.check_patch_inputs`: grey, shared distant lights, no ``views``,
    K in 1, 2, 4).

    ``spread`` (P,) float32, optional: filled with each pixel's :func:`rotation_spread` in
    degrees (0 with K = 1), or, for a heat-map predictor (``head`` ``heatmap``), with the
    mean over the K rotations of its heat-maps' spread in degrees
    (:func:`cnnps.models.heatmap.heatmap_spread_deg`); the normals are the same with or
    without it.
    """
    from cnnps.infra.prefetch import prefetched
    from cnnps.ps.camera import view_rotations
    from cnnps.ps.obsmap import observation_maps_multi, observation_maps_per_pixel

    angles = rotation_angles(int(rotations))
    per_pixel = np.ndim(lights) == 3
    channels = model_channels(predictor)
    patch = model_patch(predictor)
    check_colour_inputs(channels, per_pixel_lights=per_pixel, views=views is not None)
    check_patch_inputs(patch, channels, rotations=len(angles), per_pixel_lights=per_pixel, views=views is not None)
    if patch > 1:
        intensities = np.asarray(intensities)
        if intensities.ndim != 3 or intensities.shape[1] != patch * patch:
            raise ValueError(f"a patch model (patch={patch}) takes (P, {patch * patch}, m) intensities, "
                             f"got {intensities.shape}")
    else:
        intensities, colour = grey_and_colour(intensities, colour, channels)
    rotated = None if per_pixel else np.stack([rotate_z(lights, a) for a in angles])
    P = intensities.shape[0]
    chunk = max(1, int(pixel_chunk) // (len(angles) * channels * patch * patch))
    starts = range(0, P, chunk)

    def maps_of(start: int) -> np.ndarray:
        stop = min(start + chunk, P)
        mask = None if light_mask is None else light_mask[start:stop]
        if patch > 1:
            return patch_maps(intensities[start:stop], rotated, angles, predictor.w, mask)
        if channels > 1:
            return colour_maps(intensities[start:stop], colour[start:stop], rotated, predictor.w, mask)
        if views is None and not per_pixel:
            return observation_maps_multi(intensities[start:stop], rotated, w=predictor.w, light_mask=mask)
        if per_pixel:
            own = np.asarray(lights[start:stop], np.float64)
            if views is not None:
                own = np.einsum("nij,nmj->nmi", view_rotations(views[start:stop]), own)
        else:  # (n, m, 3) in each view frame
            own = np.einsum("nij,mj->nmi", view_rotations(views[start:stop]), np.asarray(lights, np.float64))
        # a light behind the view plane (l.v <= 0) has no cell of its own on the map (it would
        # fold onto the light mirrored above it), and orthographic captures never have one
        ahead = own[..., 2] > 0
        mask = ahead if mask is None else mask & ahead
        per = np.stack([rotate_z(own, a) for a in angles])
        return observation_maps_per_pixel(intensities[start:stop], per, w=predictor.w, light_mask=mask)

    out = np.empty((P, 3), dtype=np.float32)
    for start, maps in zip(starts, prefetched(maps_of, starts, depth=read_ahead)):
        n = maps.shape[1]
        pred = rotated_answers(predictor, maps, angles, progress=progress,
                               spread=None if spread is None else spread[start:start + n])
        if views is not None:  # back from each pixel's view frame: n = R^T (R n)
            pred = np.einsum("nji,nj->ni", view_rotations(views[start:start + n]), np.asarray(pred, np.float64))
        out[start:start + n] = pred
    return out


def rotated_answers(predictor: MapPredictor, maps: np.ndarray, angles: np.ndarray, progress=None,
                    spread: np.ndarray | None = None) -> np.ndarray:
    """(n, 3) the K-rotation average of n pixels' answers: ``maps`` (K, n, ...) the inputs
    of each pixel under the K rotations ``angles`` (K,) (maps built with the lights, and a
    patch's grid, turned by ``angles[k]``), run by ``predictor`` in one call, each answer
    turned back by -``angles[k]`` about z and averaged
    (:func:`cnnps.ps.rotation.average_rotated_predictions`; K = 1: the answer as it is,
    float32). ``spread`` (n,) float32, optional: filled as :func:`rotated_normals` fills it
    (the heat-map spread, mean over the K rotations, of a heat-map predictor, else
    :func:`rotation_spread`)."""
    K, n = maps.shape[:2]
    heat_spread = np.empty(K * n, np.float32) if spread is not None and is_heatmap(model_head(predictor)) else None
    preds = predictor(maps.reshape((K * n,) + maps.shape[2:]), progress=progress,
                      **({} if heat_spread is None else {"spread": heat_spread})).reshape(K, n, 3)
    pred = preds[0] if K == 1 else average_rotated_predictions(preds, angles)
    if heat_spread is not None:
        spread[:] = heat_spread.reshape(K, n).mean(axis=0)
    elif spread is not None:
        spread[:] = rotation_spread(preds, angles, pred)
    return pred


def rotation_spread(preds: np.ndarray, angles: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """(n,) the mean angle in degrees between K answers ``preds`` (K, n, 3), each turned
    back by its rotation ``angles`` (K,) about z, and their average ``mean`` (n, 3) unit:
    how much the network disagrees with itself over the test-time rotations (0 for K = 1).

    >>> import numpy as np
    >>> preds = np.array([[[0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0]]])
    >>> rotation_spread(preds, np.array([0.0, np.pi]), np.array([[0.0, 0.0, 1.0]]))
    array([0.], dtype=float32)
    """
    from cnnps.ps.rotation import normalize, rotate_z

    K = len(angles)
    if K == 1:
        return np.zeros(preds.shape[1], dtype=np.float32)
    mean = np.asarray(mean, np.float64)
    total = np.zeros(preds.shape[1])
    for p, a in zip(np.asarray(preds, np.float64), angles):
        cos = np.einsum("nk,nk->n", normalize(rotate_z(p, -a)), mean)
        total += np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return (total / K).astype(np.float32)


def set_cpu_threads(n: int | None = None) -> int:
    """Set torch's intra-op threads (default: all cores this process may use); returns it."""
    if n is None:
        n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    torch.set_num_threads(max(1, int(n)))
    return torch.get_num_threads()
