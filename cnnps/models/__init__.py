"""The network layer: CNN-PS and what runs a trained one (imports only ``cnnps.infra``,
``cnnps.ps`` and ``cnnps.io``; the training loop is :mod:`cnnps.train`).

- ``network``: the CNN-PS model and its inference-only folded forms;
  ``model_options``: a network from its options (``build_model``: arch, head, patch) and
  what a checkpoint records; ``heads``: each head's loss and decoding; ``heatmap``:
  heat-map targets, decoding and spread; ``unet``: the heat-map U-Net; ``patch``: the
  spatial-context first layer;
  ``train_layers``: its CPU training pass with written-out backward, which
  ``CNNPS.forward`` runs (and the oneDNN checks inference shares);
- ``checkpoint``: safe save/load of model files; ``shipped``: the model in
  ``cnnps/models/weights/`` and its provenance; ``interpolate``: weight-space mixes of two
  model files;
- ``devices``: the one device rule; ``inference``: batched prediction with test-time
  rotations (``predict_normals``, ``MapPredictor``); ``precision_probe``: what
  ``--precision auto`` measures; ``network_solver``: the network as ``cnnps predict``'s
  ``cnn`` method (:mod:`cnnps.ps.solver`).
"""
