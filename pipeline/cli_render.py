"""The `cnnps render` command(s)."""
from pipeline.app import app  # noqa: F401

