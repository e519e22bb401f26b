"""Analytic Lambertian scenes and small capture folders written in every image format.

Used by tests/cnnps and tests/pipeline (import as ``tests.support.synthetic``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

ALBEDO_RGB = np.array([0.9, 0.6, 0.3])  # different per channel: catches RGB/BGR swaps


def sphere_normals(size: int = 32, radius: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) normals of a sphere seen from +z and its (H, W) mask; row 0 is +y."""
    c = (np.arange(size) + 0.5) / size * 2 - 1
    x = c[None, :].repeat(size, 0) / radius
    y = -c[:, None].repeat(size, 1) / radius  # image row 0 on top = +y
    r2 = x**2 + y**2
    mask = r2 < 1
    n = np.zeros((size, size, 3))
    n[..., 0], n[..., 1] = x, y
    n[..., 2] = np.sqrt(np.clip(1 - r2, 0, None))
    n[~mask] = 0
    return n, mask


def random_lights(m: int, seed: int = 0, max_tilt_deg: float = 60.0) -> np.ndarray:
    """m unit lights in the upper hemisphere, at most ``max_tilt_deg`` from +z."""
    rng = np.random.default_rng(seed)
    cos_max = np.cos(np.radians(max_tilt_deg))
    z = rng.uniform(cos_max, 1.0, m)
    phi = rng.uniform(0, 2 * np.pi, m)
    s = np.sqrt(1 - z**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def shading(normals: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """(m, H, W) max(0, n . l)."""
    return np.maximum(np.einsum("hwc,mc->mhw", normals, lights), 0.0)


def write_capture(
    root: Path,
    fmt: str = "exr",
    size: int = 32,
    m: int = 12,
    seed: int = 0,
    max_tilt_deg: float = 60.0,
    gt: str | None = "npy",
    intensities: np.ndarray | None = None,
) -> dict:
    """Write a sphere capture in ``fmt`` (exr | png8 | png16 | tiff16 | dng); return the truth.

    Pixel value of channel c under light j: ALBEDO_RGB[c] * E[j, c] * max(0, n . l_j),
    with per-light, per-channel intensities E (seeded) written to light_intensities.txt.
    For integer formats the images are multiplied by one factor ``scale`` so the
    brightest value is below 1; the loaded grey images are then ``scale`` times the truth.
    ``dng``: the RGGB mosaic of each image as a 16-bit DNG camera RAW file
    (:func:`tests.support.dng.write_dng`; demosaicing blurs the sphere's edge a little).
    """
    from cnnps.io.images import write_exr, write_png

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed + 1)
    normals, mask = sphere_normals(size)
    lights = random_lights(m, seed, max_tilt_deg)
    E = rng.uniform(0.5, 2.0, (m, 3)) if intensities is None else np.asarray(intensities, float)
    shade = shading(normals, lights)  # (m, H, W)
    rgb = shade[..., None] * (ALBEDO_RGB * E[:, None, None, :])  # (m, H, W, 3)
    scale = 1.0 if fmt == "exr" else 0.95 / rgb.max()
    rgb = rgb * scale
    ext = {"exr": "exr", "png8": "png", "png16": "png", "tiff16": "tif", "dng": "dng"}[fmt]
    names = [f"{j:03d}.{ext}" for j in range(m)]
    for name, img in zip(names, rgb):
        path = root / name
        if fmt == "exr":
            write_exr(path, img.astype(np.float32))
        elif fmt == "png8":
            write_png(path, np.round(img * 255).astype(np.uint8))
        elif fmt == "png16":
            write_png(path, np.round(img * 65535).astype(np.uint16))
        elif fmt == "tiff16":
            import tifffile

            tifffile.imwrite(path, np.round(img * 65535).astype(np.uint16), photometric="rgb")
        elif fmt == "dng":
            from tests.support.dng import mosaic, write_dng

            write_dng(path, mosaic(img))
        else:  # pragma: no cover
            raise ValueError(fmt)
    (root / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(root / "light_directions.txt", lights, fmt="%.9f")
    np.savetxt(root / "light_intensities.txt", E, fmt="%.9f")
    write_png(root / "mask.png", (mask * 255).astype(np.uint8))
    if gt == "npy":
        np.save(root / "normal_gt.npy", normals.astype(np.float32))
    elif gt == "mat":
        import scipy.io

        scipy.io.savemat(root / "Normal_gt.mat", {"Normal_gt": normals})
    return {
        "normals": normals,
        "mask": mask,
        "lights": lights,
        "intensities": E,
        "shading": shade,
        "scale": scale,
        "names": names,
        # expected grey images for grey="mean" (intensity divided out)
        "grey_mean": shade * ALBEDO_RGB.mean() * scale,
        "grey_luminance": shade * (ALBEDO_RGB @ np.array([0.2989, 0.5870, 0.1140])) * scale,
    }
