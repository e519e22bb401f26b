"""The `cnnps stages` command(s)."""
from pipeline.app import app  # noqa: F401

