"""The heat-map heads on the CNN-PS trunk train: a short Adam run at the arms' learning
rate on Lambertian maps keeps the dense layer's units alive and lowers the error."""

import numpy as np
import pytest
import torch

from cnnps.models.heads import decode_output, training_loss
from cnnps.models.model_options import build_model
from cnnps.ps.metrics import angular_error_deg
from cnnps.ps.obsmap import observation_maps


def _lambertian_batch(rng, n, w, m=60):
    normals = rng.normal(size=(n, 3)) + [0, 0, 1.5]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    L = rng.normal(size=(m, 3))
    L[:, 2] = np.abs(L[:, 2]) + 0.2
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    I = np.clip(normals @ L.T, 0, None) * rng.uniform(0.3, 1.0, (n, 1))
    return torch.from_numpy(observation_maps(I, L, w=w)[:, None]).float(), torch.from_numpy(normals).float()


@pytest.mark.parametrize("head", ["heatmap-softmax", "regression"])
def test_the_cnnps_trunk_learns_with_the_head(head):
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    net = build_model(head=head, w=16)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    x_val, n_val = _lambertian_batch(np.random.default_rng(99), 256, 16)
    alive = {}
    net.fc1.register_forward_hook(lambda mod, inp, out: alive.__setitem__("fc1", (out > 0).any(0).sum().item()))

    def val_error():
        net.eval()
        with torch.no_grad():
            return angular_error_deg(decode_output(net, net(x_val)).numpy(), n_val.numpy()).mean()

    before = val_error()
    for _ in range(120):
        net.train()
        x, n = _lambertian_batch(rng, 64, 16)
        loss = training_loss(net, net(x), n)
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = val_error()
    assert alive["fc1"] >= 32  # of 128: the dense layer did not die
    assert after < 0.6 * before and after < 20.0
