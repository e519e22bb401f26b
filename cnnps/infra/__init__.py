"""Plumbing with no photometric stereo in it: errors, atomic writes, content hashes and
seeds, read-ahead threads, the CPU's name, local-or-fsspec storage, stage output folders
and the executor that runs per-item jobs locally or on Ray.

Imports nothing of the project.
"""
