"""A glTF character's texture images as the exports and the preview need them, and what a user should be told about
the ones that cannot be carried.

- `texture_image(gltf, texture)`: the image a texture shows: its `source`, or the one an image-format extension names
  (`EXT_texture_webp`, `KHR_texture_basisu`, `MSFT_texture_dds`: Ready Player Me and gltf-transform write WebP
  textures that way, with no plain `source`).
- `package_image(scene, image)`: PNG or JPEG bytes for a USDZ (the only image formats a USD package holds): PNG and
  JPEG as they are once Pillow has checked they decode, anything else Pillow reads (WebP, ...) converted to PNG;
  `TextureError` saying why otherwise (missing file, corrupt data, KTX2).
- `image_pixels(scene, image)`: (H, W, 3) uint8 for the preview, reduced to `MAX_TEXTURE_PX` a side (area filter);
  an image larger than `MAX_IMAGE_PIXELS` decoded is refused before it is decoded (a decompression bomb is a small
  file).
- `appearance_notes(character)`: one line per image, texture coordinate set or mesh instance that the USD, the USDZ
  or the preview cannot show as the file does; `animate`/`speak` put them among the package's warnings, so a user
  who wanted the whole avatar textured learns why a part is not.
"""

from __future__ import annotations

import functools
import io

import numpy as np

from visemeflow.rig.gltf import GltfScene
from visemeflow.rig.model import RigError

__all__ = ["MAX_IMAGE_PIXELS", "MAX_TEXTURE_PX", "TextureError", "appearance_notes", "image_of", "image_pixels",
           "package_image", "texture_image"]

MAX_TEXTURE_PX = 1024
MAX_IMAGE_PIXELS = 1 << 26     # 8192 x 8192
_IMAGE_EXTENSIONS = ("EXT_texture_webp", "KHR_texture_basisu", "MSFT_texture_dds")
_TEXTURE_SLOTS = (("base colour", "pbrMetallicRoughness", "baseColorTexture"),
                  ("metallic-roughness", "pbrMetallicRoughness", "metallicRoughnessTexture"),
                  ("normal map", None, "normalTexture"), ("emissive", None, "emissiveTexture"),
                  ("occlusion", None, "occlusionTexture"))


class TextureError(ValueError):
    """An image that cannot be carried; the message says which and why."""


def texture_image(gltf, texture: int) -> int | None:
    """The image index texture `texture` shows (its `source`, else an image extension's), or None."""
    textures = gltf.textures or []
    if not isinstance(texture, int) or not 0 <= texture < len(textures):
        return None
    t = textures[texture]
    if isinstance(t.source, int):
        return t.source
    for name in _IMAGE_EXTENSIONS:
        source = ((t.extensions or {}).get(name) or {}).get("source")
        if isinstance(source, int):
            return source
    return None


def image_of(gltf, info) -> int | str:
    """The image a material's texture info (`baseColorTexture`, ...) shows, or why none can be: it reads a second UV
    set (only TEXCOORD_0 is read) or its texture names no image."""
    if (info.texCoord or 0) != 0:
        return f"reads TEXCOORD_{info.texCoord}; only TEXCOORD_0 is carried"
    image = texture_image(gltf, info.index)
    return image if image is not None else f"texture {info.index} names no image visemeflow can read"


def _open(scene: GltfScene, image: int):
    """(the image's bytes, its suffix, a Pillow image opened lazily on them)."""
    from PIL import Image, UnidentifiedImageError

    try:
        blob, suffix = scene.image(image)
    except RigError as exc:
        raise TextureError(f"image {image}: {str(exc).removeprefix(f'{scene.path}: ')}") from None
    try:
        opened = Image.open(io.BytesIO(blob))
    except UnidentifiedImageError:   # Pillow's message names its in-memory buffer (<_io.BytesIO object at 0x...>)
        raise TextureError(f"image {image} ({suffix.lstrip('.').upper()}) cannot be decoded (not an image Pillow "
                           f"knows; {len(blob)} bytes starting {blob[:8].hex(' ')})") from None
    except (OSError, ValueError) as exc:
        raise TextureError(f"image {image} ({suffix.lstrip('.').upper()}) cannot be decoded ({exc})") from None
    width, height = opened.size
    if width * height > MAX_IMAGE_PIXELS:
        raise TextureError(f"image {image} is {width}x{height} pixels, more than the {MAX_IMAGE_PIXELS} decoded "
                           "pixels visemeflow reads")
    return blob, suffix, opened


