"""The report page: one self-contained HTML file (no request leaves it), from a
prediction's arrays and record.

Sections, in order (each an element with its id): ``relit`` (the normal map shaded by a
light the reader drags: max(0, n . l) per cell, optionally plus Blinn-Phong gloss, drawn
by the page's own script on a 2D canvas), ``confidence`` (the map, or a line saying
there is none), ``errors`` (with ground truth: the error map, its histogram and the
statistics; else a line), ``surface`` (with a depth map: the surface as a mesh to orbit,
drawn by three.js; else a line), ``record`` (the record: model, rotations, precision,
timings, notes, notices, warnings, and the whole of it as JSON).

The data the scripts read sits in ``<script type="application/json" id="report-data">``
(maps deflated and base64-encoded, :mod:`cnnps.io.report.data`); three.js
(:mod:`cnnps.io.report.three_vendor`) is inlined, gzip-compressed and base64-encoded,
only when there is a surface, and loaded from blob: URLs made in the page. The page's
script sets ``window.cnnpsReport``: ``ready`` (true once every view is drawn), ``light``
(the unit light vector of the relit view), ``glossy``, ``relitFrames``, ``renderedLight``
(the light of the last relit frame), ``mesh`` (three.js's ``renderer.info.render``
``calls`` and ``triangles`` of the last frame, ``frames``) and ``problems`` (views that
could not be drawn, one line each).
"""

from __future__ import annotations

import base64
import functools
import gzip
import html
import json
from pathlib import Path

import numpy as np

from cnnps.io.report import data as d
from cnnps.io.report.three_vendor import manifest, three_sources

ASSETS = Path(__file__).resolve().parent / "assets"
INITIAL_LIGHT = (-1 / 6**0.5, 1 / 6**0.5, 2 / 6**0.5)  # upper left, in front
GLOSS = {"weight": 0.35, "shininess": 40}  # glossy: (1 - weight) max(0, n.l) + weight max(0, n.h)^shininess
BACKGROUND = (38, 40, 46)  # relit cells off the mask
RECORD_ROWS = (("capture", "capture"), ("method", "method"), ("model", "model"), ("rotations", "rotations (K)"),
               ("precision", "precision"), ("n_images", "images"), ("image_size", "image size (H, W)"),
               ("pixels", "mask pixels"), ("linearize", "linearize"), ("saturated_observations", "saturated observations"),
               ("seconds", "seconds (total)"), ("load_seconds", "seconds reading images"))
STAT_ROWS = (("mean_deg", "mean", "{:.3f} deg"), ("median_deg", "median", "{:.3f} deg"),
             ("rmse_deg", "RMSE", "{:.3f} deg"), ("p90_deg", "90th percentile", "{:.3f} deg"),
             ("max_deg", "max", "{:.3f} deg"), ("under_5_deg", "under 5 deg", "{:.1%}"),
             ("under_10_deg", "under 10 deg", "{:.1%}"), ("under_20_deg", "under 20 deg", "{:.1%}"),
             ("pixels", "pixels scored", "{:,}"))


def _e(value) -> str:
    return html.escape(str(value), quote=True)


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def script_json(obj) -> str:
    """``obj`` as JSON that is safe inside a ``<script>`` element (no ``<`` in it)."""
    return json.dumps(obj, default=_json_default, separators=(",", ":")).replace("<", "\\u003c")


@functools.lru_cache(maxsize=1)
def three_payload() -> dict:
    """three.js's files for the page: each gzip-compressed and base64-encoded, the version,
    and the licence text."""
    src = three_sources()
    packed = {name: base64.b64encode(gzip.compress(src[name].encode("utf-8"), 6, mtime=0)).decode("ascii")
              for name in ("three.core.js", "three.module.js", "OrbitControls.js")}
    return {"version": src["version"], "license": src["LICENSE"], **packed}


def _note(text: str) -> str:
    return f'<p class="absent">{_e(text)}</p>'


