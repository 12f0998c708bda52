"""How a glTF character's driven meshes look, for previews: each face's material base colour and base-colour texture
(read through TEXCOORD_0) as a `render.raster.MeshTexture`, so the preview shows the user's avatar with its skin,
not a grey head.

Images are decoded once per preview with Pillow and reduced (area filter) to at most `MAX_TEXTURE_PX` on a side: a
preview panel is a few hundred pixels, and the avatar's 2048-px textures would cost 12 MB each for nothing. An
image larger than `MAX_IMAGE_PIXELS` when decoded (a decompression bomb is a small file), one Pillow cannot read
(KTX2), a texture read through TEXCOORD_1, and a file that cannot be read again are left out, each with a note; the
face then keeps its base colour. A character not read from a glTF scene, or a scene without materials, has no
texture (None): the preview keeps its vertex colours or grey.
"""

from __future__ import annotations

import io

import numpy as np

from visemeflow.render.raster import MeshTexture
from visemeflow.rig.character import Character
from visemeflow.rig.gltf import GltfScene, linear_to_srgb
from visemeflow.rig.model import RigError

__all__ = ["MAX_IMAGE_PIXELS", "MAX_TEXTURE_PX", "character_texture"]

MAX_TEXTURE_PX = 1024
MAX_IMAGE_PIXELS = 1 << 26     # 8192 x 8192


def _decode(blob: bytes, what: str, notes: list[str]) -> np.ndarray | None:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(blob)) as image:
            width, height = image.size
            if width * height > MAX_IMAGE_PIXELS:
                notes.append(f"{what} is {width}x{height} pixels, more than the {MAX_IMAGE_PIXELS} a preview decodes: "
                             "left out")
                return None
            image.draft("RGB", (MAX_TEXTURE_PX, MAX_TEXTURE_PX))        # JPEG: decoded at a reduced scale
            rgb = image.convert("RGB")
            rgb.thumbnail((MAX_TEXTURE_PX, MAX_TEXTURE_PX), Image.Resampling.BOX)
            return np.asarray(rgb, np.uint8)
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as exc:
        notes.append(f"{what} cannot be decoded ({type(exc).__name__}: {exc}): left out")
        return None


def character_texture(character: Character) -> tuple[MeshTexture | None, list[str]]:
    """The MeshTexture of `character`'s faces (see the module doc) and notes on what was left out."""
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
            if (info.texCoord or 0) != 0:
                notes.append(f"{what}: reads TEXCOORD_{info.texCoord}, which previews do not: left out")
                continue
            textures = scene.gltf.textures or []
            source = textures[info.index].source if 0 <= info.index < len(textures) else None
            if not isinstance(source, int):
                continue
            if source not in slot:
                try:
                    blob, _ = scene.image(source)
                    decoded = _decode(blob, f"{what} image {source}", notes)
                except RigError as exc:
                    notes.append(f"{what}: {exc}: left out")
                    decoded = None
                slot[source] = -1 if decoded is None else len(images)
                if decoded is not None:
                    images.append(decoded)
            face_image[rows] = slot[source]
    if row != len(face_image):
        return None, ["the file's faces no longer match the character: the preview shows no materials"]
    return MeshTexture(uv=uv, face_image=face_image, face_color=face_color, images=tuple(images)), notes
