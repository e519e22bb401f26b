"""Per-pixel training batches (:mod:`cnnps.synth.pixelwise`) as the train stage makes them:
the generator's settings from the train params (:func:`pixelwise_settings`), a maker of
batches (:func:`pixelwise_maker`), a stream of one batch a step seeded by (seed, rank, step)
(:class:`GeneratedBatches`), the network's input channels (:func:`input_channels`) and the
fewest lights of a per-pixel map (:func:`pixelwise_fewest_lights`).
"""

from __future__ import annotations

import torch

from cnnps.models.network import RGB_CHANNELS
from cnnps.train.maps_ahead import made_ahead
from cnnps.train.params import Params


class GeneratedBatches:
    """Per-pixel batches (:mod:`cnnps.synth.pixelwise`) where the shard dataset would be:
    the same ``set_epoch`` / ``set_skip`` / iteration, one batch per step, each made from
    a generator seeded by (seed, rank, step), so a resumed run makes what an uninterrupted
    one made. ``steps``: the batches of one pass (the run's steps)."""

    def __init__(self, make, steps: int, device: torch.device | None = None, ahead: int = 0):
        self.make, self.steps, self.skip = make, int(steps), 0
        self.device, self.ahead = device or torch.device("cpu"), int(ahead)

    def set_epoch(self, epoch: int) -> None:
        pass

    def set_skip(self, batches: int) -> None:
        self.skip = int(batches)

    def __iter__(self):
        # made ahead of the step in a background thread (cnnps.train.maps_ahead) when ``ahead``
        yield from made_ahead(self.make, range(self.skip, self.steps), self.device, self.ahead)


def input_channels(params: Params) -> int:
    """The network's input channels for ``params``: :data:`cnnps.models.network.RGB_CHANNELS`
    (grey, R, G, B) with ``train.pixelwise.rgb``, else 1."""
    return RGB_CHANNELS if params.pixelwise.rgb else 1


def pixelwise_settings(params: Params) -> dict:
    """The keyword arguments of :func:`cnnps.synth.pixelwise.generate` that ``params`` sets:
    the materials and light subsets of ``params.synthesis`` (``materials.categories`` /
    ``ranges``, extract's light-subset rules), the light set's size, the sparse fraction
    and the effects of ``params.pixelwise``, and ``rgb``."""
    from cnnps.synth import pixelwise

    px, syn = params.pixelwise, params.synthesis
    return {
        "categories": syn.categories, "ranges": syn.ranges, "n_lights": px.lights,
        "min_lights": syn.min_lights, "max_lights": syn.max_lights,
        "cone_min_deg": syn.cone_min_deg, "cone_max_deg": syn.cone_max_deg,
        "sparse_fraction": px.sparse_fraction, "sparse_min_lights": syn.sparse_min_lights,
        "effects": pixelwise.Effects(**{k: float(v) for k, v in px.effects.items()}),
        "rgb": input_channels(params) > 1,
    }


def pixelwise_maker(params: Params):
    """``(n, generator, device, w) -> (maps (n, C, w, w), normals (n, 3))``: per-pixel
    training maps, :func:`cnnps.synth.pixelwise.generate` with every setting of
    :func:`pixelwise_settings`, C = 1, or 4 (grey, R, G, B) with ``pixelwise.rgb``; None
    when ``pixelwise.share`` is 0."""
    if not params.pixelwise.share:
        return None
    from cnnps.synth import pixelwise

    settings = pixelwise_settings(params)

    def make(n, generator, device, w):
        return pixelwise.generate(n, generator=generator, device=device, w=w, **settings)

    return make


def pixelwise_fewest_lights(params: Params) -> int:
    """The fewest lights of any per-pixel map of ``params`` (:func:`cnnps.synth.pixelwise.light_subsets`'
    bounds): ``min(synthesis.min_lights, pixelwise.lights)``, or with sparse maps
    ``synthesis.sparse_min_lights`` below it."""
    lo = min(params.synthesis.min_lights, params.pixelwise.lights)
    if params.pixelwise.sparse_fraction > 0:
        lo = max(1, min(params.synthesis.sparse_min_lights, lo))
    return int(lo)
