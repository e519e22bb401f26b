"""report.html's contents (cnnps.io.report): the sections, the maps averaged over blocks,
nothing fetched from outside the file, the size and write time at 12 MP, the vendored
three.js checked against its pins. The page in a real browser: test_report_browser.py."""

from __future__ import annotations

import base64
import gzip
import hashlib
import io
import json
import re
import shutil
import tarfile
import time

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError, InputError
from cnnps.io.report import REPORT_FILE, notebook_html, report_html, write_report
from cnnps.io.report import data as d
from cnnps.io.report import three_vendor as tv
from tests.support.report import dome, page_data, unpacked

SECTIONS = ("relit", "confidence", "errors", "surface", "record")


def _section(page: str, key: str) -> str:
    found = re.search(rf'<section id="{key}">(.*?)</section>', page, re.S)
    assert found, f"no section {key}"
    return found.group(1)


def test_every_section_with_every_view():
    views = dome(30, 40)
    page = report_html(**views)
    assert page.startswith("<!doctype html>") and page.rstrip().endswith("</html>")
    assert [m for m in re.findall(r'<section id="(\w+)">', page)] == list(SECTIONS)
    assert 'class="absent"' not in page  # every view present: no "there is none" line
    assert 'id="relit-canvas" width="40" height="30"' in page and 'id="mesh-canvas"' in page
    assert "confidence map" in _section(page, "confidence") and "a measure" in _section(page, "confidence")
    errors = _section(page, "errors")
    assert 'id="error-histogram"' in errors and "mean" in errors and f"{views['stats']['mean_deg']:.3f} deg" in errors
    record = _section(page, "record")
    for text in ("cnn", "weights.pt", "fp32", "asked for", "12.5", "1.25", "orthographic"):
        assert f"<td>{text}</td>" in record, text
    # record text is escaped, never markup
    assert "a note &lt;b&gt;with markup&lt;/b&gt;" in record and "<b>with" not in page
    assert "a warning &amp; more" in page.split("<main>")[0]  # the warning is in the header too
    assert json.loads(re.search(r"<pre>(.*?)</pre>", record, re.S).group(1).replace("&quot;", '"')
                      .replace("&lt;", "<").replace("&gt;", ">").replace("&amp;", "&")) == views["record"]
    version = tv.manifest()["version"]
    assert f'content="cnnps report; three.js {version}"' in page and f"three.js {version}" in page
    data = page_data(page)
    assert (data["relit"]["w"], data["relit"]["h"], data["relit"]["factor"]) == (40, 30, 1)
    assert (data["mesh"]["w"], data["mesh"]["h"]) == (40, 30)
    assert data["relit"]["light"] == pytest.approx([-6**-0.5, 6**-0.5, 2 * 6**-0.5])


def test_absent_views_say_so_and_leave_three_out():
    views = dome(20, 24)
    page = report_html(views["normals"], views["mask"], {"method": "lambertian"})
    assert "No confidence map" in _section(page, "confidence")
    assert "No ground truth" in _section(page, "errors")
    assert "No surface" in _section(page, "surface") and "--depth" in _section(page, "surface")
    assert 'id="three-core"' not in page and page_data(page)["mesh"] is None
    assert len(page.encode()) < 100_000
    with_three = report_html(views["normals"], views["mask"], {}, depth=views["depth"])
    for key in ("three-core", "three-module", "three-orbit"):
        assert f'<script type="text/plain" id="{key}">' in with_three


def test_the_page_inlines_three_js_byte_for_byte():
    page = report_html(**dome(12, 16))
    sources = tv.three_sources()
    for key, name in (("three-core", "three.core.js"), ("three-module", "three.module.js"),
                      ("three-orbit", "OrbitControls.js")):
        text = re.search(rf'<script type="text/plain" id="{key}">(.*?)</script>', page, re.S).group(1)
        assert gzip.decompress(base64.b64decode(text)).decode() == sources[name]
    assert "Permission is hereby granted" in page  # its MIT licence travels with it


TAG = re.compile(r"<(\w+)\b([^>]*)>", re.S)
URL_ATTR = re.compile(r"""\b(src|href|srcset|poster|action|data|xlink:href)\s*=\s*["']?\s*([^"'\s>]*)""", re.I)


def test_nothing_in_the_page_points_outside_it():
    page = report_html(**dome(30, 40))
    tags = TAG.findall(page)
    attrs = [(name.lower(), value) for _, body in tags for name, value in URL_ATTR.findall(body)]
    assert attrs, "the page has no src/href at all?"
    assert all(v.startswith("data:") for n, v in attrs if n == "src"), attrs
    assert all(v.startswith("#") for n, v in attrs if n == "href"), attrs
    assert not [t for t, body in tags if t.lower() in ("link", "iframe", "object", "embed", "base")]
    assert not [body for t, body in tags if t.lower() == "script" and "src" in body.lower()]
    assert not re.search(r"https?://", "".join(body for _, body in tags)), "a URL inside a tag"
    assert not re.search(r"url\(\s*['\"]?(https?:)?//", page), "a URL in the style"
    assert "import(" not in page.replace("await import(main)", "").replace("await import(orbit)", "")


