"""One module per pipeline stage; each exposes a frozen ``Params`` dataclass (its params.yaml
section) and ``run(params, data_dir)`` (stages with per-scene jobs also take ``executor=``).

A stage module holds only its parameters, its plan (what to write, with content keys),
the per-scene job and ``run``; the library it calls lives in :mod:`cnnps.synth`,
:mod:`cnnps.train`, :mod:`cnnps.models`, :mod:`cnnps.io`, :mod:`cnnps.ps` and :mod:`cnnps.infra`. Importing a
stage module never imports bpy. A stage too big for one module keeps its parts beside it:
``extract_params`` and ``extract_scene`` (its settings, one scene's job); ``eval_params``,
``eval_scoring``, ``eval_testset`` and ``eval_report`` (the eval stage's settings, scoring,
test set, table and report).

:data:`STAGES` is the list of stages, in the order they run, declared here once: the config
layer, the CLI's help, ``tools/long_run.py`` and the tests read it.
"""

STAGES = ("meshes", "materials", "render", "extract", "train", "eval")
