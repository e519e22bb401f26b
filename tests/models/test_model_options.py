"""Model options in checkpoints (cnnps.models.model_options, cnnps.models.checkpoint):
files without them are the paper's network, bit for bit; files with them round-trip."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cnnps.infra.errors import InputError
from cnnps.models.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from cnnps.models.heatmap import decode_heatmaps
from cnnps.models.inference import MapPredictor
from cnnps.models.model_options import build_model, model_options
from cnnps.models.network import CNNPS, FastCNNPS
from cnnps.models.shipped import weights_path
from cnnps.models.unet import HeatmapUNet


def _paper_forward(sd: dict, x: torch.Tensor) -> torch.Tensor:
    """The paper's layers in eval mode, written out from a state dict."""

    def conv(name, t, pad):
        return F.conv2d(t, sd[f"{name}.weight"], sd[f"{name}.bias"], padding=pad)

    r = F.relu(conv("conv0", x, 1))
    r = torch.cat([r, F.relu(conv("block1_conv1", r, 1))], dim=1)
    r = torch.cat([r, F.relu(conv("block1_conv2", r, 1))], dim=1)
    r = F.relu(F.avg_pool2d(conv("trans_conv", r, 0), 2))
    r = torch.cat([r, F.relu(conv("block2_conv1", r, 1))], dim=1)
    r = torch.cat([r, F.relu(conv("block2_conv2", r, 1))], dim=1)
    h = F.relu(F.linear(conv("final_conv", r, 0).flatten(1), sd["fc1.weight"], sd["fc1.bias"]))
    return F.normalize(F.linear(h, sd["fc2.weight"], sd["fc2.bias"]).float(), dim=1)


def test_the_shipped_checkpoint_is_the_papers_network_bit_for_bit():
    path = weights_path()
    payload = read_checkpoint(path)
    assert not {"arch", "head", "patch"} & set(payload["config"])  # written before the options existed
    model, config, _ = load_checkpoint(path)
    assert type(model) is CNNPS and model_options(model) == {"arch": "cnnps", "head": "regression", "patch": 1}
    sd = {k: v.float() for k, v in payload["state_dict"].items()}
    x = torch.rand(16, 1, 32, 32, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert torch.equal(model(x), _paper_forward(sd, x))


def test_default_models_save_no_option_keys(tmp_path):
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "m.pt", CNNPS(w=8), meta={"steps": 1})
    assert set(read_checkpoint(tmp_path / "m.pt")["config"]) == {"w", "dropout", "in_channels", "arch_version"}


@pytest.mark.parametrize("options", [
    dict(arch="cnnps", head="heatmap", patch=1),
    dict(arch="cnnps", head="regression", patch=3),
    dict(arch="unet", head="heatmap", patch=5),
])
def test_options_round_trip_through_a_checkpoint(tmp_path, options):
    torch.manual_seed(1)
    net = build_model(**options, w=8).eval()
    save_checkpoint(tmp_path / "m.pt", net, meta={"note": "tiny"})
    config = read_checkpoint(tmp_path / "m.pt")["config"]
    assert {k: config.get(k, d) for k, d in (("arch", "cnnps"), ("head", "regression"), ("patch", 1))} == options
    back, _, meta = load_checkpoint(tmp_path / "m.pt")
    assert model_options(back) == options and meta == {"note": "tiny"}
    assert type(back) is (HeatmapUNet if options["arch"] == "unet" else CNNPS)
    x = torch.rand(3, options["patch"] ** 2, 8, 8)
    with torch.no_grad():
        assert torch.equal(back(x), net(x))


def test_a_config_naming_an_unknown_head_names_the_file(tmp_path):
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "m.pt", CNNPS(w=8), config={"head": "bogus"})
    with pytest.raises(InputError, match="head must be one of regression, heatmap, heatmap-softmax, got 'bogus'") as info:
        load_checkpoint(tmp_path / "m.pt")
    assert info.value.path == tmp_path / "m.pt"
    with pytest.raises(ValueError, match=r"config\['head'\] = 'regression' disagrees"):
        save_checkpoint(tmp_path / "h.pt", build_model(head="heatmap", w=8), config={"head": "regression"})


def test_heatmap_predictors_decode_what_the_network_outputs():
    torch.manual_seed(3)
    rng = np.random.default_rng(0)
    maps = rng.random((40, 16, 16)).astype(np.float32)
    x = torch.from_numpy(maps)[:, None]
    for net in (build_model(head="heatmap", w=16).eval(), build_model(arch="unet", head="heatmap", w=16).eval()):
        with torch.no_grad():
            heat = net(x)
        for precision in ("fp32", "bf16"):
            pred = MapPredictor(net, device="cpu", precision=precision, batch_size=16)
            spread = np.empty(40, np.float32)
            normals = pred(maps, spread=spread)
            assert normals.shape == (40, 3) and np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-5)
            assert np.all(spread >= 0) and np.all(spread <= 90)
            with torch.no_grad():  # what the predictor runs, batch by batch: FastCNNPS (its own bf16 weights) or the U-Net
                ran = torch.cat([pred._forward(x[i:i + 16].contiguous(memory_format=torch.channels_last))
                                 for i in range(0, 40, 16)])
            np.testing.assert_allclose(normals, decode_heatmaps(ran).numpy(), atol=1e-6)
            tol = 1e-4 if precision == "fp32" else 3e-2
            torch.testing.assert_close(ran, heat, rtol=0, atol=tol * float(heat.abs().max()))
            if precision == "fp32":
                assert isinstance(pred.net, FastCNNPS) == isinstance(net, CNNPS)
    with pytest.raises(ValueError, match="spread= needs a heat-map model"):
        MapPredictor(build_model(w=16), device="cpu")(maps, spread=np.empty(40, np.float32))


def test_interpolation_refuses_networks_of_other_options(tmp_path):
    from cnnps.infra.errors import CnnpsError
    from cnnps.models.interpolate import interpolate

    torch.manual_seed(4)
    a = save_checkpoint(tmp_path / "a.pt", build_model(w=8))
    b = save_checkpoint(tmp_path / "b.pt", build_model(head="heatmap", w=8))
    with pytest.raises(CnnpsError, match="different network.*'head': 'heatmap'"):
        interpolate(a, b, 0.5)
    net, config, _ = interpolate(b, b, 0.5)
    assert model_options(net)["head"] == "heatmap" and config["head"] == "heatmap"