def relit_section(normals, mask, max_side: int, box: str) -> tuple[str, dict]:
    cells, inside, f = d.page_normals(normals, mask, max_side)
    h, w = inside.shape
    shown = box + ("" if f == 1 else f" Shown at 1/{f} ({w} x {h} cells, each the mean of {f} x {f} pixels).")
    body = f"""
<p>Drag on the picture (or on the ball) to move the light; each pixel shows max(0, n &middot; l), the
light l pointing from the surface, x right, y up, z toward the camera.{_e(shown)}</p>
<div class="row">
  <canvas id="relit-canvas" width="{w}" height="{h}" style="max-width:{max(w, 512)}px"></canvas>
  <div class="controls">
    <canvas id="light-ball" width="160" height="160" title="drag to move the light"></canvas>
    <label><input type="checkbox" id="glossy"> glossy (Blinn-Phong)</label>
    <label>shininess <input type="range" id="shininess" min="2" max="200" value="{GLOSS['shininess']}"></label>
    <output id="light-readout"></output>
  </div>
</div>"""
    payload = {"w": w, "h": h, "factor": f, "normals": d.packed(cells, delta=4), "light": INITIAL_LIGHT,
               "gloss": GLOSS, "background": BACKGROUND}
    return _section("relit", "Normals, relit", body), payload


def confidence_section(confidence, mask, record: dict, max_side: int) -> str:
    if confidence is None:
        return _section("confidence", "Confidence", _note(
            "No confidence map: this method gives none (the network with one rotation has no spread to measure)."))
    mask = np.asarray(mask, dtype=bool)
    f = d.block_factor(mask.shape, max_side)
    mean, share = d.block_mean(np.where(mask, confidence, 0).astype(np.float32), mask, f)
    picture = d.png_url(d.colour_map(mean, share >= 0.5, "VIRIDIS"))
    about = record.get("confidence") or {}
    lines = "".join(f"<li>{_e(k)}: {_e(v)}</li>" for k, v in about.items())
    body = f"""
<p>How far each normal can be trusted: 1 the most (bright), 0 the least (dark). Rank it, don't read it as degrees.</p>
<div class="row"><figure><img class="map" alt="confidence map" src="{picture}">
{_bar("VIRIDIS", "0", "0.5", "1 trusted")}</figure><ul class="facts">{lines}</ul></div>"""
    return _section("confidence", "Confidence", body)


def _bar(cmap: str, low: str, mid: str, high: str) -> str:
    return (f'<figcaption class="bar"><img alt="" src="{d.colour_bar(cmap)}"><span>{_e(low)}</span>'
            f'<span>{_e(mid)}</span><span>{_e(high)}</span></figcaption>')


def _histogram_svg(counts: np.ndarray, top: float) -> str:
    width, height, pad = 480, 180, 28
    peak = max(int(counts.max()), 1)
    bw = (width - 2 * pad) / len(counts)
    bars = "".join(
        f'<rect x="{pad + i * bw:.1f}" y="{height - pad - c / peak * (height - 2 * pad):.1f}" width="{bw * 0.9:.1f}" '
        f'height="{c / peak * (height - 2 * pad):.1f}"><title>{i * top / len(counts):g}-{(i + 1) * top / len(counts):g}'
        f' deg: {int(c)} pixels</title></rect>' for i, c in enumerate(counts))
    ticks = "".join(f'<text x="{pad + t * (width - 2 * pad):.1f}" y="{height - 8}">{top * t:g}{" deg" if t == 1 else ""}'
                    '</text>' for t in (0, 0.25, 0.5, 0.75, 1))
    return (f'<svg id="error-histogram" class="histogram" viewBox="0 0 {width} {height}" role="img" '
            f'aria-label="histogram of the angular errors">{bars}{ticks}'
            f'<text x="{width - pad}" y="14" class="end">{peak} pixels</text></svg>')


