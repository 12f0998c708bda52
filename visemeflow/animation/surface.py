"""How a glTF character looks in a preview: its whole scene, not the driven meshes alone. `preview_scene` gives the
vertices a panel draws each frame (the driven meshes as the curves move them, the other nodes that show a driven
mesh, moved with it, and the meshes no target moves, a body, hair, placed as the file places them), their faces, and
each face's material base colour and base-colour texture (read through TEXCOORD_0) as a `render.raster.MeshTexture`,
so the preview shows the user's avatar with its skin and hair, not a grey head alone.

Images are decoded once per preview with Pillow and reduced (area filter) to at most `textures.MAX_TEXTURE_PX` on a
side: a preview panel is a few hundred pixels, and the avatar's 2048-px textures would cost 12 MB each for nothing.
An image larger than `textures.MAX_IMAGE_PIXELS` when decoded (a decompression bomb is a small file), one Pillow
cannot read (KTX2, corrupt data), a texture read through TEXCOORD_1, and a file that cannot be read again are left
out, each with a note; the face then keeps its base colour. WebP textures (`EXT_texture_webp`) are drawn. A character
not read from a glTF scene has its own vertices alone and no texture: the preview keeps its vertex colours or grey.
The static meshes are drawn once per preview, as the panels' backdrop (`render.raster.render_backdrop`): each frame
costs what the driven meshes cost.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from visemeflow.animation.textures import TextureError, image_of, image_pixels
from visemeflow.render.raster import MeshTexture
from visemeflow.rig.character import Character
from visemeflow.rig.gltf import GltfMesh, GltfScene, linear_to_srgb
from visemeflow.rig.model import RigError

__all__ = ["PreviewScene", "StaticMeshes", "preview_scene"]


@dataclass(frozen=True, eq=False)
class StaticMeshes:
    """The meshes of a scene that no target moves, joined and placed (a preview draws them once, as its backdrop)."""

    vertices: np.ndarray
    """(S, 3) float32 in the character's unit."""
    faces: np.ndarray
    """(G, 3) int64 into `vertices`."""
    texture: MeshTexture | None


@dataclass(frozen=True, eq=False)
class PreviewScene:
    """What a preview panel draws of a character (see the module doc). Rows of `vertices(driven)`: the character's
    own vertices, then each extra instance of a driven mesh; `static` apart, drawn once."""

    faces: np.ndarray
    """(F, 3) int64 triangles into the rows of `vertices`: the character's faces first, in its order."""
    texture: MeshTexture | None
    """Per face of `faces` (None: no materials; vertex colours or grey)."""
    colors: np.ndarray | None
    """(N, 3) display colours per row of `vertices`, or None."""
    instances: tuple[tuple[int, int, np.ndarray, np.ndarray], ...] = ()
    """(start, stop, linear (3, 3), offset (3,)): the character's vertices start..stop as another node shows them,
    v -> linear @ v + offset (in the character's unit)."""
    static: StaticMeshes | None = None
    """The meshes no target moves (None: there are none)."""

    def vertices(self, driven: np.ndarray) -> np.ndarray:
        """(N, 3): one frame's driven vertices (V, 3) followed by their other instances."""
        if not self.instances:
            return driven
        return np.concatenate([driven] + [driven[a:b] @ linear.T.astype(driven.dtype) + offset.astype(driven.dtype)
                                          for a, b, linear, offset in self.instances])


