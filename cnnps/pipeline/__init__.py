"""The top layer: params.yaml configuration, stage orchestration, ``cnnps predict`` and
the ``cnnps`` command line (Typer), a thin layer over the library below."""
