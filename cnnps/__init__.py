"""cnnps: learning-based calibrated photometric stereo (CNN-PS, Ikehata ECCV 2018).

The Python API (NumPy in, NumPy out; :mod:`cnnps.api`)::

    import cnnps
    cap = cnnps.load_capture("path/to/capture")        # a DiLiGenT-layout folder
    res = cnnps.predict(cap.images, cap.lights, cap.mask, intensities=cap.intensities)
    res.normals                                        # (H, W, 3) unit normals
    surf = cnnps.integrate(res.normals, cap.mask)      # surf.depth, surf.mesh

``cnnps.predict``, ``cnnps.predict_folder``, ``cnnps.load_capture``,
``cnnps.calibrate``, ``cnnps.integrate`` and ``cnnps.render`` (Blender) are the same
functions the ``cnnps`` command line runs; ``help(cnnps.predict)`` states the contract.

The package, lowest layer first, each importing only the ones before it
(docs/ARCHITECTURE.md; tests/test_layers.py holds the contract):

- ``cnnps.infra``: plumbing (errors, atomic writes, hashing, storage, the executor);
- ``cnnps.ps``: photometric-stereo maths on arrays (observation maps, rotations, least
  squares, the sparse fill, metrics, integration, light calibration);
- ``cnnps.io``: files (capture folders, images, the pixel stack, shards, surfaces, pictures);
- ``cnnps.models``: the CNN-PS network (PyTorch), inference, shipped weights;
- ``cnnps.synth``: the synthesis library (meshes, materials, BSDF, lights, Blender renderer);
- ``cnnps.train``: the training loop and its speed machinery;
- ``cnnps.stages``: one module per pipeline stage;
- ``cnnps.api``: the Python API above;
- ``cnnps.pipeline``: ``params.yaml`` configuration and the command line.

Frame everywhere: x right, y up, z toward the camera; image row 0 is the top row.
"""

__version__ = "0.1.0"

_API = ("Calibration", "Capture", "Prediction", "Surface", "calibrate", "integrate", "load_capture",
        "predict", "predict_folder", "render")
__all__ = list(_API)


def __getattr__(name: str):
    if name in _API:
        import cnnps.api

        value = getattr(cnnps.api, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'cnnps' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