def _block_reference(normals, mask, f):
    """Each f x f block's mean normal (cut-short edges), made unit, and its mask share."""
    H, W = mask.shape
    h, w = -(-H // f), -(-W // f)
    out, share = np.zeros((h, w, 3)), np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            block = normals[i * f:(i + 1) * f, j * f:(j + 1) * f].reshape(-1, 3).astype(np.float64)
            s = block.sum(axis=0)
            out[i, j] = s / (np.linalg.norm(s) or 1)
            share[i, j] = mask[i * f:(i + 1) * f, j * f:(j + 1) * f].mean()
    return out, share


def test_large_maps_are_averaged_over_blocks():
    views = dome(103, 151)  # cropped to 103 x 149, then blocks of 4: 38 x 26 cells, both edges cut short
    rows, cols = d.crop_box(views["mask"])
    assert (rows, cols) == (slice(0, 103), slice(1, 150))
    page = report_html(**views, max_side=40, mesh_side=20)
    data = page_data(page)
    relit = data["relit"]
    assert (relit["factor"], relit["w"], relit["h"], relit["origin"]) == (4, 38, 26, [0, 1])
    cells = unpacked(relit["normals"], delta=4).reshape(26, 38, 4)
    ref, share = _block_reference(views["normals"][rows, cols], views["mask"][rows, cols], 4)
    inside = cells[..., 3] == 255
    assert np.array_equal(inside, (share >= 0.5) & (np.linalg.norm(ref, axis=2) > 0))
    assert np.array_equal(cells, d.page_normals(views["normals"][rows, cols], views["mask"][rows, cols], 40)[0])
    decoded = d.decoded_normals(cells)
    assert np.degrees(np.arccos(np.clip((decoded * ref).sum(-1)[inside], -1, 1))).max() < 0.7  # 8-bit steps
    assert "Cropped to the object: rows 0-102, columns 1-149 of 151 x 103" in page
    assert "Shown at 1/4 (38 x 26 cells" in page
    mesh = data["mesh"]
    assert (mesh["w"], mesh["h"]) == (19, 13)  # 149 / 20 -> blocks of 8
    xyz = np.frombuffer(unpacked(mesh["positions"]).tobytes(), np.float32).reshape(13, 19, 3)
    block = views["depth"][48:56, 73:81]  # cell (6, 9), inside the dome: its centre pixel (51.5, 76.5)
    assert np.isfinite(block).all()
    assert xyz[6, 9] == pytest.approx([76.5 - 75, 51 - 51.5, block.mean()], rel=1e-5)  # the image's frame
    last = views["depth"][96:, 145:150]  # cell (12, 18), cut short to 7 x 5: off the dome
    assert np.isnan(last).all() and np.isnan(xyz[12, 18]).all()
    assert 'src="data:image/png;base64,' in _section(page, "confidence")


def test_a_small_object_is_cropped_with_a_margin():
    views = dome(20, 24)
    normals = np.zeros((200, 300, 3), np.float32)
    mask = np.zeros((200, 300), bool)
    normals[50:70, 180:204], mask[50:70, 180:204] = views["normals"], views["mask"]
    rows, cols = d.crop_box(mask)
    on = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    assert (rows.start, rows.stop) == (on[0][0] - 9, on[0][-1] + 10)  # 3 % of 300 = 9 pixels each side
    assert (cols.start, cols.stop) == (on[1][0] - 9, on[1][-1] + 10)
    page = report_html(normals, mask, {})
    relit = page_data(page)["relit"]
    assert (relit["h"], relit["w"], relit["factor"]) == (rows.stop - rows.start, cols.stop - cols.start, 1)
    assert relit["origin"] == [rows.start, cols.start]
    assert d.crop_box(np.zeros((5, 6), bool)) == (slice(0, 5), slice(0, 6))
    edge = np.zeros((50, 50), bool)
    edge[0, 49] = True
    assert d.crop_box(edge) == (slice(0, 3), slice(47, 50))


def test_block_sums_match_a_loop_for_uneven_sizes():
    rng = np.random.default_rng(1)
    for H, W, f in ((7, 5, 3), (9, 9, 3), (10, 3, 4), (1, 8, 2)):
        a = rng.normal(size=(H, W, 2)).astype(np.float32)
        ref = np.array([[a[i:i + f, j:j + f].sum(axis=(0, 1)) for j in range(0, W, f)] for i in range(0, H, f)])
        assert np.allclose(d.block_sum(a, f), ref, atol=1e-5)
        assert np.array_equal(d.block_counts((H, W), f),
                              [[min(f, H - i) * min(f, W - j) for j in range(0, W, f)] for i in range(0, H, f)])


def test_error_histogram_counts_every_scored_pixel():
    errors = np.array([[0.1, 2.4, 9.99, 10.0], [55.0, 0.0, 3.0, 7.0]])
    scored = np.array([[True, True, True, True], [True, False, True, True]])
    counts = d.error_histogram(errors, scored, top=10.0, bins=4)
    assert counts.tolist() == [2, 1, 1, 3] and counts.sum() == scored.sum()


def test_write_report_and_notebook_html(tmp_path):
    views = dome(16, 20)
    path = write_report(tmp_path, **views)
    assert path == tmp_path / REPORT_FILE and path.read_text(encoding="utf-8") == report_html(**views)
    frame = notebook_html(**views)
    assert frame.startswith('<iframe class="cnnps-report" srcdoc="') and "<script" not in frame
    import html

    inner = html.unescape(re.search(r'srcdoc="(.*?)"', frame, re.S).group(1))
    assert inner == report_html(**views, max_side=512, mesh_side=160)


@pytest.mark.slow
def test_a_12_megapixel_page_is_small_and_quick(tmp_path):
    views = dome(3000, 4000)
    views["mask"][:] = True  # the whole frame: no crop, the most cells
    views["normals"][views["normals"][..., 2] == 0] = (0, 0, 1)
    write_report(tmp_path, **dome(8, 8))  # once a process: imports, three.js (cold: docs/performance.md)
    t0 = time.process_time()
    path = write_report(tmp_path, **views)
    cpu = time.process_time() - t0
    size = path.stat().st_size
    assert size < 20e6, f"{size / 1e6:.1f} MB"
    assert cpu < 2.0, f"{cpu:.2f} s of CPU"  # wall time is in docs/performance.md
    data = page_data(path.read_text(encoding="utf-8"))
    assert (data["relit"]["w"], data["relit"]["h"], data["relit"]["factor"]) == (1000, 750, 4)
    assert (data["mesh"]["w"], data["mesh"]["h"]) == (250, 188)


# ----------------------------------------------------------------------------- three.js


def test_the_vendored_files_are_the_pinned_release():
    info = tv.manifest()
    assert info["package"] == "three" and re.fullmatch(r"\d+\.\d+\.\d+", info["version"])
    assert info["integrity"].startswith("sha512-") and info["license"] == "MIT"
    for name, entry in info["files"].items():
        data = (tv.VENDOR_DIR / name).read_bytes()
        assert hashlib.sha256(data).hexdigest() == entry["sha256"] and len(data) == entry["bytes"], name
    assert set(info["files"]) == set(tv.FILES)
    assert "MIT License" in (tv.VENDOR_DIR / "LICENSE").read_text()
    assert "'./three.core.js'" in tv.three_sources()["three.module.js"]  # what the page rewrites
    assert "from 'three'" in tv.three_sources()["OrbitControls.js"]


def test_a_changed_vendored_file_is_refused(tmp_path):
    folder = tmp_path / "three"
    shutil.copytree(tv.VENDOR_DIR, folder)
    with open(folder / "three.module.js", "ab") as f:
        f.write(b"\n// changed\n")
    with pytest.raises(InputError, match="three.module.js.*differs from three.js"):
        tv.three_sources(folder)


def _tarball(path, files: dict[str, bytes]):
    with tarfile.open(path, "w:gz") as tar:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))


