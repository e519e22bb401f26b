"""cnnps: learning-based calibrated photometric stereo (CNN-PS, Ikehata ECCV 2018).

Five layers, each a subpackage, each importing only the ones before it
(docs/ARCHITECTURE.md; tests/test_layers.py holds the contract):

- ``cnnps.core``: maths and I/O with no network in it: observation maps, rotations,
  least squares, metrics, the capture folder, images, atomic writes, content keys,
  fsspec storage, Parquet shards, the per-scene executor;
- ``cnnps.models``: the CNN-PS network (PyTorch), checkpoints, inference, training
  machinery, the shipped weights;
- ``cnnps.synth``: the synthesis library: meshes, procedural shapes, rasteriser,
  superpixel materials, the Blender 5 BSDF mapping, lights, the Blender renderer (the
  only module that imports bpy);
- ``cnnps.stages``: one module per pipeline stage, each a typed ``Params`` and
  ``run(params, data_dir)``;
- ``cnnps.pipeline``: ``params.yaml`` configuration, ``cnnps predict`` and the
  command line.

Frame everywhere: x right, y up, z toward the camera; image row 0 is the top row.
"""

__version__ = "0.1.0"
