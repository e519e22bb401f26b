"""report.html in headless Chromium, opened from file:// with every host name made
unresolvable: dragging the light relights each cell as numpy's n.l says (read back from
the canvas), the glossy option adds Blinn-Phong, the three.js mesh draws, the console has
no error and the page asks for nothing beyond itself. The same in a notebook's iframe.
Skips, saying what is missing, without selenium, Chromium or chromedriver."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from cnnps.io.report import data as d
from cnnps.io.report import notebook_html, report_html, write_report
from cnnps.io.report.page import BACKGROUND, GLOSS, INITIAL_LIGHT
from tests.support.browser import browser_or_skip, console_errors, outside_requests
from tests.support.report import dome, page_data, relit, unpacked

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def browser():
    driver = browser_or_skip()
    yield driver
    driver.quit()


def wait_for(driver, script: str, timeout: float = 60.0):
    """The value of ``script`` once it is truthy (fails after ``timeout`` seconds)."""
    end = time.monotonic() + timeout
    while True:
        value = driver.execute_script(script)
        if value:
            return value
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for: {script}")
        time.sleep(0.1)


def open_page(driver, path):
    driver.get(path.as_uri())
    wait_for(driver, "return window.cnnpsReport && window.cnnpsReport.ready")
    return driver.execute_script("return window.cnnpsReport")


def canvas_pixels(driver, h: int, w: int) -> np.ndarray:
    flat = driver.execute_script(
        "const c = document.getElementById('relit-canvas');"
        "return Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data);")
    return np.asarray(flat, dtype=np.int64).reshape(h, w, 4)


def assert_relit(pixels: np.ndarray, cells: np.ndarray, light, glossy: bool = False):
    inside = cells[..., 3] == 255
    want = relit(d.decoded_normals(cells), light, glossy, GLOSS["weight"], GLOSS["shininess"])
    grey = pixels[..., :3]
    assert np.abs(grey[inside] - want[inside][:, None]).max() <= 1  # rounding half up vs half even
    assert (grey[~inside] == BACKGROUND).all() and (pixels[..., 3] == 255).all()
    return want


def assert_clean(driver):
    assert console_errors(driver) == []
    assert outside_requests(driver) == []


def drag(driver, element, dx: int, dy: int):
    """Press at the element's centre, move by (dx, dy) CSS pixels, release."""
    from selenium.webdriver.common.action_chains import ActionChains

    ActionChains(driver).move_to_element(element).click_and_hold().move_by_offset(dx, dy).release().perform()


def test_dragging_the_light_relights_as_n_dot_l(browser, tmp_path):
    from selenium.webdriver.common.by import By

    views = dome(90, 130)
    path = write_report(tmp_path, **views, max_side=48, mesh_side=32)
    data = page_data(path.read_text(encoding="utf-8"))["relit"]
    h, w = data["h"], data["w"]
    rows, cols = d.crop_box(views["mask"])
    assert (data["factor"], w, h) == (3, 43, 30)  # 127 x 90 pixels cropped, averaged over blocks of 3
    cells = d.page_normals(views["normals"][rows, cols], views["mask"][rows, cols], 48)[0]
    assert np.array_equal(unpacked(data["normals"], 4).reshape(h, w, 4), cells)
    hook = open_page(browser, path)
    assert hook["problems"] == [] and hook["light"] == pytest.approx(INITIAL_LIGHT)
    before = assert_relit(canvas_pixels(browser, h, w), cells, INITIAL_LIGHT)

    canvas = browser.find_element(By.ID, "relit-canvas")
    rect = browser.execute_script("const r = arguments[0].getBoundingClientRect(); return [r.width, r.height];", canvas)
    radius = min(rect) / 2
    dx, dy = round(0.5 * radius), round(0.3 * radius)  # to the lower right of the centre
    frames = hook["relitFrames"]
    drag(browser, canvas, dx, dy)
    light = wait_for(browser, f"const h = window.cnnpsReport; return h.relitFrames > {frames} && "
                              "JSON.stringify(h.renderedLight) === JSON.stringify(h.light) && h.light")
    u, v = dx / radius, -dy / radius
    assert light == pytest.approx([u, v, math.sqrt(1 - u * u - v * v)], abs=0.02)  # where the drag ended
    assert np.linalg.norm(light) == pytest.approx(1)
    after = assert_relit(canvas_pixels(browser, h, w), cells, light)
    assert np.abs(after - before)[cells[..., 3] == 255].max() > 100  # the light really moved
    assert browser.find_element(By.ID, "light-readout").text == "l = ({:.3f}, {:.3f}, {:.3f})".format(*light)

    frames = browser.execute_script("return window.cnnpsReport.relitFrames")
    browser.find_element(By.ID, "glossy").click()
    wait_for(browser, f"return window.cnnpsReport.glossy && window.cnnpsReport.relitFrames > {frames}")
    glossy = assert_relit(canvas_pixels(browser, h, w), cells, light, glossy=True)
    assert (glossy != after)[cells[..., 3] == 255].any()
    assert_clean(browser)


