"""Parquet shards of observation maps: schema, atomic writer, manifest, streaming loader.

One row is one training sample: an observation map of w x w cells and its unit normal,
both in the (rotated) camera frame of that row.

Columns (see :func:`shard_schema`):

- ``map``: ``fixed_size_binary(w*w*2)`` holding the w x w map as little-endian float16,
  row-major, indexed ``[row = y cell, col = x cell]`` exactly like
  :func:`cnnps.ps.obsmap.observation_maps` (the field metadata says so). A binary column
  is used instead of ``fixed_size_list<halffloat>[w*w]`` because Parquet stores a
  repetition/definition level per list element, which makes the list column slower to
  write and to read for the same file size (docs/performance.md#shards-and-the-loader).
  Decoding is one ``np.frombuffer``.
- ``normal``: ``fixed_size_list<float>[3]`` unit normal (x right, y up, z to camera).
- ``scene``: dictionary-encoded string scene id; ``row``, ``col``: the pixel (int32);
  ``n_lights``: lights used for this map (int16); ``cone_deg``: half-angle (degrees) of
  the cone about the view axis the lights were drawn from (float32); ``rotation``:
  rotation index (int8) and ``angle_deg`` (float32): lights and normal were rotated
  about z by this angle.

Files are written under a temporary name and renamed only when complete
(:class:`SceneShardWriter`), so a file named ``shard-*.parquet`` is always whole.

Integrity: every shard's size and SHA-256 are recorded when it is written
(:class:`ShardInfo`, copied into the extract stage's scene markers and ``manifest.json``),
and the manifest carries a ``checksum`` of its own content
(:func:`cnnps.infra.hashing.json_checksum`, indent 1). :func:`manifest_digest` checks that
checksum (a manifest edited by hand is refused) and :func:`verify_shards` checks every
shard against its record before training reads one; :class:`ShardStream` also refuses a
row group holding a non-finite map or normal, so NaN never reaches the network.

Shards can live at a local path or at an fsspec URL (``s3://bucket/run/extract``,
``gs://...``, ``memory://...``; :mod:`cnnps.infra.storage`): the writer stages a scene's
files in a local temporary folder and uploads each one atomically (temporary name,
then move) when the scene is complete; the readers (:func:`load_manifest`,
:func:`row_group_units`, :func:`read_row_group`, :class:`ShardStream`) open URLs
through a pyarrow filesystem. Local paths stay :class:`~pathlib.Path`, URLs stay strings.

The modules, one concern each: :mod:`~cnnps.io.shards.schema` (the columns, a batch of
rows, decoding), :mod:`~cnnps.io.shards.writer` (a scene's files written atomically),
:mod:`~cnnps.io.shards.manifest` (the manifest and the shards' records checked) and
:mod:`~cnnps.io.shards.stream` (row groups read and checked, :class:`ShardStream`). The
names below are the package's public API.
"""

from cnnps.io.shards.manifest import (
    FIX_EXTRACT,
    MANIFEST,
    MANIFEST_INDENT,
    file_size,
    load_manifest,
    manifest_digest,
    manifest_files,
    shard_path,
    shard_problem,
    verify_shards,
)
from cnnps.io.shards.schema import MAP_DTYPE, ZSTD_LEVEL, decode_maps, decode_normals, make_batch, shard_schema
from cnnps.io.shards.stream import (
    PREFETCH_DEFAULT,
    ShardStream,
    check_finite,
    open_parquet,
    read_row_group,
    row_group_units,
)
from cnnps.io.shards.writer import SceneShardWriter, ShardInfo

__all__ = ["FIX_EXTRACT", "MANIFEST", "MANIFEST_INDENT", "MAP_DTYPE", "PREFETCH_DEFAULT", "ZSTD_LEVEL", "SceneShardWriter",
           "ShardInfo", "ShardStream", "check_finite", "decode_maps", "decode_normals", "file_size", "load_manifest",
           "make_batch", "manifest_digest", "manifest_files", "open_parquet", "read_row_group", "row_group_units",
           "shard_path", "shard_problem", "shard_schema", "verify_shards"]
