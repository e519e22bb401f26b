"""Orchestration: configuration (params.yaml), caching, the command line."""
