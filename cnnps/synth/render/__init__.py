"""What the capture renderer (:mod:`cnnps.synth.capture_render`) renders from and into,
none of it needing Blender:

- :mod:`cnnps.synth.render.settings`: ``RenderSettings`` and ``CaptureSettings``;
- :mod:`cnnps.synth.render.scene`: ``Scene`` and a capture's lights;
- :mod:`cnnps.synth.render.keys`: the content keys that name a rendered folder;
- :mod:`cnnps.synth.render.materials`: renderer materials;
- :mod:`cnnps.synth.render.mesh_input`: the mesh a user names;
- :mod:`cnnps.synth.render.resume`: the resume and checksum state machine of a folder;
- :mod:`cnnps.synth.render.rendered_folder`: reading a finished folder (what the extract
  stage imports).

Importing this package imports none of them.
"""
