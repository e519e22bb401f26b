"""`cnnps.predict`'s result shows the report page in a notebook (`_repr_html_`)."""

from __future__ import annotations

import html
import re

import numpy as np

import cnnps
from tests.support.report import page_data
from tests.support.synthetic import random_lights, shading, sphere_normals


def test_a_prediction_shows_the_report_in_a_notebook():
    normals, mask = sphere_normals(24)
    lights = random_lights(12, seed=3, max_tilt_deg=45)
    images = shading(normals, lights).astype(np.float32)
    result = cnnps.predict(images, lights, mask, normal_gt=normals, method="lambertian")
    frame = result._repr_html_()
    assert frame.startswith('<iframe class="cnnps-report" srcdoc="') and frame.endswith("</iframe>")
    page = html.unescape(re.search(r'srcdoc="(.*?)"', frame, re.S).group(1))
    assert re.findall(r'<section id="(\w+)">', page) == ["relit", "confidence", "errors", "surface", "record"]
    assert "confidence map" in page and 'id="error-histogram"' in page  # least squares measures its confidence
    assert "No surface" in page  # distant lights: no depth in memory
    assert f"{result.stats['mean_deg']:.3f} deg" in page
    assert (page_data(page)["relit"]["w"], page_data(page)["relit"]["h"]) == (24, 24)
