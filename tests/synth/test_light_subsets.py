"""cnnps.synth.light_subsets: the light-subset rule's settings declared once and checked once,
for every place that takes them."""

from __future__ import annotations

import dataclasses

import pytest

from cnnps.infra.errors import ConfigError
from cnnps.stages.extract import Params as ExtractParams
from cnnps.synth import light_subsets as ls
from cnnps.synth import pixelwise
from cnnps.train.params import SynthesisParams
from cnnps.train.patch_dataset import PatchSampling


def test_every_place_takes_its_defaults_from_the_one_declaration():
    for obj in (ExtractParams(), SynthesisParams(), PatchSampling()):
        assert {n: getattr(obj, n) for n in ls.SETTINGS} == dataclasses.asdict(ls.RULE), type(obj)
    import inspect

    for fn in (pixelwise.generate, ls.light_subsets):
        sig = inspect.signature(fn)
        assert {n: sig.parameters[n].default for n in ls.SETTINGS} == dataclasses.asdict(ls.RULE), fn.__name__
    assert ls.SETTINGS == ("min_lights", "max_lights", "cone_min_deg", "cone_max_deg", "sparse_min_lights")


@pytest.mark.parametrize("bad, message", [
    ({"min_lights": 0}, "need 1 <= min_lights <= max_lights, got 0 and 1300"),
    ({"min_lights": 60, "max_lights": 50}, "need 1 <= min_lights <= max_lights, got 60 and 50"),
    ({"cone_min_deg": 50.0, "cone_max_deg": 40.0}, "need 0 < cone_min_deg <= cone_max_deg <= 180, got 50.0, 40.0"),
    ({"sparse_min_lights": 0}, ".sparse_min_lights must be >= 1, got 0"),
])
def test_one_check_one_message_named_for_its_section(bad, message):
    for cls, where in ((ExtractParams, "extract"), (SynthesisParams, "train.synthesis"), (PatchSampling, "patch")):
        with pytest.raises(ConfigError) as err:
            cls(**bad)
        assert str(err.value).startswith(where) and message in str(err.value), (where, str(err.value))


def test_a_sparse_share_needs_fewer_sparse_lights_than_dense_ones():
    with pytest.raises(ConfigError, match="extract: need sparse_min_lights < min_lights, got 50 and 50"):
        ExtractParams(sparse_fraction=0.2, sparse_min_lights=50, min_lights=50)
    ExtractParams(sparse_min_lights=50, min_lights=50)  # no sparse share: no constraint
