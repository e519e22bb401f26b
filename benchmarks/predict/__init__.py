"""Normals from a capture: the network's speed and memory, its precisions, and its accuracy
against least squares, the published numbers and the cameras and lights of real rigs."""
