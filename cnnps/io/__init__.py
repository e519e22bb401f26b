"""Files: the capture folder, image formats and sRGB decoding, the per-pixel image stack,
Parquet training shards, surface outputs (depth, mesh) and pictures.

Imports :mod:`cnnps.infra` and :mod:`cnnps.ps`.
"""
