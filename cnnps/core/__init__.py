"""Core maths and I/O: everything the other layers build on, importing none of them.

Observation maps, rotations about the view axis, least squares, metrics, the capture
folder and image files, atomic writes, content keys, fsspec storage, Parquet shards and
the executor that runs per-scene jobs. PyTorch is imported lazily and only where a
module hands data to it (the shard dataset).
"""
