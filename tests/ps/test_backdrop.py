"""A lit backdrop found in the photos (cnnps.ps.backdrop) and left out of the made mask
(cnnps.ps.mask_estimate), on scenes made here with NumPy: a Lambertian sphere resting on
a lit Lambertian table that casts its shadow on it, seen from above."""

import numpy as np
import pytest

from cnnps.ps.backdrop import MIN_BORDER_SHARE, find_backdrop, ring
from cnnps.ps.mask_estimate import estimate_mask, response

SIZE = 128


def lights(m=40, max_deg=60.0, seed=0):
    """(m, 3) unit directions within ``max_deg`` of the view (+z), seeded."""
    rng = np.random.default_rng(seed)
    theta = np.radians(max_deg) * np.sqrt(rng.uniform(0, 1, m))
    phi = rng.uniform(0, 2 * np.pi, m)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)


def grid():
    """Pixel centres' x (right) and y (up) in [-1, 1]; row 0 on top."""
    g = (np.arange(SIZE) + 0.5) / SIZE * 2 - 1
    return np.meshgrid(g, -g)


def on_a_table(L, centre=(-0.2, 0.1), radius=0.3, table=0.5, ball=0.7, lamp_distance=None, seed=0):
    """(m, H, W) images of a Lambertian sphere resting on a Lambertian table (z = 0) with
    the sphere's cast shadows and a little ambient light, each image scaled by a random
    exposure, noisy; and the sphere's disc. ``lamp_distance``: the table is lit by a lamp
    at that distance along each direction (its light falls off across the table) instead
    of a distant one."""
    X, Y = grid()
    dx, dy = X - centre[0], Y - centre[1]
    inside = dx**2 + dy**2 < radius**2
    n = np.stack([dx / radius, dy / radius, np.sqrt(np.clip(radius**2 - dx**2 - dy**2, 0, None)) / radius], -1)
    images = np.clip(np.einsum("hwc,mc->mhw", n, L), 0, None) * ball
    P = np.stack([dx, dy, -radius * np.ones_like(dx)], -1)  # a table point less the sphere's centre
    for j, l in enumerate(L):
        if lamp_distance is None:
            lit = np.full(X.shape, l[2])
        else:
            to_lamp = lamp_distance * l - np.stack([X, Y, np.zeros_like(X)], -1)
            d2 = (to_lamp**2).sum(-1)
            lit = to_lamp[..., 2] / np.sqrt(d2) * lamp_distance**2 / d2
        b = P @ l
        disc = b**2 - ((P**2).sum(-1) - radius**2)
        shadow = (disc > 0) & (-b + np.sqrt(np.maximum(disc, 0)) > 0)
        images[j][~inside] = (table * lit * ~shadow)[~inside]
    rng = np.random.default_rng(seed)
    images = (images + 0.02) * rng.uniform(0.5, 2.0, len(L))[:, None, None]
    return np.clip(images + rng.normal(0, 0.003, images.shape), 0, None), inside


def iou(a, b):
    return (a & b).sum() / (a | b).sum()


@pytest.mark.parametrize("lamp_distance", [None, 3.0])  # distant; 10 object radii away
def test_a_sphere_on_a_lit_table_is_its_disc_and_the_table_its_backdrop(lamp_distance):
    images, truth = on_a_table(lights(), lamp_distance=lamp_distance)
    found = find_backdrop(images, response(images))
    assert found.found and found.border_share == 1.0
    assert (found.mask & truth).sum() < 0.01 * truth.sum()  # (nearly) nothing of the object
    assert (found.mask | truth).mean() > 0.99  # the table, shadows included
    est = estimate_mask(images)
    assert iou(est.mask, truth) > 0.97 and est.backdrop == found.mask.sum()
    assert iou(estimate_mask(images, backdrop=False).mask, truth) < 0.6  # the table joins it otherwise
    strict = find_backdrop(images, response(images), tol=1e-6)  # a tolerance given holds in both passes
    assert strict.tol == 1e-6 and strict.mask.sum() < 0.1 * found.mask.sum()


def test_a_black_background_has_no_backdrop_and_the_mask_is_unchanged():
    images, truth = on_a_table(lights(), table=0.0)
    found = find_backdrop(images, response(images))
    assert not found.found and found.border_share < MIN_BORDER_SHARE and found.tol == 0.0
    est = estimate_mask(images)
    assert est.backdrop == 0 and np.array_equal(est.mask, estimate_mask(images, backdrop=False).mask)
    assert iou(est.mask, truth) > 0.97


def test_an_object_filling_the_frame_is_no_backdrop():
    # a sphere larger than the frame: the whole ring responds, but its pixels are not shaded alike
    images, _ = on_a_table(lights(), centre=(0.0, 0.0), radius=1.6)
    found = find_backdrop(images, response(images))
    assert found.border_share == 1.0 and not found.found


def test_a_face_turned_like_the_table_stays_when_the_objects_rim_parts_it_from_it():
    # a mesa: a flat top facing the camera (like the table) inside a sloped rim
    L = lights()
    X, Y = grid()
    r = np.hypot(X, Y)
    top, outer = r < 0.25, r < 0.45
    slope = np.stack([X / np.maximum(r, 1e-9), Y / np.maximum(r, 1e-9), np.ones_like(X)], -1) / np.sqrt(2)
    n = np.where(top[..., None], [0.0, 0.0, 1.0], np.where(outer[..., None], slope, [0.0, 0.0, 1.0]))
    albedo = np.where(outer, 0.7, 0.5)
    images = np.clip(np.einsum("hwc,mc->mhw", n, L), 0, None) * albedo + 0.01
    images *= np.random.default_rng(0).uniform(0.5, 2.0, len(L))[:, None, None]
    found = find_backdrop(images, response(images))
    assert found.found and not (found.mask & outer).any()
    assert iou(estimate_mask(images).mask, outer) > 0.97


def test_the_ring_is_the_frames_edge():
    edge = ring((6, 8), 2)
    assert edge.sum() == 6 * 8 - 2 * 4 and not edge[2:4, 2:6].any()

