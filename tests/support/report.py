"""Synthetic predictions for the report page's tests, the page's data read back, and
the page's shading computed in numpy."""

from __future__ import annotations

import base64
import json
import re
import zlib

import numpy as np


def dome(H: int, W: int, seed: int = 0) -> dict:
    """A prediction of an elliptic dome filling most of an H x W image (not square, so
    rows and columns cannot be swapped unnoticed): the views :func:`cnnps.io.report.report_html`
    takes, every one present."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W]
    u, v = (x - (W - 1) / 2) / (0.46 * W), ((H - 1) / 2 - y) / (0.46 * H)
    r2 = u**2 + v**2
    mask = r2 < 1
    n = np.dstack([u, v, np.sqrt(np.clip(1 - r2, 0, None)) + 0.3]).astype(np.float32)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    n[~mask] = 0
    errors = np.where(mask, rng.gamma(2.0, 2.0, (H, W)), 0.0)
    depth = np.where(mask, 0.3 * min(H, W) * np.sqrt(np.clip(1 - r2, 0, None)), np.nan).astype(np.float32)
    record = {"capture": "/data/dome", "method": "cnn", "model": "weights.pt", "rotations": 10,
              "precision": "fp32", "precision_choice": {"reason": "asked for"}, "n_images": 40,
              "image_size": [H, W], "pixels": int(mask.sum()), "seconds": 12.5, "load_seconds": 1.25,
              "camera": {"model": "orthographic"}, "lights": {"model": "directional"},
              "confidence": {"measure": "a measure", "median": 0.5},
              "notes": ["a note <b>with markup</b>"], "notices": [], "warnings": ["a warning & more"]}
    return {"normals": n, "mask": mask, "record": record,
            "confidence": np.where(mask, rng.uniform(0, 1, (H, W)), 0).astype(np.float32),
            "errors": errors, "scored": mask,
            "stats": {"mean_deg": float(errors[mask].mean()), "median_deg": float(np.median(errors[mask])),
                      "pixels": int(mask.sum())},
            "depth": depth}


def page_data(page: str) -> dict:
    """The JSON of the page's ``report-data`` script."""
    found = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', page, re.S)
    assert found, "no report-data script"
    return json.loads(found.group(1))


def unpacked(text: str, delta: int = 0) -> np.ndarray:
    """The bytes of :func:`cnnps.io.report.data.packed`, as the page's script reads them."""
    raw = np.frombuffer(zlib.decompress(base64.b64decode(text)), dtype=np.uint8).copy()
    if delta:
        for k in range(delta):  # the running sum of each interleaved stream, mod 256
            raw[k::delta] = np.cumsum(raw[k::delta], dtype=np.uint64).astype(np.uint8)
    return raw


def relit(normals: np.ndarray, light, glossy: bool = False, weight: float = 0.35, shininess: float = 40):
    """The page's relit value of unit ``normals`` (..., 3) under unit ``light``: round(255 x
    max(0, n.l)), or with gloss (1 - weight) max(0, n.l) + weight max(0, n.h)^shininess
    (h the half vector of l and +z; no highlight where n.l <= 0), at most 255."""
    light = np.asarray(light, dtype=np.float64)
    d = normals @ light
    value = np.maximum(d, 0)
    if glossy:
        h = light + np.array([0.0, 0.0, 1.0])
        h /= np.linalg.norm(h)
        spec = np.where(d > 0, np.maximum(normals @ h, 0) ** shininess, 0)
        value = (1 - weight) * value + weight * spec
    return np.round(255 * np.minimum(value, 1))
