"""A training run longer than a session: a fixed checkout, data outside the work tree, a
CPU-time ledger, and a fallback to committed weights.

    .venv/bin/python tools/long_run.py start v4 --preset cpu-train-v4 [--commit HEAD] [--root /work/runs]
    .venv/bin/python tools/long_run.py start fx --preset cpu-train-v5-continue --set train.max_steps=1500
    .venv/bin/python tools/long_run.py resume v4 [--root /work/runs] [--stages render extract train]
    .venv/bin/python tools/long_run.py start arm --preset P --data-from v6 --set train.seed=1   # v6's renders, linked
    .venv/bin/python tools/long_run.py resume fx --stages train eval --testset-from v4   # one rendered test set
    .venv/bin/python tools/long_run.py save v4 [--root /work/runs]      # then commit tools/runs/v4/
    .venv/bin/python tools/long_run.py save v5 --final           # ended before its plan: the record, not the weights
    .venv/bin/python tools/long_run.py status v4
    .venv/bin/python tools/long_run.py study v4                  # a clone for `dvc exp run`
    .venv/bin/python tools/long_run.py exp v4 -- -n NAME -S train.optimiser.lr=1e-4   # one variant, timed
    .venv/bin/python tools/long_run.py table v4                  # the study's table (and study.json)
    .venv/bin/python tools/long_run.py probe v4                  # score the newest checkpoint now
    .venv/bin/python tools/long_run.py probe v4 --model MID.pt --name mid   # or a candidate weights file
    .venv/bin/python tools/long_run.py curve v5 --every 5000 --pixels 2000   # real objects along the run
    .venv/bin/python tools/long_run.py curve v5 --every 5000 --no-newest     # while it trains: the grid only
    .venv/bin/python tools/long_run.py stop v5                   # at the next checkpoint
    .venv/bin/python tools/long_run.py arms v6 --arm heatmap=v6-hm-s1,v6-hm-s2 --arm regression=v6-re-s1,v6-re-s2 \
        --reference v6-v4   # the arms' table, the selection rule's verdicts, tools/runs/v6/arms.json

A run of ``train.phases`` is handled too: its checkpoints and validation log are read from
its phases' folders, steps counted over the chain (:mod:`~tools.longrun.checkpoints`).

It imports ``cnnps`` from this interpreter's install (``make setup``: this checkout, in
editable mode) for its own bookkeeping; the stages run the clone's code.

The work tree is laid anew every session and only git is certain, but a folder outside
it often survives. So a run lives in ``ROOT/NAME/``:

- ``code/``: a clone of this repository at one commit (``start --commit``), so editing the
  work tree never changes the code that is running; the stages run with ``PYTHONPATH``
  set to it (the interpreter is this one's: its packages, that commit's ``cnnps``);
- ``params.yaml``: the preset with ``data_dir`` set to ``ROOT/NAME/data`` (absolute);
- ``data/``: the stage outputs; every stage skips the work it finds done (scenes, shards)
  and the train stage resumes from its newest checkpoint, so ``resume`` after a kill
  continues exactly where the folder left off;
- ``study/``: a second clone at the same commit for the variant study (``study``): its
  ``params.yaml`` is the run's, its data phase is linked to the run's folders, and
  ``dvc exp run -S train.optimiser.lr=...`` there trains and scores one variant into its own
  ``data/train`` and ``data/eval``; ``dvc exp show`` is the table. ``exp`` runs one such
  experiment and books its time in the ledger as stage ``study``;
- ``curve``: the checkpoints every ``--every`` steps (and the newest, unless
  ``--no-newest``) scored on real objects with ground truth (BALL and the four DiLiGenT
  crops under ``--shared``) by ``cnnps score --pixels N`` of this work tree: the same
  seeded sample of pixels for every checkpoint, a quick paired comparison, not the
  benchmark's number. Rows go to
  ``real_curve.json`` in git's folder (step, CPU-hours at that step, validation error, each
  capture's mean, the dev-real mean: the captures but BALL); the time to the ledger (stage
  ``curve``). A step already scored with the same options is not scored again;
- ``stop``: waits for the train stage's next checkpoint, then ends the run's process tree
  (this run's only); ``resume`` continues from that checkpoint;
- ``arms``: the arms of a study (``--arm NAME=RUN,RUN``: runs of one recipe, one per
  ``train.seed``), read from each run's ``data/eval/metrics.json``, eval section and
  ledger: per arm and column the mean over its seeds and the spread (half their range),
  the selection rule and the ship gates of docs/models.md ("Model v6: the plan and the
  selection rule") against ``--reference``; the table printed and kept in ``arms.json`` in
  git's folder of STUDY. A run with no metrics yet is listed and left out (the table is
  read while seeds still train); a run that does not exist, or a reference not scored,
  stops with one line naming the file;
- ``ledger.json``: wall and CPU seconds of every stage call (the stage's whole process
  tree, sampled every ``--poll`` seconds, so a killed call loses at most that much), with
  the CPU model of the machine it ran on.

What git carries, in ``tools/runs/NAME/``: ``run.json`` (commit, preset, params),
``ledger.json`` and the newest checkpoint's weights in float16 (``save``; ``tools/run_weights.py``):
while the run is in progress, the file itself (``intermediate.pt``, replaced each time,
never a second file) and its record ``intermediate.json`` (bytes, SHA-256, steps); once
the run is finished (its plan spent, or ``save --final``), the record alone: the weights
stay in ``ROOT/NAME/intermediate.pt``, outside the tree. ``resume`` on a machine where
``ROOT/NAME`` is gone clones the same commit again and regenerates the data (the stages
are deterministic and seeded; the ledger records the time it took again). If the train
stage then has no checkpoint and the carried weights stop before the plan's end, training
restarts from those weights with the rest of its schedule (:func:`continue_schedule`): the
steps left, the milestones still ahead, the learning rate reached; Adam's moments start
afresh (the one thing such a fallback loses). Weights put back by hand are checked
against the record's SHA-256; weights that are only recorded stop ``resume`` with one
line saying how to get them back.

The package's modules: :mod:`~tools.longrun.run` (the run's folder, its stages, timed),
:mod:`~tools.longrun.variant_study`, :mod:`~tools.longrun.real_scores` and
:mod:`~tools.longrun.carried_weights` (the run's parts), :mod:`~tools.longrun.arms` (the
arms of a study), :mod:`~tools.longrun.train_section` (a train section in either layout),
:mod:`~tools.longrun.checkpoints` (a run's checkpoints, with or without phases),
:mod:`~tools.longrun.process_time` (CPU time of a process tree),
:mod:`~tools.longrun.paths` and :mod:`~tools.longrun.cli` (``tools/long_run.py``).
"""