def package_image(scene: GltfScene, image: int) -> tuple[bytes, str]:
    """PNG or JPEG bytes and their suffix for a USD package (see the module doc); TextureError otherwise."""
    from PIL import Image

    blob, suffix, opened = _open(scene, image)
    try:
        with opened:
            kind = opened.format
            if kind in ("PNG", "JPEG"):
                opened.verify()                       # the whole stream, without keeping the pixels
                return blob, ".png" if kind == "PNG" else ".jpg"
            out = io.BytesIO()
            opened.convert("RGBA" if "A" in opened.getbands() else "RGB").save(out, format="PNG")
            return out.getvalue(), ".png"
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise TextureError(f"image {image} cannot be decoded ({type(exc).__name__}: {exc})") from None


def image_pixels(scene: GltfScene, image: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB, at most `MAX_TEXTURE_PX` a side; TextureError otherwise."""
    from PIL import Image

    _, _, opened = _open(scene, image)
    try:
        with opened:
            opened.draft("RGB", (MAX_TEXTURE_PX, MAX_TEXTURE_PX))        # JPEG: decoded at a reduced scale
            rgb = opened.convert("RGB")
            rgb.thumbnail((MAX_TEXTURE_PX, MAX_TEXTURE_PX), Image.Resampling.BOX)
            return np.asarray(rgb, np.uint8)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise TextureError(f"image {image} cannot be decoded ({type(exc).__name__}: {exc})") from None


def _missing(scene: GltfScene, uri: str) -> bool:
    from visemeflow.rig.gltf import resolve_gltf_uri

    try:
        return not resolve_gltf_uri(scene.path, uri).is_file()
    except ValueError:
        return False


def _texture_infos(material):
    for label, holder, slot in _TEXTURE_SLOTS:
        owner = getattr(material, holder) if holder else material
        info = getattr(owner, slot, None) if owner is not None else None
        if info is not None and isinstance(getattr(info, "index", None), int):
            yield label, info


@functools.lru_cache(maxsize=16)
def appearance_notes(character) -> tuple[str, ...]:
    """What the USD, USDZ and preview of a glTF `character` cannot show as its file does (see the module doc); ()
    for other characters. Computed once per character object."""
    if not character.parts or not character.source:
        return ()
    try:
        scene = GltfScene(character.source)
    except RigError as exc:
        return (str(exc),)
    materials = scene.gltf.materials or []
    used = {}
    for info in scene.meshes:
        if not info.nodes:
            continue
        for primitive in scene.gltf.meshes[info.index].primitives or []:
            if isinstance(primitive.material, int) and 0 <= primitive.material < len(materials):
                used.setdefault(primitive.material, info.label)
    notes, seen = [], set()
    for index, mesh_label in sorted(used.items()):
        m = materials[index]
        what = f"material {m.name or index!r} ({mesh_label})"
        for label, info in _texture_infos(m):
            image = image_of(scene.gltf, info)
            if isinstance(image, str):
                notes.append(f"{what} {label}: {image}")
                continue
            if image in seen:
                continue
            seen.add(image)
            try:
                package_image(scene, image)
            except TextureError as exc:
                uri = (scene.gltf.images or [])[image].uri
                if isinstance(uri, str) and not uri.startswith("data:") and _missing(scene, uri):
                    notes.append(f"{what} {label}: image {image} ({uri}) is not beside {scene.path.name}: the GLB "
                                 "holds a grey 1-pixel stand-in, the USD and the preview leave it out")
                else:
                    notes.append(f"{what} {label}: {exc}: left out of the USD and the preview")
    return tuple(notes)
