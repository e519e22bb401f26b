"""Speed and accuracy measurements, grouped by area (``predict``, ``train``, ``synth``,
``io``, ``pipeline``), each run as a module from the repository root
(``.venv/bin/python -m benchmarks.<area>.<name>``) on the shared harness
(:mod:`benchmarks.harness`). benchmarks/README.md lists them."""