def test_unpack_checks_the_tarball_against_npm_integrity(tmp_path):
    tarball = tmp_path / "three-9.9.9.tgz"
    _tarball(tarball, {member: f"// {name}\n".encode() for name, member in tv.FILES.items()})
    integrity = tv.sri_sha512(tarball.read_bytes())
    with pytest.raises(ConfigError, match="is not the registry's dist.integrity"):
        tv.unpack(tarball, "sha512-" + base64.b64encode(b"x" * 64).decode(), tmp_path / "bad")
    assert not (tmp_path / "bad").exists()
    info = tv.unpack(tarball, integrity, tmp_path / "out")
    assert info["version"] == "9.9.9" and info["integrity"] == integrity
    assert tv.three_sources(tmp_path / "out")["three.core.js"] == "// three.core.js\n"


@pytest.mark.slow
def test_the_vendored_files_match_the_registry(tmp_path):
    """The pinned release fetched again from npm: its integrity is the registry's and
    its files are the vendored ones (skips without npm or the registry)."""
    import subprocess

    if shutil.which("npm") is None:
        pytest.skip("npm not installed")
    version = tv.manifest()["version"]
    try:
        tv._npm("view", f"three@{version}", "dist.integrity")
    except (ConfigError, subprocess.TimeoutExpired) as exc:
        pytest.skip(f"npm registry not reachable: {exc}")
    info = tv.vendor_three(version, tmp_path / "three")
    assert info == tv.manifest()
    for name in tv.FILES:
        assert (tmp_path / "three" / name).read_bytes() == (tv.VENDOR_DIR / name).read_bytes()
