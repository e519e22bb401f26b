"""The top layer: params.yaml configuration, stage orchestration, the data-folder lock and
the ``cnnps`` command line (Typer), a thin layer over :mod:`cnnps.api` and the stages."""