def errors_section(errors, scored, stats, picture_url: str | None, max_side: int) -> str:
    if stats is None:
        from cnnps.io.capture import GROUND_TRUTH_FILES

        return _section("errors", "Errors against ground truth", _note(
            f"No ground truth: the capture has none ({' or '.join(GROUND_TRUTH_FILES)}), so there is no error map."))
    rows = "".join(f"<tr><th>{label}</th><td>{_e(fmt.format(stats[k]))}</td></tr>"
                   for k, label, fmt in STAT_ROWS if stats.get(k) is not None)
    if errors is None:  # a folder whose capture is gone: the picture it holds, no histogram
        figure = f'<figure><img class="map" alt="error map" src="{picture_url}"></figure>' if picture_url else ""
        body = (f'<div class="row">{figure}<table class="stats">{rows}</table></div>'
                + _note("No histogram: the per-pixel errors are not kept in the output folder and the capture's "
                        "ground truth was not found."))
        return _section("errors", "Errors against ground truth", body)
    scored = np.asarray(scored, dtype=bool)
    f = d.block_factor(scored.shape, max_side)
    mean, share = d.block_mean(np.where(scored, errors, 0), scored, f)
    top = d.nice_ceiling(float(np.percentile(mean[share > 0], 99))) if (share > 0).any() else 1.0
    picture = d.png_url(d.colour_map(mean / top, share >= 0.5, "JET"))
    counts = d.error_histogram(errors, scored, top)
    body = f"""
<p>Angular error of each normal against the ground truth, in degrees (cells: the mean of their scored pixels).</p>
<div class="row"><figure><img class="map" alt="error map" src="{picture}">
{_bar("JET", "0", f"{top / 2:g}", f"{top:g} deg")}</figure>
<figure>{_histogram_svg(counts, top)}<figcaption>errors of all {int(scored.sum()):,} scored pixels; the last bar
holds {top:g} deg and above</figcaption></figure>
<table class="stats">{rows}</table></div>"""
    return _section("errors", "Errors against ground truth", body)


def surface_section(depth, mask, record: dict, mesh_side: int, origin, image_shape) -> tuple[str, dict | None]:
    if depth is None:
        return _section("surface", "Surface", _note(
            "No surface: run cnnps predict with --depth to integrate the normals into one.")), None
    camera = record.get("camera") or {}
    xyz, f = d.mesh_grid(depth, mask, camera.get("intrinsics"), mesh_side, origin, image_shape)
    info = record.get("depth") or {}
    facts = "".join(f"<li>{_e(k)}: {_e(info[k])}</li>" for k in ("method", "components", "residual_rms",
                                                                 "vertices", "faces") if k in info)
    body = f"""
<p>The surface the normals integrate to (depth.npy; {xyz.shape[1]} x {xyz.shape[0]} vertices, a block of {f} x {f}
pixels each). Drag to orbit, scroll to zoom; the light is the relit view's.</p>
<div class="row"><canvas id="mesh-canvas"></canvas><ul class="facts">{facts}</ul></div>"""
    payload = {"w": xyz.shape[1], "h": xyz.shape[0], "positions": d.packed(xyz)}
    return _section("surface", "Surface", body), payload


def record_section(record: dict) -> str:
    rows = [(label, record[k]) for k, label in RECORD_ROWS if record.get(k) is not None]
    choice = record.get("precision_choice") or {}
    if choice.get("reason"):
        rows.append(("precision chosen", choice["reason"]))
    for key, label in (("camera", "camera"), ("lights", "lights")):
        if isinstance(record.get(key), dict) and record[key].get("model"):
            rows.append((label, record[key]["model"]))
    fill = record.get("sparse_fill")
    if isinstance(fill, dict):
        rows.append(("sparse fill", ", ".join(f"{k} {v}" for k, v in fill.items())))
    table = "".join(f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in rows)
    lists = ""
    for key in ("warnings", "notices", "notes"):
        items = record.get(key) or []
        lists += (f'<h3>{key}</h3><ul class="{key}">' + "".join(f"<li>{_e(t)}</li>" for t in items) + "</ul>"
                  if items else f'<h3>{key}</h3><p class="none">none</p>')
    whole = html.escape(json.dumps(record, indent=2, default=_json_default))
    body = (f'<table class="record">{table}</table>{lists}'
            f"<details><summary>the whole record (prediction.json)</summary><pre>{whole}</pre></details>")
    return _section("record", "Record", body)


def _section(key: str, title: str, body: str) -> str:
    return f'<section id="{key}"><h2>{_e(title)}</h2>{body}\n</section>\n'


