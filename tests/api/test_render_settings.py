"""One set of render settings: :func:`cnnps.render`, ``cnnps render`` and the render stage
share the names and defaults of :class:`cnnps.synth.render.settings.RenderSettings` (and
:class:`~cnnps.synth.render.settings.CaptureSettings`, which adds the scene's material,
camera and lights). No Blender needed."""

from __future__ import annotations

import dataclasses
import inspect

import pytest


def _defaults(cls) -> dict:
    return {f.name: f.default for f in dataclasses.fields(cls)}


def test_the_shared_defaults():
    from cnnps.synth.render.settings import CaptureSettings

    assert _defaults(CaptureSettings) == {
        "size": 128, "samples": 32, "lights": 40, "jitter_deg": 0.0, "min_elevation_deg": 5.0,
        "light_intensity": 1.0, "max_bounces": 8, "device": "cpu", "seed": 0, "threads": 0,
        "material": "lambertian", "superpixels": 100, "fov_deg": None, "light_distance": None, "environment": 0.0,
    }


def test_the_api_keywords_are_the_capture_settings_with_their_defaults():
    import cnnps
    from cnnps.synth.render.settings import CaptureSettings

    params = inspect.signature(cnnps.render).parameters
    api = {n: p.default for n, p in params.items() if p.kind is p.KEYWORD_ONLY and n != "progress"}
    assert api == _defaults(CaptureSettings)


def test_the_cli_options_are_the_same_names_flags_and_defaults():
    import typer.main

    import cnnps.pipeline.cli  # noqa: F401 (registers every command)
    from cnnps.pipeline import cli_render
    from cnnps.pipeline.app import app
    from cnnps.synth.render.settings import CaptureSettings

    fields = _defaults(CaptureSettings)
    params = inspect.signature(cli_render.render).parameters
    assert {n: p.default.default for n, p in params.items() if n not in ("mesh", "out", "progress")} == fields
    command = typer.main.get_command(app).commands["render"]
    flags = {p.name: p.opts for p in command.params}
    for name in fields:
        assert flags[name] == ["--" + name.replace("_", "-")], name  # jitter_deg -> --jitter-deg


def test_the_render_stage_extends_the_same_settings():
    from cnnps.stages.render import Params
    from cnnps.synth.render.settings import CaptureSettings, RenderSettings

    assert issubclass(Params, RenderSettings) and issubclass(CaptureSettings, RenderSettings)
    stage = _defaults(Params)
    assert {n: stage[n] for n in _defaults(RenderSettings)} == _defaults(RenderSettings)


def test_old_spellings_are_refused(tmp_path):
    import cnnps
    from cnnps.synth.capture_render import render_capture

    for old in ("jitter", "fov"):
        with pytest.raises(TypeError, match=old):
            cnnps.render("procedural:blob", tmp_path / "a", **{old: 1.0})
        with pytest.raises(TypeError, match=old):
            render_capture("procedural:blob", tmp_path / "a", **{old: 1.0})
    assert not (tmp_path / "a").exists()