class _Looks:
    """Texture coordinates, per-face base colours and images, gathered mesh by mesh."""

    def __init__(self, scene: GltfScene, notes: list[str]):
        self.scene, self.notes = scene, notes
        self.materials = scene.gltf.materials or []
        self.uv: list[np.ndarray] = []
        self.face_image: list[np.ndarray] = []
        self.face_color: list[np.ndarray] = []
        self.images: list[np.ndarray] = []
        self.slot: dict[int, int] = {}          # glTF image index -> position in `images` (-1: left out)

    def add(self, mesh: GltfMesh) -> None:
        """`mesh`'s vertices' coordinates and its faces' looks, in the order of its `faces`."""
        self.notes.extend(n for n in mesh.uv_problems if n not in self.notes)
        self.uv.append(mesh.uvs if mesh.uvs is not None else np.zeros((len(mesh.neutral), 2), np.float32))
        n_faces = len(mesh.faces)
        image = np.full(n_faces, -1, np.int64)
        color = np.ones((n_faces, 3), np.float64)
        row = 0
        for material, count in mesh.surfaces:
            rows = slice(row, row + count)
            row += count
            if not isinstance(material, int) or not 0 <= material < len(self.materials):
                continue
            m = self.materials[material]
            pbr = m.pbrMetallicRoughness
            factor = (pbr.baseColorFactor if pbr is not None and pbr.baseColorFactor else None) or (1, 1, 1, 1)
            color[rows] = linear_to_srgb(np.asarray(factor[:3], np.float32))
            info = pbr.baseColorTexture if pbr is not None else None
            if info is None or not isinstance(info.index, int) or mesh.uvs is None:
                continue
            image[rows] = self._image(info, f"material {material} ({m.name or 'unnamed'}) base colour")
        self.face_image.append(image)
        self.face_color.append(color)

    def _image(self, info, what: str) -> int:
        source = image_of(self.scene.gltf, info)
        if isinstance(source, str):
            self.notes.append(f"{what}: {source}: left out")
            return -1
        if source not in self.slot:
            try:
                self.images.append(image_pixels(self.scene, source))
                self.slot[source] = len(self.images) - 1
            except TextureError as exc:
                self.notes.append(f"{what}: {exc}: left out")
                self.slot[source] = -1
        return self.slot[source]

    def texture(self, meshes: slice) -> MeshTexture | None:
        """The MeshTexture of the meshes added `meshes` (by their order of `add`); None without materials."""
        if not self.materials:
            return None
        return MeshTexture(uv=np.concatenate(self.uv[meshes]).astype(np.float32),
                           face_image=np.concatenate(self.face_image[meshes]),
                           face_color=np.concatenate(self.face_color[meshes]), images=tuple(self.images))


def _own(character: Character) -> PreviewScene:
    return PreviewScene(np.asarray(character.faces, np.int64), None, character.vertex_colors)


@functools.lru_cache(maxsize=8)
def preview_scene(character: Character) -> tuple[PreviewScene, tuple[str, ...]]:
    """The PreviewScene of `character` (see the module doc) and notes on what was left out; made once per character
    object (`animate` previews every utterance of a run on the same one)."""
    notes: list[str] = []
    if not character.parts or not character.source:
        return _own(character), ()
    try:
        scene = GltfScene(character.source)
    except RigError as exc:
        return _own(character), (f"{exc}: the preview shows no materials and no other meshes",)
    looks = _Looks(scene, notes)
    scale = 1000.0 / float(character.mm_per_unit)      # the scene's metres in the character's unit
    faces = [np.asarray(character.faces, np.int64)]
    colors = [character.vertex_colors] if character.vertex_colors is not None else []
    n_rows = character.n_vertices
    instances = []
    read: dict[int, GltfMesh] = {}       # the driven meshes, read once: their other instances look the same
    try:
        for part in character.parts:
            mesh = read[part.mesh] = scene.placed_mesh(part.mesh)[0]
            if len(mesh.neutral) != part.n_vertices or len(mesh.faces) != int(
                    ((character.faces >= part.start) & (character.faces < part.stop)).all(axis=1).sum()):
                return _own(character), (f"{part.name}: the file's mesh no longer matches the character: the preview "
                                         "shows no materials and no other meshes",)
            looks.add(mesh)
        parts = {part.mesh: part for part in character.parts}
        placements, left_out = scene.other_placements(parts)
        if left_out:
            notes.append(f"the preview: {left_out}")
        moving = None
        static, static_faces, n_static = [], [], 0
        for info, node in placements:
            part = parts.get(info.index)
            if part is not None:           # another node showing a driven mesh: moved with it
                mesh = read[part.mesh]
                move = scene.world_matrix(node) @ np.linalg.inv(scene.world_matrix(part.nodes[0]))
                instances.append((part.start, part.stop, move[:3, :3].copy(), move[:3, 3] * scale))
                faces.append(mesh.faces.astype(np.int64) + n_rows)
                if colors:
                    colors.append(character.vertex_colors[part.start:part.stop])
                n_rows += part.n_vertices
                looks.add(mesh)
                continue
            if moving is None:
                moving = len(looks.uv)
            try:
                mesh, neutral, _, _ = scene.placed_mesh(info.index, node, morph_targets=False)
            except RigError as exc:     # a mesh we cannot read (lines, points): the rest of the scene stays
                notes.append(f"{exc}: left out of the preview")
                continue
            static.append(neutral * np.float32(scale))
            static_faces.append(mesh.faces.astype(np.int64) + n_static)
            n_static += len(neutral)
            looks.add(mesh)
        moving = len(looks.uv) if moving is None else moving
    except RigError as exc:
        return _own(character), (f"{exc}: the preview shows no materials and no other meshes",)
    others = StaticMeshes(np.concatenate(static).astype(np.float32), np.concatenate(static_faces),
                          looks.texture(slice(moving, None))) if static else None
    return PreviewScene(np.concatenate(faces), looks.texture(slice(0, moving)),
                        None if not colors else np.concatenate(colors).astype(np.float32), tuple(instances),
                        others), tuple(notes)
