"""The rest of a glTF character's scene in its USD: texture coordinates, materials, textures and the meshes it does
not drive, so that Omniverse, Blender or Quick Look show the user's avatar, not a grey floating face.

`usd.build_stage` writes the driven meshes with their blend shapes; for a character read from a glTF scene
(`Character.parts`) it then calls `dress_gltf_scene`, which adds:

- on every driven mesh: `primvars:st` (TEXCOORD_0, vertex interpolation, v flipped: glTF's texture origin is the
  top left, USD's the bottom left) and its material binding (one GeomSubset per primitive's material, family
  `materialBind`, where a mesh's primitives use several);
- a driven mesh that several nodes show (one eye mesh for both eyes): a driven Mesh prim for each further node, placed
  by it, with the same blend shapes;
- every other mesh of the scene (a body, hair, eyes that share no target) as a static Mesh prim under the SkelRoot,
  placed as the scene shows it (node world transform, or a skinned mesh's rest pose: `GltfScene.placed_mesh`; one prim
  per node that instances a mesh without a skin), named by its node (else its mesh), in the character's unit, with
  its st and materials;
- `/<Root>/Materials/<name>`: one UsdPreviewSurface material per glTF material used: base colour (factor times
  texture; alpha as opacity for BLEND, with `opacityThreshold` = alphaCutoff for MASK), metallic and roughness
  (factors times the blue and green channels of their texture), normal map (scale 2, bias -1, its `scale` on x and
  y), emissive, occlusion; `doubleSided` on meshes whose material is.

Textures: with `texture_dir` (the `usdz` export: `usd.write_usdz` packs them into the one file) each image the
materials use is written there once, as `textures/<index>_<name>.png|.jpg` (checked to decode; WebP and other
formats Pillow reads converted to PNG, `textures.package_image`), and referenced by a UsdUVTexture; without it (the
plain `.usd`), materials carry their factors only, since a `.usd` is one file and holds no image. Images that cannot
be read or decoded (a missing file, corrupt data, KTX2), textures read through TEXCOORD_1 and KHR_texture_transform
are not carried; `dress_gltf_scene` returns a note for each, which the writer puts in the layer's documentation (and
`textures.appearance_notes` among the package's warnings).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib as gl
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

from visemeflow.rig.character import Character
from visemeflow.animation.textures import TextureError, image_of, package_image
from visemeflow.rig.gltf import GltfMesh, GltfScene
from visemeflow.rig.model import RigError

__all__ = ["MATERIALS", "TEXTURES", "dress_gltf_scene"]

MATERIALS = "Materials"
TEXTURES = "textures"
_WRAP = {gl.REPEAT: "repeat", gl.CLAMP_TO_EDGE: "clamp", gl.MIRRORED_REPEAT: "mirror"}


class _Materials:
    """The glTF materials as USD materials, made on first use; images written once each."""

    def __init__(self, stage: Usd.Stage, root: Sdf.Path, scene: GltfScene, texture_dir: Path | None,
                 prim_name, notes: list[str]):
        self.stage, self.scene, self.texture_dir, self.notes = stage, scene, texture_dir, notes
        self.folder = root.AppendChild(MATERIALS)
        self.prim_name = prim_name
        self.made: dict[int, UsdShade.Material] = {}
        self.images: dict[int, str | None] = {}
        self.names: set[str] = set()

    def material(self, index: int | None) -> UsdShade.Material | None:
        materials = self.scene.gltf.materials or []
        if not isinstance(index, int) or not 0 <= index < len(materials):
            return None
        if index not in self.made:
            if not self.names:
                UsdGeom.Scope.Define(self.stage, self.folder)
            name = self.prim_name(materials[index].name or f"material_{index}")
            base, k = name, 1
            while name in self.names:
                name, k = f"{base}_{k}", k + 1
            self.names.add(name)
            self.made[index] = self._define(self.folder.AppendChild(name), materials[index], index)
        return self.made[index]

    def double_sided(self, index: int | None) -> bool:
        materials = self.scene.gltf.materials or []
        return isinstance(index, int) and 0 <= index < len(materials) and bool(materials[index].doubleSided)

    def _image(self, info, what: str) -> str | None:
        """The asset path of the image of texture info `info` in `texture_dir`, written on first use (PNG or JPEG:
        others are converted, `textures.package_image`); None (with a note) when it cannot be carried."""
        source = image_of(self.scene.gltf, info)
        if isinstance(source, str):
            self.notes.append(f"{what}: {source}: left out")
            return None
        if source not in self.images:
            try:
                blob, suffix = package_image(self.scene, source)
            except TextureError as exc:      # a missing or broken image costs its texture, not the animation
                self.notes.append(f"{what}: {exc}: left out")
                self.images[source] = None
                return None
            image = (self.scene.gltf.images or [])[source]
            name = f"{source}_{self.prim_name(image.name or 'image')}{suffix}"
            self.texture_dir.mkdir(parents=True, exist_ok=True)
            (self.texture_dir / name).write_bytes(blob)
            self.images[source] = f"./{TEXTURES}/{name}"
        return self.images[source]

    def _texture(self, path: Sdf.Path, info, what: str, color_space: str, scale, bias=None) -> UsdShade.Shader | None:
        """A UsdUVTexture for glTF texture info `info`, reading `st`; None when there is none to carry."""
        if info is None or not isinstance(getattr(info, "index", None), int) or self.texture_dir is None:
            return None
        if (info.extensions or {}).get("KHR_texture_transform"):
            self.notes.append(f"{what}: KHR_texture_transform is not carried (the texture is placed untransformed)")
        asset = self._image(info, what)
        if asset is None:
            return None
        reader_path = path.GetParentPath().AppendChild("st")
        if not self.stage.GetPrimAtPath(reader_path):
            reader = UsdShade.Shader.Define(self.stage, reader_path)
            reader.CreateIdAttr("UsdPrimvarReader_float2")
            reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
            reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
        reader = UsdShade.Shader.Get(self.stage, reader_path)
        texture = UsdShade.Shader.Define(self.stage, path)
        texture.CreateIdAttr("UsdUVTexture")
        texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(asset))
        texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(color_space)
        samplers = self.scene.gltf.samplers or []
        s = self._sampler(info.index)
        wrap_s = wrap_t = gl.REPEAT
        if s is not None and 0 <= s < len(samplers):
            wrap_s, wrap_t = samplers[s].wrapS or gl.REPEAT, samplers[s].wrapT or gl.REPEAT
        texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set(_WRAP.get(wrap_s, "repeat"))
        texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set(_WRAP.get(wrap_t, "repeat"))
        texture.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*map(float, scale)))
        if bias is not None:
            texture.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*map(float, bias)))
        for output, kind in (("rgb", Sdf.ValueTypeNames.Float3), ("r", Sdf.ValueTypeNames.Float),
                             ("g", Sdf.ValueTypeNames.Float), ("b", Sdf.ValueTypeNames.Float),
                             ("a", Sdf.ValueTypeNames.Float)):
            texture.CreateOutput(output, kind)
        return texture

    def _sampler(self, texture_index: int) -> int | None:
        textures = self.scene.gltf.textures or []
        s = textures[texture_index].sampler if 0 <= texture_index < len(textures) else None
        return s if isinstance(s, int) else None

    def _define(self, path: Sdf.Path, m: gl.Material, index: int) -> UsdShade.Material:
        what = f"material {index} ({m.name!r})" if m.name else f"material {index}"
        material = UsdShade.Material.Define(self.stage, path)
        surface = UsdShade.Shader.Define(self.stage, path.AppendChild("Surface"))
        surface.CreateIdAttr("UsdPreviewSurface")
        material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        pbr = m.pbrMetallicRoughness or gl.PbrMetallicRoughness()
        base = [float(c) for c in (pbr.baseColorFactor or (1.0, 1.0, 1.0, 1.0))]
        metallic = 1.0 if pbr.metallicFactor is None else float(pbr.metallicFactor)
        roughness = 1.0 if pbr.roughnessFactor is None else float(pbr.roughnessFactor)

        def connect(name: str, kind, shader: UsdShade.Shader, output: str) -> None:
            surface.CreateInput(name, kind).ConnectToSource(shader.ConnectableAPI(), output)

        color = self._texture(path.AppendChild("BaseColor"), pbr.baseColorTexture, f"{what} base colour", "sRGB", base)
        if color is not None:
            connect("diffuseColor", Sdf.ValueTypeNames.Color3f, color, "rgb")
        else:
            surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*base[:3]))
        mode = m.alphaMode or gl.OPAQUE
        if mode in (gl.BLEND, gl.MASK):
            if color is not None:
                connect("opacity", Sdf.ValueTypeNames.Float, color, "a")
            else:
                surface.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(base[3])
            if mode == gl.MASK:
                cutoff = 0.5 if m.alphaCutoff is None else float(m.alphaCutoff)
                surface.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(cutoff)
        mr = self._texture(path.AppendChild("MetallicRoughness"), pbr.metallicRoughnessTexture,
                           f"{what} metallic-roughness", "raw", (1.0, roughness, metallic, 1.0))
        if mr is not None:
            connect("metallic", Sdf.ValueTypeNames.Float, mr, "b")
            connect("roughness", Sdf.ValueTypeNames.Float, mr, "g")
        else:
            surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(metallic)
            surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(roughness)
        n = m.normalTexture
        strength = 1.0 if n is None or n.scale is None else float(n.scale)
        normal = self._texture(path.AppendChild("Normal"), n, f"{what} normal map", "raw",
                               (2.0 * strength, 2.0 * strength, 2.0, 1.0), (-strength, -strength, -1.0, 0.0))
        if normal is not None:
            connect("normal", Sdf.ValueTypeNames.Normal3f, normal, "rgb")
        emissive = [float(c) for c in (m.emissiveFactor or (0.0, 0.0, 0.0))]
        glow = self._texture(path.AppendChild("Emissive"), m.emissiveTexture, f"{what} emissive", "sRGB",
                             (*emissive, 1.0))
        if glow is not None:
            connect("emissiveColor", Sdf.ValueTypeNames.Color3f, glow, "rgb")
        elif any(emissive) and m.emissiveTexture is None:    # a factor alone, not one meant to scale an image
            surface.CreateInput("emissiveColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*emissive))
        occlusion = self._texture(path.AppendChild("Occlusion"), m.occlusionTexture, f"{what} occlusion", "raw",
                                  (1.0, 1.0, 1.0, 1.0))
        if occlusion is not None:
            connect("occlusion", Sdf.ValueTypeNames.Float, occlusion, "r")
        return material


def _dress_mesh(stage: Usd.Stage, mesh: UsdGeom.Mesh, source: GltfMesh, materials: _Materials) -> None:
    """`source`'s texture coordinates and materials on the Mesh prim made from it (same vertices, same faces)."""
    materials.notes.extend(source.uv_problems)
    if source.uvs is not None:
        st = np.c_[source.uvs[:, 0], 1.0 - source.uvs[:, 1]].astype(np.float32)
        UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                UsdGeom.Tokens.vertex).Set(Vt.Vec2fArray.FromNumpy(st))
    used = [m for m, _ in source.surfaces]
    if any(materials.double_sided(m) for m in used):
        mesh.CreateDoubleSidedAttr(True)
    if len(set(used)) == 1:
        made = materials.material(used[0])
        if made is not None:
            UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(made)
        return
    binding = UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
    first, ranges = 0, {}
    for m, count in source.surfaces:
        ranges.setdefault(m, []).append(np.arange(first, first + count, dtype=np.int32))
        first += count
    for k, (m, parts) in enumerate(ranges.items()):
        made = materials.material(m)
        if made is None:
            continue
        subset = binding.CreateMaterialBindSubset(f"surface_{k}", Vt.IntArray.FromNumpy(np.concatenate(parts)),
                                                  UsdGeom.Tokens.face)
        UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(made)