def full_blocks(xyz: np.ndarray) -> int:
    ok = ~np.isnan(xyz[..., 0])
    return int((ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1] & ok[1:, 1:]).sum())


def test_the_mesh_draws_and_follows_the_light(browser, tmp_path):
    views = dome(60, 80)
    path = write_report(tmp_path, **views)
    mesh = page_data(path.read_text(encoding="utf-8"))["mesh"]
    xyz = np.frombuffer(unpacked(mesh["positions"]).tobytes(), np.float32).reshape(mesh["h"], mesh["w"], 3)
    hook = open_page(browser, path)
    assert hook["problems"] == []
    assert hook["mesh"]["calls"] > 0 and hook["mesh"]["triangles"] == 2 * full_blocks(xyz) > 0
    drawn = browser.execute_script("""
        const c = document.getElementById('mesh-canvas');
        const t = document.createElement('canvas'); t.width = c.width; t.height = c.height;
        const g = t.getContext('2d'); g.drawImage(c, 0, 0);
        const p = g.getImageData(0, 0, t.width, t.height).data;
        let lit = 0, shades = new Set();
        for (let i = 0; i < p.length; i += 4) {
          if (Math.abs(p[i] - 0x20) + Math.abs(p[i + 1] - 0x23) + Math.abs(p[i + 2] - 0x29) > 12) lit++;
          shades.add(p[i]);
        }
        return [lit / (p.length / 4), shades.size];""")
    assert drawn[0] > 0.05 and drawn[1] > 20  # a shaded surface, not a blank or flat canvas
    frames = hook["mesh"]["frames"]
    browser.execute_script("window.cnnpsReport.setLight([0, 0, 1])")
    wait_for(browser, f"return window.cnnpsReport.mesh.frames > {frames}")
    assert_clean(browser)


def test_a_page_with_no_optional_view(browser, tmp_path):
    from selenium.webdriver.common.by import By

    views = dome(24, 30)
    path = tmp_path / "report.html"
    path.write_text(report_html(views["normals"], views["mask"], {"method": "lambertian"}), encoding="utf-8")
    hook = open_page(browser, path)
    assert hook["problems"] == [] and hook["mesh"] is None and hook["relitFrames"] >= 1
    notes = [e.text for e in browser.find_elements(By.CSS_SELECTOR, "p.absent")]
    assert [n.split(":")[0] for n in notes] == ["No confidence map", "No ground truth", "No surface"]
    assert_clean(browser)


def test_the_notebook_frame_draws_both_views(browser, tmp_path):
    from selenium.webdriver.common.by import By

    host = tmp_path / "notebook.html"
    host.write_text(f"<!doctype html><html><body>{notebook_html(**dome(40, 50))}</body></html>", encoding="utf-8")
    browser.get(host.as_uri())
    browser.switch_to.frame(browser.find_element(By.CSS_SELECTOR, "iframe.cnnps-report"))
    try:
        wait_for(browser, "return window.cnnpsReport && window.cnnpsReport.ready")
        hook = browser.execute_script("return window.cnnpsReport")
        assert hook["problems"] == [] and hook["relitFrames"] >= 1 and hook["mesh"]["calls"] > 0
        assert_clean(browser)
    finally:
        browser.switch_to.default_content()


def test_the_checks_catch_a_request_and_a_console_error(browser, tmp_path):
    """What the tests above rely on: a fetch beyond the file and a console error are seen."""
    views = dome(12, 16)
    page = report_html(views["normals"], views["mask"], {})
    bad = page.replace("</body>", '<img src="https://example.com/a.png"><script>console.error("boom")</script></body>')
    path = tmp_path / "bad.html"
    path.write_text(bad, encoding="utf-8")
    open_page(browser, path)
    assert any("boom" in e for e in console_errors(browser))
    assert "https://example.com/a.png" in outside_requests(browser)
