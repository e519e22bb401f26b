"""Blender Cycles in this process, split by concern; the only package that imports ``bpy``.

- :mod:`~cnnps.synth.blender.session`: finding ``bpy`` (one clear line when it is missing),
  its version, Blender's output silenced, the seed folded into Cycles' range;
- :mod:`~cnnps.synth.blender.scene_setup`: the film, sampling, device, world, camera and
  lamps of a new scene;
- :mod:`~cnnps.synth.blender.shaders`: material node graphs (Diffuse and Principled BSDFs
  with per-pixel maps, the emission overrides that show normals and depth);
- :mod:`~cnnps.synth.blender.renderer`: :class:`BlenderRenderer`, one scene rendered once
  per light, what the rest of the code sees.

Its module shows how the renderer is used.
"""

from cnnps.synth.blender.renderer import POINT_POWER, BlenderRenderer
from cnnps.synth.blender.session import (
    BLENDER_MISSING,
    blender_available,
    blender_version,
    cycles_seed,
    require_blender,
)

__all__ = ["BLENDER_MISSING", "POINT_POWER", "BlenderRenderer", "blender_available", "blender_version", "cycles_seed",
           "require_blender"]
