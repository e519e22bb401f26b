"""Training CNN-PS: the loop the train stage (:mod:`cnnps.stages.train`) runs and the
machinery that makes its steps fast. Imports :mod:`cnnps.models` (the network,
checkpoints, inference) and the layers below it, and :mod:`cnnps.synth` for per-pixel
maps; nothing below imports it. This file, like ``openmp``, loads no torch.

The loop and what it keeps:

- ``params``: the train section's typed tree, ``Params`` (loads no torch either);
- ``process_setup``: this process's threads, device and (under torchrun) process group;
- ``training_data``: the extract manifest and its shards opened and checked, or none;
- ``init_weights``: the checkpoint a run starts from (``train.init``);
- ``pixelwise_batches``: per-pixel batches from the train params, one a step;
- ``data_streams``: this rank's stream of shards or patches, and the run's steps;
- ``loop``: resume, the step loop, checkpoints, the model file and ``metrics.json``
  (:func:`~cnnps.train.loop.train`, :class:`~cnnps.train.loop.Trainer`);
- ``run_outputs``: the params the model file records and the curves for ``dvc plots``;
- ``optimiser``: the model and Adam, the learning-rate schedule, one step;
- ``resume``: the resumable ``checkpoints/step-*.pt`` files and RNG states;
- ``validation``: the validation sample and its angular error;
- ``precision``: what ``train.precision: auto`` steps in, timed at the run's start;
- ``shard_dataset``: the torch side of the shard reader;
- ``distributed``: several processes under torchrun.

Speed (none changes the weights beyond float rounding):

- ``openmp``: OpenMP's wait policy, set before torch loads;
- ``allocator``: glibc's heap kept for the next step (``train.cpu.keep_freed_memory``);
- ``step_processes``: processes sharing each CPU step (``train.cpu.step_processes``);
- ``batch_lookahead``: the next batch read while the step's helpers finish;
- ``maps_ahead``: per-pixel maps made a step ahead (``train.pixelwise.ahead``);
- ``device_feed``: pinned buffers and async copies to a GPU;
- ``step_clock``: where the step loop's wall time goes.
"""
