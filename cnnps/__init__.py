"""cnnps: learning-based calibrated photometric stereo (CNN-PS).

The core library (this package) is pure NumPy/PyTorch-free math plus capture I/O:
observation maps, rotations about the view axis, the least-squares Lambertian
baseline, angular-error metrics and the capture-folder contract.

Frame everywhere: x right, y up, z toward the camera; image row 0 is the top row.
"""

__version__ = "0.1.0"
