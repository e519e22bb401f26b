"""The shards' Parquet schema (one row a map and its normal, the map as float16 bytes),
an Arrow batch of rows made from arrays, and the columns decoded back to numpy."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

MAP_DTYPE = np.dtype("<f2")


ZSTD_LEVEL = 1  # faster to write than zstd's default 3, the same size for these maps


def shard_schema(w: int) -> pa.Schema:
    map_meta = {
        b"cnnps.dtype": b"float16",
        b"cnnps.shape": f"{w},{w}".encode(),
        b"cnnps.layout": b"row-major [row = y cell (row 0: ly = -1), col = x cell (col 0: lx = -1)]",
    }
    return pa.schema(
        [
            pa.field("map", pa.binary(w * w * MAP_DTYPE.itemsize), nullable=False, metadata=map_meta),
            pa.field("normal", pa.list_(pa.float32(), 3), nullable=False),
            pa.field("scene", pa.dictionary(pa.int32(), pa.string()), nullable=False),
            pa.field("row", pa.int32(), nullable=False),
            pa.field("col", pa.int32(), nullable=False),
            pa.field("n_lights", pa.int16(), nullable=False),
            pa.field("cone_deg", pa.float32(), nullable=False),
            pa.field("rotation", pa.int8(), nullable=False),
            pa.field("angle_deg", pa.float32(), nullable=False),
        ],
        metadata={b"cnnps.w": str(w).encode()},
    )


def make_batch(
    schema: pa.Schema,
    maps: np.ndarray,
    normals: np.ndarray,
    scene: str,
    rows: np.ndarray,
    cols: np.ndarray,
    n_lights: np.ndarray,
    cone_deg: np.ndarray,
    rotation: np.ndarray,
    angle_deg: np.ndarray,
) -> pa.RecordBatch:
    """Arrow record batch of n rows; ``maps`` is (n, w, w) (converted to float16)."""
    n = maps.shape[0]
    maps = np.ascontiguousarray(maps, dtype=MAP_DTYPE)
    width = schema.field("map").type.byte_width
    if maps.ndim != 3 or maps.shape[1] * maps.shape[2] * MAP_DTYPE.itemsize != width:
        raise ValueError(f"maps of {maps.shape[1:]} do not match the schema's {width} bytes")
    map_arr = pa.FixedSizeBinaryArray.from_buffers(pa.binary(width), n, [None, pa.py_buffer(maps)])
    normal_arr = pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(normals, np.float32).ravel()), 3)
    scene_arr = pa.DictionaryArray.from_arrays(pa.array(np.zeros(n, np.int32)), pa.array([scene], pa.string()))
    cols_ = [
        map_arr,
        normal_arr,
        scene_arr,
        pa.array(np.asarray(rows, np.int32)),
        pa.array(np.asarray(cols, np.int32)),
        pa.array(np.asarray(n_lights, np.int16)),
        pa.array(np.asarray(cone_deg, np.float32)),
        pa.array(np.asarray(rotation, np.int8)),
        pa.array(np.asarray(angle_deg, np.float32)),
    ]
    return pa.RecordBatch.from_arrays(cols_, schema=schema)


def decode_maps(column: pa.Array | pa.ChunkedArray, w: int) -> np.ndarray:
    """(n, w, w) float16 view of a ``map`` column (no copy for a single chunk)."""
    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks()
    if column.offset:
        column = pa.concat_arrays([column])  # materialise a sliced array
    buf = column.buffers()[1]
    n = len(column)
    return np.frombuffer(buf, dtype=MAP_DTYPE, count=n * w * w).reshape(n, w, w)


def decode_normals(column: pa.Array | pa.ChunkedArray) -> np.ndarray:
    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks()
    return column.flatten().to_numpy(zero_copy_only=False).reshape(-1, 3).astype(np.float32, copy=False)