def dress_gltf_scene(stage: Usd.Stage, root: Sdf.Path, character: Character, part_prims: list[Sdf.Path],
                     texture_dir: Path | None, prim_name, define_static, define_driven,
                     scene: GltfScene | None = None) -> list[str]:
    """Add to `stage` what the glTF scene `character.source` holds beside the driven meshes (see the module doc):
    `part_prims[k]` is the Mesh prim of `character.parts[k]`; `define_static(path, points, faces, node=, skin=,
    source=)` makes the Mesh prim of a mesh no target moves (placed at rest; its node, that node's skin or None, and
    the mesh as stored), `define_driven(path, points, faces, shape names, deltas, node=)` one the SkelAnimation
    drives (a driven mesh's other instances: a mesh two nodes show, such as one eye mesh for both eyes). Returns
    notes on what could not be carried. `scene`: the file already read (`GltfScene(character.source)`), else it is
    read here."""
    notes: list[str] = []
    scene = scene if scene is not None else GltfScene(character.source)
    materials = _Materials(stage, root, scene, texture_dir, prim_name, notes)
    scale = np.float32(1000.0 / float(character.mm_per_unit))    # the scene's metres in the character's unit
    driven = {part.mesh for part in character.parts}
    taken = {child.GetName() for child in stage.GetPrimAtPath(root).GetChildren()}

    def free(label: str) -> Sdf.Path:
        name = base = prim_name(label)
        k = 1
        while name in taken:
            name, k = f"{base}_{k}", k + 1
        taken.add(name)
        return root.AppendChild(name)

    sources = {}
    for part, path in zip(character.parts, part_prims):
        source = scene.placed_mesh(part.mesh)[0]     # with its targets: primitives share vertices as they did
        if len(source.neutral) != part.n_vertices:   # not the mesh the character was read from: leave it as is
            notes.append(f"{part.name}: the file's mesh has {len(source.neutral)} vertices, the character "
                         f"{part.n_vertices}: no materials")
            continue
        _dress_mesh(stage, UsdGeom.Mesh(stage.GetPrimAtPath(path)), source, materials)
        sources[part.mesh] = (part, source)
    placements, left_out = scene.other_placements(driven)
    if left_out:
        notes.append(left_out)
    for info, node in placements:
        if info.index in driven:       # another node showing a driven mesh: a Mesh the same weights drive
            if info.index not in sources:
                continue
            part, source = sources[info.index]
            _, neutral, deltas, _ = scene.placed_mesh(part.mesh, node)
            mesh = define_driven(free(scene.gltf.nodes[node].name or part.name), neutral * scale, source.faces,
                                 part.target_names, deltas * scale, node=node)
        else:
            try:
                source, neutral, _, _ = scene.placed_mesh(info.index, node, morph_targets=False)
            except RigError as exc:     # a mesh we cannot read (lines, points): the rest of the scene stays
                notes.append(f"{exc}: left out")
                continue
            # named as the object is in Blender and the engines: its node
            mesh = define_static(free(scene.gltf.nodes[node].name or info.label), neutral * scale, source.faces,
                                 node=node, skin=info.skin, source=source)
        _dress_mesh(stage, mesh, source, materials)
    return notes
