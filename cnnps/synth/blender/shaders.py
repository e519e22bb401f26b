"""Material node graphs: the object's surface (a Diffuse or a Principled BSDF whose inputs
are constants or per-pixel maps) and the emission overrides that show the shading normal
and the depth.

Materials: ``{"bsdf": "lambertian", "Color": albedo}`` is a Diffuse BSDF (roughness 0 =
pure Lambertian). Anything else is a Principled BSDF: every other key is the name of a
Principled input and its value a constant (scalar or RGB) or a per-pixel map (S, S) or
(S, S, 3) (image row 0 on top). Maps reach the shader as image-space textures
(Texture Coordinate ``Window`` -> Image Texture, Closest interpolation, non-colour data),
so each pixel renders with its own parameters. Scalar maps are packed three to an image.
Rays that bounce onto the object elsewhere read the map at the point's projection into
the image (an approximation only for self-occluded points).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from cnnps.infra.errors import ConfigError
from cnnps.synth.render.scene import CAMERA_ORIGIN

LAMBERTIAN = "lambertian"


def image(bpy, name: str, rgb: np.ndarray, size: int, images: list):
    """An S x S float, non-colour image holding rgb (S, S, 3), row 0 on top (S = ``size``),
    packed, appended to ``images`` (the renderer removes them with the material)."""
    S = size
    if rgb.shape[:2] != (S, S):
        raise ConfigError(f"material map {name!r} is {rgb.shape[1]}x{rgb.shape[0]}, render size is {S}x{S}")
    img = bpy.data.images.new(name, S, S, alpha=False, float_buffer=True, is_data=True)
    img.colorspace_settings.name = "Non-Color"
    rgba = np.ones((S, S, 4), dtype=np.float32)
    rgba[:, :, :3] = rgb[::-1]  # Blender images start at the bottom row
    img.pixels.foreach_set(rgba.ravel())
    img.pack()
    images.append(img)
    return img

def empty_material(bpy, name: str):
    """A new material and its node tree, emptied."""
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender 5 makes the tree already (use_nodes is deprecated)
        mat.use_nodes = True
    mat.node_tree.nodes.clear()
    return mat, mat.node_tree

def surface_material(bpy, spec: Mapping[str, Any], size: int, images: list):
    """The object's material of ``spec`` (the module docstring: Materials); the images its
    maps need are appended to ``images``."""
    spec = dict(spec)
    kind = spec.pop("bsdf", "principled")
    mat, nt = empty_material(bpy, "material")
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    if kind == LAMBERTIAN:
        bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Roughness"].default_value = 0.0
        spec.setdefault("Color", 1.0)
    elif kind == "principled":
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Diffuse Roughness"].default_value = 0.0
    else:
        raise ConfigError(f"unknown material bsdf {kind!r} (use 'lambertian' or 'principled')")
    nt.links.new(bsdf.outputs[0], out.inputs["Surface"])

    coord = None
    scalar_maps: list[tuple[str, np.ndarray]] = []
    for name, value in spec.items():
        if name not in bsdf.inputs:
            raise ConfigError(f"material input {name!r} is not an input of {bsdf.bl_idname}")
        sock = bsdf.inputs[name]
        arr = np.asarray(value, dtype=np.float32)
        is_color = sock.type == "RGBA"
        if arr.ndim <= 1:  # constant
            if is_color:
                rgb = np.broadcast_to(arr, (3,))
                sock.default_value = (float(rgb[0]), float(rgb[1]), float(rgb[2]), 1.0)
            elif arr.ndim == 0:
                sock.default_value = float(arr)
            else:
                raise ConfigError(f"material input {name!r} takes one number, got {arr.shape}")
            continue
        if coord is None:
            coord = nt.nodes.new("ShaderNodeTexCoord")
        if arr.ndim == 3 and arr.shape[2] == 3:
            if not is_color:
                raise ConfigError(f"material input {name!r} takes one number per pixel, got an RGB map")
            tex = texture(nt, coord, image(bpy, name, arr, size, images))
            nt.links.new(tex.outputs["Color"], sock)
        elif arr.ndim == 2:
            if is_color:
                tex = texture(nt, coord, image(bpy, name, np.repeat(arr[:, :, None], 3, axis=2), size, images))
                nt.links.new(tex.outputs["Color"], sock)
            else:
                scalar_maps.append((name, arr))
        else:
            raise ConfigError(f"material map {name!r} must be (S,S) or (S,S,3), got {arr.shape}")
    for i in range(0, len(scalar_maps), 3):  # pack three scalar maps per image
        group = scalar_maps[i : i + 3]
        rgb = np.zeros((size, size, 3), dtype=np.float32)
        for k, (_, arr) in enumerate(group):
            if arr.shape != (size, size):
                raise ConfigError(f"material map {group[k][0]!r} is {arr.shape}, render size is {size}")
            rgb[:, :, k] = arr
        tex = texture(nt, coord, image(bpy, "+".join(n for n, _ in group), rgb, size, images))
        sep = nt.nodes.new("ShaderNodeSeparateColor")
        sep.mode = "RGB"
        nt.links.new(tex.outputs["Color"], sep.inputs[0])
        for k, (name, _) in enumerate(group):
            nt.links.new(sep.outputs[k], bsdf.inputs[name])
    return mat

def texture(nt, coord, image):
    """An Image Texture of ``image`` read at the window coordinates, Closest interpolation."""
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = image
    tex.interpolation = "Closest"
    tex.extension = "EXTEND"
    nt.links.new(coord.outputs["Window"], tex.inputs["Vector"])
    return tex


def emission_material(bpy, name: str, link) -> Any:
    """A material emitting (strength 1) the colour ``link(nt, geometry_node)`` returns."""
    mat, nt = empty_material(bpy, name)
    geo = nt.nodes.new("ShaderNodeNewGeometry")
    emit = nt.nodes.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 1.0
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(link(nt, geo), emit.inputs["Color"])
    nt.links.new(emit.outputs[0], out.inputs["Surface"])
    return mat

def normal_material(bpy):
    """Emission of (N + 1) / 2 with N Blender's smooth shading normal (world = camera frame)."""

    def link(nt, geo):
        scale = nt.nodes.new("ShaderNodeVectorMath")
        scale.operation = "MULTIPLY_ADD"
        scale.inputs[1].default_value = (0.5, 0.5, 0.5)
        scale.inputs[2].default_value = (0.5, 0.5, 0.5)
        nt.links.new(geo.outputs["Normal"], scale.inputs[0])
        return scale.outputs["Vector"]

    return emission_material(bpy, "normals", link)

def depth_material(bpy):
    """Emission of CAMERA_ORIGIN - P (P the hit point): its blue is the depth 5 - z."""

    def link(nt, geo):
        sub = nt.nodes.new("ShaderNodeVectorMath")
        sub.operation = "SUBTRACT"
        sub.inputs[0].default_value = CAMERA_ORIGIN
        nt.links.new(geo.outputs["Position"], sub.inputs[1])
        return sub.outputs["Vector"]

    return emission_material(bpy, "depth", link)
