"""Training shards: the extract stage's maps and Parquet writing, and the loader reading
them back."""