def _asset(name: str) -> str:
    return (ASSETS / name).read_text(encoding="utf-8")


def page_html(normals, mask, record: dict, *, confidence=None, errors=None, scored=None, stats=None,
              depth=None, error_picture_url: str | None = None, max_side: int = d.RELIT_SIDE,
              mesh_side: int = d.MESH_SIDE) -> str:
    """The whole page (module docstring). ``normals`` (H, W, 3), zeros off ``mask`` (H, W);
    ``record``: the prediction's record; ``confidence`` (H, W) or None; ``errors`` (H, W)
    degrees on the ``scored`` pixels (default: the mask) with ``stats`` (``mean_deg``,
    ...), or ``stats`` alone with ``error_picture_url`` (a picture of them); ``depth``
    (H, W), NaN where there is no surface, or None. ``max_side``: the maps' longest side
    on the page; ``mesh_side``: the mesh's."""
    mask = np.asarray(mask, dtype=bool)
    scored = mask if scored is None else np.asarray(scored, dtype=bool)
    shape = mask.shape
    rows, cols = d.crop_box(mask | scored)
    box = "" if (rows.stop - rows.start, cols.stop - cols.start) == shape else (
        f" Cropped to the object: rows {rows.start}-{rows.stop - 1}, columns {cols.start}-{cols.stop - 1} of "
        f"{shape[1]} x {shape[0]}.")
    crop = [None if a is None else np.asarray(a)[rows, cols] for a in (normals, mask, confidence, errors, scored, depth)]
    normals, mask, confidence, errors, scored, depth = crop
    relit, relit_data = relit_section(normals, mask, max_side, box)
    relit_data["origin"] = [rows.start, cols.start]  # the top-left pixel of the crop
    surface, mesh_data = surface_section(depth, mask, record, mesh_side, (rows.start, cols.start), shape)
    sections = (relit + confidence_section(confidence, mask, record, max_side)
                + errors_section(errors, scored, stats, error_picture_url, max_side)
                + surface + record_section(record))
    three = three_payload() if mesh_data is not None else None
    scripts = f'<script type="application/json" id="report-data">{script_json({"relit": relit_data, "mesh": mesh_data})}</script>\n'
    if three is not None:
        scripts += "".join(f'<script type="text/plain" id="{key}">{three[name]}</script>\n'
                           for key, name in (("three-core", "three.core.js"), ("three-module", "three.module.js"),
                                             ("three-orbit", "OrbitControls.js")))
    return _frame(record, shape, sections, scripts, three)


def _frame(record: dict, shape, sections: str, scripts: str, three: dict | None) -> str:
    name = Path(str(record.get("capture") or "prediction")).name
    method = record.get("method", "?")
    how = f"{method}, K={record['rotations']}" if record.get("rotations") else str(method)
    warnings = record.get("warnings") or []
    banner = ("".join(f'<p class="warning">warning: {_e(w)}</p>' for w in warnings)) if warnings else ""
    version = manifest()["version"]  # three.js itself is read only for a page with a surface
    licence = (f"<details><summary>three.js {_e(version)} is inlined in this page for the surface view; its MIT "
               f"licence</summary><pre>{_e(three['license'])}</pre></details>") if three else ""
    nav = "".join(f'<a href="#{k}">{t}</a>' for k, t in (("relit", "relit"), ("confidence", "confidence"),
                                                         ("errors", "errors"), ("surface", "surface"),
                                                         ("record", "record")))
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta name="generator" content="cnnps report; three.js {_e(version)}">
<title>cnnps: {_e(name)}</title>
<style>{_asset("report.css")}</style></head>
<body>
<header><h1>{_e(name)}</h1>
<p class="sub">{_e(how)} &middot; {shape[1]} x {shape[0]} pixels &middot; {_e(record.get("n_images", "?"))} images
&middot; {_e(record.get("seconds", "?"))} s</p>{banner}<nav>{nav}</nav></header>
<main>
{sections}</main>
<footer><p>Written by cnnps; opens from disk, nothing is fetched.</p>{licence}</footer>
{scripts}<script type="module">{_asset("report.js")}</script>
</body></html>
"""
