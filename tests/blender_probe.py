"""Run by Blender's Python (the bpy venv of `make blender-deps`), never by pytest: open a file as a Blender user
does and report what Blender shows. argv[1] is a JSON request:

- "path": a GLB / USD, imported with Blender's own importer as File > Import does (default options) into an empty
  scene whose frame rate is "fps" (null: Blender's default), or a .blend, opened as it was saved;
- "frames": the frames at which every mesh's evaluated vertices (world space, after shape keys and armatures) are
  written to "out" (.npz, one (frames, V, 3) array per mesh object, by name, and `NAME.uv`, (V, 2) per vertex, for
  a mesh with a UV map, and `NAME.color`, (V, 3) linear RGB, for one with a per-vertex colour attribute).

Prints one line `probe: {json}`: the scene's frame rate, frame range, sync mode, objects (name, type, parent), the
shape key names of each mesh, each mesh's
materials with their image textures (name, size, first pixel) and what feeds their Base Color, and the sound strips (name, start frame, length in frames, file).
"""

import json
import sys

import bpy
import numpy as np

request = json.loads(sys.argv[1])
path = request["path"]
if path.endswith(".blend"):
    bpy.ops.wm.open_mainfile(filepath=path)
else:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if request.get("fps"):
        bpy.context.scene.render.fps, bpy.context.scene.render.fps_base = int(request["fps"]), 1.0
    if path.endswith(".glb"):
        bpy.ops.import_scene.gltf(filepath=path)
    else:
        bpy.ops.wm.usd_import(filepath=path)
scene = bpy.context.scene
meshes = [o for o in scene.objects if o.type == "MESH"]
positions = {o.name: [] for o in meshes}
for frame in request["frames"]:
    scene.frame_set(frame)
    graph = bpy.context.evaluated_depsgraph_get()
    for o in meshes:
        evaluated = o.evaluated_get(graph)
        mesh = evaluated.to_mesh()
        co = np.empty(3 * len(mesh.vertices), np.float64)
        mesh.vertices.foreach_get("co", co)
        m = np.array(evaluated.matrix_world)
        positions[o.name].append(co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3])
        evaluated.to_mesh_clear()
uvs = {}
for o in meshes:            # per vertex, from the first UV map's loops (a vertex's loops agree on a seamless mesh)
    if o.data.uv_layers:
        loops = np.empty(len(o.data.loops), np.int64)
        o.data.loops.foreach_get("vertex_index", loops)
        uv = np.empty(2 * len(o.data.loops), np.float64)
        o.data.uv_layers[0].data.foreach_get("uv", uv)
        per_vertex = np.full((len(o.data.vertices), 2), np.nan)
        per_vertex[loops] = uv.reshape(-1, 2)
        uvs[f"{o.name}.uv"] = per_vertex
    colors = [a for a in o.data.color_attributes if a.domain == "POINT"]
    if colors:               # the first per-vertex colour attribute, RGB as Blender stores it (linear floats)
        rgba = np.empty(4 * len(o.data.vertices), np.float64)
        colors[0].data.foreach_get("color", rgba)
        uvs[f"{o.name}.color"] = rgba.reshape(-1, 4)[:, :3]
np.savez(request["out"], **{name: np.array(p) for name, p in positions.items()}, **uvs)


def base_colour_source(material) -> list | None:
    """[node type, its attribute name] of what feeds the material's Principled BSDF's Base Color, or None."""
    if material is None or not material.use_nodes:
        return None
    bsdf = next((n for n in material.node_tree.nodes if n.type == "BSDF_PRINCIPLED"), None)
    links = bsdf.inputs["Base Color"].links if bsdf is not None else ()
    return [links[0].from_node.bl_idname, getattr(links[0].from_node, "attribute_name", None)] if links else None


def images(material) -> list:
    """[name, width, height, the first pixel's RGBA] of each image texture node of `material`."""
    if material is None or not material.use_nodes:
        return []
    out = []
    for node in material.node_tree.nodes:
        if node.type == "TEX_IMAGE" and node.image is not None:
            image = node.image
            pixel = list(image.pixels[:4]) if image.size[0] else []
            out.append([image.name, image.size[0], image.size[1], pixel])
    return out

editor = scene.sequence_editor
strips = [] if editor is None else list(editor.strips if hasattr(editor, "strips") else editor.sequences)
print("probe: " + json.dumps({
    "fps": scene.render.fps / scene.render.fps_base, "frame_start": scene.frame_start, "frame_end": scene.frame_end,
    "sync_mode": scene.sync_mode,
    "objects": [[o.name, o.type, o.parent.name if o.parent else None] for o in scene.objects],
    "bones": {o.name: [b.name for b in o.data.bones] for o in scene.objects if o.type == "ARMATURE"},
    "shape_keys": {o.name: [k.name for k in o.data.shape_keys.key_blocks] for o in meshes if o.data.shape_keys},
    "materials": {o.name: [[m.name, images(m)] for m in o.data.materials if m is not None] for o in meshes},
    "base_colour": {o.name: [base_colour_source(m) for m in o.data.materials if m is not None] for o in meshes},
    "sounds": [[s.name, s.frame_start, s.frame_final_duration, bpy.path.abspath(s.sound.filepath)] for s in strips
               if s.type == "SOUND"],
}), flush=True)
