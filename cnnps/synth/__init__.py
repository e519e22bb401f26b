"""The synthesis library: everything that makes training and test captures.

- :mod:`cnnps.synth.meshes`: mesh loading, cleaning, normalising into the unit sphere, poses;
- :mod:`cnnps.synth.procedural`: seeded non-convex procedural shapes;
- :mod:`cnnps.synth.raster`: the orthographic z-buffer rasteriser (mask, normals, depth);
- :mod:`cnnps.synth.material_maps`: SLIC superpixel material maps;
- :mod:`cnnps.synth.bsdf`: the paper's material ranges and their Blender 5 mapping;
- :mod:`cnnps.synth.lights`: light directions on the hemisphere;
- :mod:`cnnps.synth.capture_render`: the one capture renderer (a ``Scene`` and
  ``RenderSettings`` in, a cached, resumable capture folder out; orthographic or pinhole
  camera, suns or point lights);
- :mod:`cnnps.synth.render`: what the capture renderer needs no Blender for: settings,
  scene, content keys, materials, the mesh a user names, the resume and checksum state
  machine, and reading a rendered folder (what the extract stage imports);
- :mod:`cnnps.synth.blender`: the in-process Cycles renderer (session, scene set-up,
  shaders, renderer), the only package that imports bpy (an optional extra, ``cnnps[render]``).
"""
