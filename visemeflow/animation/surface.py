"""How a glTF character's driven meshes look, for previews: each face's material base colour and base-colour texture
(read through TEXCOORD_0) as a `render.raster.MeshTexture`, so the preview shows the user's avatar with its skin,
not a grey head.

Images are decoded once per preview with Pillow and reduced (area filter) to at most `textures.MAX_TEXTURE_PX` on a
side: a preview panel is a few hundred pixels, and the avatar's 2048-px textures would cost 12 MB each for nothing.
An image larger than `textures.MAX_IMAGE_PIXELS` when decoded (a decompression bomb is a small file), one Pillow
cannot read (KTX2, corrupt data), a texture read through TEXCOORD_1, and a file that cannot be read again are left
out, each with a note; the face then keeps its base colour. WebP textures (`EXT_texture_webp`) are drawn. A character not read from a glTF scene, or a scene without materials, has no
texture (None): the preview keeps its vertex colours or grey.
"""

from __future__ import annotations

import functools

import numpy as np

from visemeflow.animation.textures import TextureError, image_of, image_pixels
from visemeflow.render.raster import MeshTexture
from visemeflow.rig.character import Character
from visemeflow.rig.gltf import GltfScene, linear_to_srgb
from visemeflow.rig.model import RigError

__all__ = ["character_texture"]


@functools.lru_cache(maxsize=8)
def character_texture(character: Character) -> tuple[MeshTexture | None, list[str]]:
    """The MeshTexture of `character`'s faces (see the module doc) and notes on what was left out; made once per
    character object (`animate` previews every utterance of a run on the same one)."""
    notes: list[str] = []
    if not character.parts or not character.source:
        return None, notes
    try:
        scene = GltfScene(character.source)
    except RigError as exc:
        return None, [f"{exc}: the preview shows no materials"]
    materials = scene.gltf.materials or []
    if not materials:
        return None, notes
    uv = np.zeros((character.n_vertices, 2), np.float32)
    face_image = np.full(len(character.faces), -1, np.int64)
    face_color = np.ones((len(character.faces), 3), np.float64)
    images: list[np.ndarray] = []
    slot: dict[int, int] = {}          # glTF image index -> position in `images` (-1: left out)
    row = 0
    for part in character.parts:
        try:
            mesh = scene.placed_mesh(part.mesh)[0]
        except RigError as exc:
            return None, [f"{exc}: the preview shows no materials"]
        n_faces = sum(count for _, count in mesh.surfaces)
        if len(mesh.neutral) != part.n_vertices or row + n_faces > len(face_image):
            return None, [f"{part.name}: the file's mesh no longer matches the character: the preview shows no "
                          "materials"]
        notes.extend(mesh.uv_problems)
        if mesh.uvs is not None:
            uv[part.start:part.stop] = mesh.uvs
        for material, count in mesh.surfaces:
            rows = slice(row, row + count)
            row += count
            if not isinstance(material, int) or not 0 <= material < len(materials):
                continue
            m = materials[material]
            pbr = m.pbrMetallicRoughness
            factor = (pbr.baseColorFactor if pbr is not None and pbr.baseColorFactor else None) or (1, 1, 1, 1)
            face_color[rows] = linear_to_srgb(np.asarray(factor[:3], np.float32))
            info = pbr.baseColorTexture if pbr is not None else None
            if info is None or not isinstance(info.index, int) or mesh.uvs is None:
                continue
            what = f"material {material} ({m.name or 'unnamed'}) base colour"
            source = image_of(scene.gltf, info)
            if isinstance(source, str):
                notes.append(f"{what}: {source}: left out")
                continue
            if source not in slot:
                try:
                    images.append(image_pixels(scene, source))
                    slot[source] = len(images) - 1
                except TextureError as exc:
                    notes.append(f"{what}: {exc}: left out")
                    slot[source] = -1
            face_image[rows] = slot[source]
    if row != len(face_image):
        return None, ["the file's faces no longer match the character: the preview shows no materials"]
    return MeshTexture(uv=uv, face_image=face_image, face_color=face_color, images=tuple(images)), notes
