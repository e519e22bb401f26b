"""The weights a training run starts from (``train.init``): a cnnps checkpoint checked
against the run's map width and model options, a grey one widened for a colour run.
"""

from __future__ import annotations

import sys

from cnnps.infra.errors import InputError
from cnnps.models.checkpoint import load_checkpoint, read_checkpoint
from cnnps.models.model_options import model_options
from cnnps.models.network import widen_state


def load_init_weights(init: str | None, w: int, in_channels: int = 1,
                      options: dict | None = None) -> tuple[dict | None, str | None]:
    """(state_dict for a network of ``in_channels`` input channels and the model
    ``options`` (``{"arch", "head", "patch"}``, ``train.model``; None: the paper's
    network), weights SHA-256) of the cnnps checkpoint ``init`` (``train.init``), or
    (None, None). The SHA-256, not the path, enters the run key. A grey (1-channel)
    checkpoint for a colour run is widened (:func:`cnnps.models.network.widen_state`: the
    colour filters at 0, so it starts as the grey model), which one line on stderr says;
    other mismatches (w, the model options the checkpoint records) are an InputError."""
    if init is None:
        return None, None
    model, config, _ = load_checkpoint(init)
    if int(config["w"]) != w:
        raise InputError(init, f"train.init is a w={config['w']} model, the shards hold w={w} maps")
    want, have = options or {"arch": "cnnps", "head": "regression", "patch": 1}, model_options(model)
    if have != want:
        have_s, want_s = (", ".join(f"{k} {o[k]}" for k in ("arch", "head", "patch")) for o in (have, want))
        raise InputError(init, f"train.init is a model of {have_s}; train.model asks for {want_s}")
    state = model.state_dict()
    if model.in_channels != in_channels:
        if model.in_channels != 1:
            raise InputError(init, f"train.init takes {model.in_channels} input channels, this run trains "
                             f"{in_channels} (train.pixelwise.rgb: {'true' if in_channels > 1 else 'false'})")
        state = widen_state(state, in_channels)
        print(f"train: train.init {init} is a grey model: widened to {in_channels} input channels "
              "(grey, R, G, B; the colour filters start at 0)", file=sys.stderr)
    return state, read_checkpoint(init)["weights_sha256"]
