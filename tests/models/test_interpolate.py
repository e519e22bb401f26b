"""Weight-space interpolation of two checkpoints (cnnps.models.interpolate)."""

from __future__ import annotations

import json

import pytest
import torch

from cnnps.infra.errors import CnnpsError
from cnnps.models.checkpoint import load_checkpoint, save_checkpoint
from cnnps.models.interpolate import interpolate, main
from cnnps.models.network import CNNPS


def _net(seed: int, w: int = 8) -> CNNPS:
    torch.manual_seed(seed)
    return CNNPS(w=w)


@pytest.fixture
def ends(tmp_path):
    a, b = _net(0), _net(1)
    pa = save_checkpoint(tmp_path / "a.pt", a, meta={"min_lights": 50, "name": "a"})
    pb = save_checkpoint(tmp_path / "b.pt", b, meta={"min_lights": 6, "name": "b"})
    return a, b, pa, pb


@pytest.mark.parametrize("alpha", [0.0, 0.3, 1.0])
def test_each_tensor_is_the_weighted_sum(ends, alpha):
    a, b, pa, pb = ends
    net, _config, meta = interpolate(pa, pb, alpha)
    sa, sb = a.state_dict(), b.state_dict()
    for name, t in net.state_dict().items():
        torch.testing.assert_close(t, (1 - alpha) * sa[name] + alpha * sb[name], rtol=0, atol=1e-7)
    assert meta["interpolated"]["alpha"] == alpha


def test_the_outputs_of_the_mid_point_differ_from_both_ends(ends):
    a, b, pa, pb = ends
    net, _, _ = interpolate(pa, pb, 0.5)
    x = torch.rand(4, 1, 8, 8)
    for m in (a, b, net):
        m.eval()
    with torch.no_grad():
        ya, yb, ym = a(x), b(x), net(x)
    assert not torch.allclose(ym, ya) and not torch.allclose(ym, yb)


def test_meta_records_both_ends_and_the_fewest_lights_both_saw(ends):
    _, _, pa, pb = ends
    _, _, meta = interpolate(pa, pb, 0.5)
    rec = meta["interpolated"]
    assert rec["a"]["meta"]["name"] == "a" and rec["b"]["meta"]["name"] == "b"
    assert len(rec["a"]["sha256"]) == 64 and rec["a"]["sha256"] != rec["b"]["sha256"]
    assert meta["min_lights"] == 50


def test_min_lights_from_a_provenance_record_beside_shipped_weights(tmp_path):
    pa = save_checkpoint(tmp_path / "old.pt", _net(0))  # no meta.min_lights: shipped before it existed
    (tmp_path / "old.json").write_text(json.dumps({"min_lights": 50}))
    pb = save_checkpoint(tmp_path / "new.pt", _net(1), meta={"min_lights": 6})
    assert interpolate(pa, pb, 0.5)[2]["min_lights"] == 50


def test_refuses_a_different_network_and_a_bad_alpha(tmp_path, ends):
    _, _, pa, _ = ends
    other = save_checkpoint(tmp_path / "w16.pt", _net(2, w=16))
    with pytest.raises(CnnpsError, match="different network"):
        interpolate(pa, other, 0.5)
    with pytest.raises(CnnpsError, match="alpha"):
        interpolate(pa, pa, 1.5)


def test_command_writes_a_loadable_checkpoint(tmp_path, ends, capsys):
    _, _, pa, pb = ends
    out = tmp_path / "mid.pt"
    main([str(pa), str(pb), "--alpha", "0.25", "--out", str(out)])
    _, _, meta = load_checkpoint(out)
    assert meta["interpolated"]["alpha"] == 0.25
    with pytest.raises(SystemExit, match="alpha"):
        main([str(pa), str(pb), "--alpha", "-1", "--out", str(tmp_path / "bad.pt")])
    assert not (tmp_path / "bad.pt").exists()


def test_the_mean_of_three_is_each_tensor_averaged_and_records_every_file(tmp_path, ends):
    from cnnps.models.interpolate import mean

    a, b, pa, pb = ends
    c = _net(2)
    pc = save_checkpoint(tmp_path / "c.pt", c, meta={"min_lights": 20})
    net, _config, meta = mean([pa, pb, pc])
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    for name, t in net.state_dict().items():
        torch.testing.assert_close(t, (sa[name] + sb[name] + sc[name]) / 3, rtol=1e-6, atol=1e-7)
    assert [e["meta"].get("min_lights") for e in meta["mean"]] == [50, 6, 20] and meta["min_lights"] == 50
    # the mean of two is the mid-point
    two, _, _ = mean([pa, pb])
    mid, _, _ = interpolate(pa, pb, 0.5)
    for name, t in two.state_dict().items():
        torch.testing.assert_close(t, mid.state_dict()[name], rtol=1e-6, atol=1e-7)
    with pytest.raises(CnnpsError, match="two or more"):
        mean([pa])
    wide = save_checkpoint(tmp_path / "w.pt", _net(3, w=16))
    with pytest.raises(CnnpsError, match="different network"):
        mean([pa, wide])


def test_the_command_takes_mean_or_alpha(tmp_path, ends, capsys):
    _, _, pa, pb = ends
    out = tmp_path / "soup.pt"
    main([str(pa), str(pb), str(pa), "--mean", "--out", str(out)])
    assert "the mean of 3 checkpoints" in capsys.readouterr().out and load_checkpoint(out)[2]["mean"]
    with pytest.raises(SystemExit):
        main([str(pa), str(pb), str(pa), "--alpha", "0.5", "--out", str(tmp_path / "x.pt")])
    assert "takes two checkpoints" in capsys.readouterr().err
