"""Photometric-stereo maths on arrays: observation maps, rotations about the view axis,
least-squares Lambertian normals, the sparse-capture fill, angular-error metrics, normal
integration and light calibration from ball pictures.

NumPy and SciPy (scikit-image for the ball's outline); no files read or written, no torch.
Imports only :mod:`cnnps.infra` (its errors).
"""
