"""The `cnnps predict` command(s)."""
from pipeline.app import app  # noqa: F401

