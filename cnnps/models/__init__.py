"""The network layer: CNN-PS and everything that runs it (imports only ``cnnps.infra``,
``cnnps.ps`` and ``cnnps.io``).

- ``network``: the CNN-PS model and its inference-only folded forms;
- ``checkpoint``: safe save/load of model files; ``shipped``: the model in
  ``cnnps/models/weights/`` and its provenance;
- ``devices``: the one device rule; ``inference``: batched prediction with test-time
  rotations (``predict_normals``, ``MapPredictor``);
- training, as the train stage (``cnnps.stages.train``) runs it: ``training`` (the
  loop), ``optimiser`` (model and Adam, learning rate, one step), ``train_state``
  (resumable checkpoints, RNG states), ``validation``, ``shard_dataset`` (the torch
  side of the shard reader), ``distributed`` (torchrun) and
  ``openmp`` (OpenMP's wait policy, set before torch loads; torch-free, like this file).
"""
