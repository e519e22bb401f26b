"""Learning curves of long runs side by side, as one SVG: the validation maps' mean error
and the dev-real mean (the real crops, ``tools/long_run.py curve``) against CPU-hours.

    .venv/bin/python tools/plot_curves.py v5-scratch=scratch v5-continue=continue \\
        --reference "v4=6.47" --out docs/images/v5_curves.svg

Each ``NAME[=LABEL]`` reads ``tools/runs/NAME/val.csv`` (``long_run.py save``) and
``tools/runs/NAME/real_curve.json`` (``long_run.py curve``); a run without one of them has
no line in that panel. ``--reference LABEL=DEG`` draws a dashed level in the dev-real panel
(e.g. the shipped model on the same pixel sample). Only numbers that were measured are
drawn; nothing is smoothed.
"""

from __future__ import annotations

import argparse
import json
from html import escape
from pathlib import Path

from cnnps.infra.atomic import write_text

CARRIED = Path(__file__).resolve().parents[1] / "tools" / "runs"
COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e")
W, H, PAD_L, PAD_R, PAD_T, PAD_B = 420, 300, 52, 14, 30, 42  # one panel, in SVG units


def read_run(folder: Path) -> dict:
    """{"val": [(cpu_hours, mean_deg)], "real": [(cpu_hours, dev_real_mean_deg)]} of a run."""
    out: dict = {"val": [], "real": []}
    val = folder / "val.csv"
    if val.is_file():
        rows = [ln.split(",") for ln in val.read_text().splitlines()[1:] if ln.strip()]
        out["val"] = [(float(r[1]), float(r[2])) for r in rows if r[1] not in ("", "None")]
    real = folder / "real_curve.json"
    if real.is_file():
        rows = json.loads(real.read_text())["rows"]
        out["real"] = [(r["cpu_hours"], r["dev_real_mean_deg"]) for r in rows
                       if r.get("cpu_hours") is not None and r.get("dev_real_mean_deg") is not None]
    return out


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    span = max(hi - lo, 1e-9)
    step = min((s * 10 ** e for e in range(-3, 4) for s in (1, 2, 5) if s * 10 ** e >= span / n), default=span)
    first = step * int(lo / step)
    return [first + i * step for i in range(n + 3) if lo - 1e-9 <= first + i * step <= hi + 1e-9]


def panel(series: list[tuple[str, str, list]], title: str, x0: float, refs: list[tuple[str, float]] = ()) -> str:
    """One chart at horizontal offset ``x0``: ``series`` [(label, colour, [(x, y)])]."""
    pts = [p for _, _, s in series for p in s]
    if not pts:
        return f'<text x="{x0 + W / 2}" y="{H / 2}" text-anchor="middle">{escape(title)}: no data yet</text>'
    ys = [y for _, y in pts] + [v for _, v in refs]
    xlo, xhi = 0.0, max(x for x, _ in pts) * 1.05
    ylo, yhi = min(ys), max(ys)
    ylo, yhi = ylo - 0.05 * (yhi - ylo + 1e-9), yhi + 0.05 * (yhi - ylo + 1e-9)

    def sx(x):
        return x0 + PAD_L + (x - xlo) / (xhi - xlo) * (W - PAD_L - PAD_R)

    def sy(y):
        return PAD_T + (yhi - y) / (yhi - ylo) * (H - PAD_T - PAD_B)

    out = [f'<text x="{x0 + W / 2}" y="18" text-anchor="middle" font-weight="bold">{escape(title)}</text>',
           f'<rect x="{sx(xlo):.1f}" y="{PAD_T}" width="{W - PAD_L - PAD_R}" height="{H - PAD_T - PAD_B}" '
           'fill="none" stroke="#999"/>']
    for t in _ticks(xlo, xhi):
        out.append(f'<text x="{sx(t):.1f}" y="{H - PAD_B + 14}" text-anchor="middle">{t:g}</text>')
    for t in _ticks(ylo, yhi):
        out.append(f'<line x1="{sx(xlo):.1f}" x2="{sx(xhi):.1f}" y1="{sy(t):.1f}" y2="{sy(t):.1f}" stroke="#eee"/>'
                   f'<text x="{sx(xlo) - 4:.1f}" y="{sy(t) + 4:.1f}" text-anchor="end">{t:g}</text>')
    out.append(f'<text x="{x0 + W / 2}" y="{H - 6}" text-anchor="middle">CPU-hours</text>')
    out.append(f'<text transform="translate({x0 + 12},{H / 2}) rotate(-90)" text-anchor="middle">mean error (°)</text>')
    for label, value in refs:
        out.append(f'<line x1="{sx(xlo):.1f}" x2="{sx(xhi):.1f}" y1="{sy(value):.1f}" y2="{sy(value):.1f}" '
                   f'stroke="#555" stroke-dasharray="5,4"/><text x="{sx(xhi) - 4:.1f}" y="{sy(value) - 4:.1f}" '
                   f'text-anchor="end" fill="#555">{escape(label)} {value:.2f}°</text>')
    for i, (label, colour, s) in enumerate(series):
        if not s:
            continue
        path = " ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y in s)
        out.append(f'<polyline points="{path}" fill="none" stroke="{colour}" stroke-width="1.8"/>')
        out += [f'<circle cx="{sx(x):.1f}" cy="{sy(y):.1f}" r="2.4" fill="{colour}"/>' for x, y in s]
        out.append(f'<text x="{sx(xhi) - 6:.1f}" y="{PAD_T + 16 + 15 * i}" text-anchor="end" fill="{colour}">'
                   f'{escape(label)}</text>')
    return "\n".join(out)


def plot(runs: list[tuple[str, dict]], refs: list[tuple[str, float]]) -> str:
    """The SVG text: validation (left) and dev-real (right) against CPU-hours."""
    series = [(label, COLOURS[i % len(COLOURS)], data) for i, (label, data) in enumerate(runs)]
    left = panel([(lb, c, d["val"]) for lb, c, d in series], "validation maps", 0)
    right = panel([(lb, c, d["real"]) for lb, c, d in series], "dev-real (four crops, pixel sample)", W, refs)
    return (f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {2 * W} {H}" width="{2 * W}" height="{H}" '
            f'font-family="sans-serif" font-size="11">\n<rect width="100%" height="100%" fill="white"/>\n'
            f"{left}\n{right}\n</svg>\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", metavar="NAME[=LABEL]")
    ap.add_argument("--reference", action="append", default=[], metavar="LABEL=DEG")
    ap.add_argument("--carried", type=Path, default=CARRIED)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    runs = []
    for spec in a.runs:
        name, _, label = spec.partition("=")
        folder = a.carried / name
        if not folder.is_dir():
            raise SystemExit(f"{folder}: no such run folder")
        runs.append((label or name, read_run(folder)))
    refs = []
    for spec in a.reference:
        label, _, value = spec.partition("=")
        try:
            refs.append((label, float(value)))
        except ValueError:
            raise SystemExit(f"--reference {spec!r}: expected LABEL=DEGREES") from None
    write_text(a.out, plot(runs, refs))
    print(f"-> {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
