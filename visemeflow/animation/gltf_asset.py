"""The user's own glTF asset back, with our animation added: `write_character_glb`.

A character read from a .glb / .gltf scene (`gltf.read_character_glb`, `Character.parts`) is exported as that whole
scene: every mesh, material, texture, image, skin, camera, light, extension, node of the hierarchy and existing
animation stays, byte for byte and JSON value for JSON value, and one new animation is added first (index 0: the
one Blender's importer makes active and model-viewer's autoplay plays; the file's own follow in their order, and no
other part of glTF refers to an animation by index), named by the utterance, with one `weights` channel per node that instances a driven mesh (nodes sharing a mesh share its
sampler). Each sampler is LINEAR; its input is the frame times k / fps (float32, with the min/max the specification
asks), its output the frames' weights of that mesh's own targets in that mesh's own order (a teeth mesh with 12
targets gets 12 columns, whatever the head has).

How: the document is edited as plain JSON (not through a typed model, which could drop or reorder what it does not
know), the new binary data (frame times, weights, 4-byte aligned) is appended to the end of buffer 0, the GLB's
binary chunk, and `buffers[0].byteLength` is updated; new buffer views and accessors are appended to their
arrays, so every existing index of them stays valid. Only the buffer entry (its new length) changes.

A `.gltf` (JSON) input, or a GLB whose buffers live in other files, is written as a self-contained GLB: the buffers
are concatenated into the binary chunk (each 16-byte aligned; buffer views re-pointed with their offsets shifted),
images stored as files get a buffer view and a `mimeType` in place of their `uri`; data: URIs are decoded as
buffers and left as they are for images. Only files inside the glTF's folder are read (`rig.gltf.resolve_gltf_uri`:
no scheme, no absolute path, no way out through `..`, percent-encoding or a link), each declared byteLength must
fit its data, and the GLB written may hold at most `MAX_FILE_BYTES`.

Characters that are not glTF scenes (npz, mesh folders, our rigs, characters built in memory) are written by
`gltf.write_glb`, a new single-mesh GLB.
"""

from __future__ import annotations

import io
import json
import os
import struct
import urllib.parse
from pathlib import Path

import numpy as np

from visemeflow.rig.character import Character, CharacterError
from visemeflow.animation.gltf import GLTF_SUFFIXES, _check_animation, write_glb
from visemeflow.atomic import atomic_path
from visemeflow.rig.gltf import MAX_FILE_BYTES, read_gltf_uri

__all__ = ["write_asset_glb", "write_character_glb"]

_MAGIC = b"glTF"
_JSON = 0x4E4F534A
_BIN = 0x004E4942
_FLOAT = 5126
_LINEAR = "LINEAR"
_MIME = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".webp": "image/webp",
         ".ktx2": "image/ktx2"}


def write_character_glb(path: str | os.PathLike, character: Character, weights, fps: float, *,
                        name: str | None = None) -> Path:
    """The GLB of `character` playing (T, S) `weights` at `fps`: its own asset with the clip added when it was read
    from a glTF scene (`write_asset_glb`), else a new single-mesh GLB (`gltf.write_glb`)."""
    if character.parts and Path(character.source).suffix.lower() in GLTF_SUFFIXES:
        return write_asset_glb(path, character, weights, fps, name=name)
    return write_glb(path, character, weights, fps, name=name)


def _read_document(source: Path) -> tuple[dict, bytes | None]:
    """(the JSON document, the GLB binary chunk or None)."""
    try:
        with open(source, "rb") as handle:
            size = os.fstat(handle.fileno()).st_size
            if size > MAX_FILE_BYTES:
                raise CharacterError(f"{source}: {size} bytes, more than the {MAX_FILE_BYTES} bytes a character "
                                     "file may have")
            data = handle.read(size)
    except OSError as exc:
        raise CharacterError(f"{source}: the character's file cannot be read to write its asset back "
                             f"({exc.strerror or exc})") from None
    try:
        if data[:4] != _MAGIC:
            return json.loads(data.decode("utf-8-sig")), None
        length = struct.unpack_from("<I", data, 8)[0]
        document, binary, offset = None, None, 12
        while offset + 8 <= min(length, len(data)):
            size, kind = struct.unpack_from("<II", data, offset)
            chunk = data[offset + 8: offset + 8 + size]
            if kind == _JSON and document is None:
                document = json.loads(chunk.decode("utf-8"))
            elif kind == _BIN and binary is None:
                binary = chunk
            offset += 8 + size
        if not isinstance(document, dict):
            raise ValueError("no JSON chunk")
        return document, binary
    except (ValueError, UnicodeDecodeError, struct.error) as exc:
        raise CharacterError(f"{source}: not a readable glTF 2.0 / GLB file ({exc})") from None


def _external(source: Path, uri, what: str) -> bytes:
    """The bytes of a data: URI or of a file inside the glTF's folder (`rig.gltf.read_gltf_uri`)."""
    if not isinstance(uri, str):
        raise CharacterError(f"{source}: {what}: its uri must be a string, got {uri!r}")
    try:
        return read_gltf_uri(source, uri)
    except ValueError as exc:
        raise CharacterError(f"{source}: {what}: {exc}") from None
    except OSError as exc:
        raise CharacterError(f"{source}: {what} ({uri}) cannot be read: {exc.strerror or exc}") from None


def _stand_in_png() -> bytes:
    """A 1x1 mid-grey PNG: what the GLB holds for a texture file that was missing beside the .gltf
    (`textures.appearance_notes` tells the user)."""
    from PIL import Image

    out = io.BytesIO()
    Image.new("RGB", (1, 1), (128, 128, 128)).save(out, format="PNG")
    return out.getvalue()


def _fits(source: Path, blob: bytearray, adding: int, what: str) -> None:
    if len(blob) + adding > MAX_FILE_BYTES:
        raise CharacterError(f"{source}: with {what} the exported GLB would hold more than {MAX_FILE_BYTES} bytes")


def _one_buffer(source: Path, document: dict, binary: bytes | None) -> bytearray:
    """The bytes of the GLB's buffer 0 once every buffer and image file is inside it (see the module)."""
    buffers = document.get("buffers") or []
    if not buffers:
        return bytearray()
    blob, starts = bytearray(), []
    for k, buffer in enumerate(buffers):
        if not isinstance(buffer, dict):
            raise CharacterError(f"{source}: buffer {k} is not a JSON object")
        if "uri" in buffer:
            data = _external(source, buffer["uri"], f"buffer {k}")
        elif k == 0 and binary is not None:
            data = binary
        else:
            raise CharacterError(f"{source}: buffer {k} has no uri and is not the GLB binary chunk")
        declared = buffer.get("byteLength")
        if not isinstance(declared, int) or not 0 <= declared <= len(data):
            raise CharacterError(f"{source}: buffer {k} declares {declared!r} bytes (byteLength) but its data "
                                 f"holds {len(data)}")
        if len(buffers) == 1 and "uri" not in buffer:
            return bytearray(data[:declared])
        blob += bytes(-len(blob) % 16)
        _fits(source, blob, declared, f"buffer {k}")
        starts.append(len(blob))
        blob += data[:declared]
    for view in document.get("bufferViews") or []:
        view["byteOffset"] = view.get("byteOffset", 0) + starts[view["buffer"]]
        view["buffer"] = 0
    for k, image in enumerate(document.get("images") or []):
        uri = image.get("uri") if isinstance(image, dict) else None
        if uri is None or (isinstance(uri, str) and uri.startswith("data:")):
            continue
        try:
            data = read_gltf_uri(source, uri) if isinstance(uri, str) else _external(source, uri, f"image {k}")
            mime = image.get("mimeType") or _MIME.get(Path(urllib.parse.unquote(uri)).suffix.lower())
        except OSError:     # a texture file not copied beside the .gltf: the animation is still wanted
            data, mime = _stand_in_png(), "image/png"
            image["name"] = f"{image.get('name') or uri} (missing: a grey stand-in)"
        except ValueError as exc:
            raise CharacterError(f"{source}: image {k}: {exc}") from None
        _fits(source, blob, len(data) + 3, f"image {k}")
        if mime is None:
            raise CharacterError(f"{source}: image {k} ({uri}): unknown image type; expected "
                                 f"{', '.join(_MIME)}")
        blob += bytes(-len(blob) % 4)
        document.setdefault("bufferViews", []).append({"buffer": 0, "byteOffset": len(blob),
                                                       "byteLength": len(data)})
        blob += data
        del image["uri"]
        image["bufferView"] = len(document["bufferViews"]) - 1
        image["mimeType"] = mime
    document["buffers"] = [{"byteLength": len(blob)}]
    return blob


_COMPONENTS = {np.dtype("float32"): 5126, np.dtype("uint8"): 5121, np.dtype("uint16"): 5123}
_TYPES = {1: "SCALAR", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


def _append_array(document: dict, blob: bytearray, values: np.ndarray, bounds: bool = False,
                  target: int | None = None) -> int:
    """Append (count, k) `values` (float32, uint8 or uint16; k 1, 3, 4 or 16: SCALAR, VEC3, VEC4, MAT4 as stored, a
    matrix column-major) as a buffer view (4-byte aligned, with `target` when given) and an accessor; its index."""
    data = np.ascontiguousarray(values)
    data = data.astype(data.dtype.newbyteorder("<"), copy=False)
    width = 1 if data.ndim == 1 else data.shape[1]
    blob += bytes(-len(blob) % 4)
    views = document.setdefault("bufferViews", [])
    view = {"buffer": 0, "byteOffset": len(blob), "byteLength": data.nbytes}
    if target is not None:
        view["target"] = target
    views.append(view)
    blob += data.tobytes()
    accessor = {"bufferView": len(views) - 1, "componentType": _COMPONENTS[data.dtype.newbyteorder("=")],
                "count": int(len(data)), "type": _TYPES[width]}
    if bounds:
        flat = data.reshape(len(data), -1)
        accessor["min"], accessor["max"] = flat.min(axis=0).tolist(), flat.max(axis=0).tolist()
    accessors = document.setdefault("accessors", [])
    accessors.append(accessor)
    return len(accessors) - 1


def _append(document: dict, blob: bytearray, values: np.ndarray, bounds: bool = False) -> int:
    """Append float32 SCALAR `values` as a buffer view (4-byte aligned) and an accessor; its index."""
    return _append_array(document, blob, np.asarray(values, np.float32).ravel(), bounds)


def _target_names(mesh: dict) -> list | None:
    for extras in [mesh.get("extras")] + [p.get("extras") for p in (mesh.get("primitives") or [])[:1]]:
        if isinstance(extras, dict) and isinstance(extras.get("targetNames"), list):
            return extras["targetNames"]
    return None


def _glb(document: dict, blob: bytes) -> bytes:
    """A GLB container: header, JSON chunk (space padded), BIN chunk (zero padded) when there is binary data."""
    text = json.dumps(document, ensure_ascii=False, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), _JSON) + text
    if blob:
        data = bytes(blob) + bytes(-len(blob) % 4)
        chunks += struct.pack("<II", len(data), _BIN) + data
    return _MAGIC + struct.pack("<II", 2, 12 + len(chunks)) + chunks


def write_asset_glb(path: str | os.PathLike, character: Character, weights, fps: float, *,
                    name: str | None = None) -> Path:
    """Write the scene `character` was read from, whole, with one new animation (named `name`, else the
    character's name) playing (T, S) `weights` (columns in `character.shape_names` order, frame k at k / fps) on
    each driven mesh's nodes, as a GLB at `path` (atomically); returns `path`. See the module for what is kept.

    CharacterError naming the file when it cannot be read back, no longer holds the driven meshes with the same
    target names (changed since it was loaded), or no node instances a driven mesh; ValueError for bad weights."""
    path = Path(path)
    source = Path(character.source)
    times, w = _check_animation(character, weights, fps)
    document, binary = _read_document(source)
    meshes = document.get("meshes") or []
    for part in character.parts:
        if not 0 <= part.mesh < len(meshes) or tuple(_target_names(meshes[part.mesh]) or ()) != part.target_names:
            raise CharacterError(f"{source}: mesh {part.mesh} ({part.name}) is not the one loaded (its targets "
                                 "differ); the file changed since the character was read")
    if not any(part.nodes for part in character.parts):
        raise CharacterError(f"{source}: no node instances the driven meshes "
                             f"({', '.join(p.name for p in character.parts)}); a weights animation needs one")
    blob = _one_buffer(source, document, binary)
    frame_times = _append(document, blob, times, bounds=True)
    samplers, channels = [], []
    for part in character.parts:
        if not part.nodes:
            continue
        output = _append(document, blob, w[:, part.columns(character.shape_names)])
        samplers.append({"input": frame_times, "output": output, "interpolation": _LINEAR})
        channels += [{"sampler": len(samplers) - 1, "target": {"node": node, "path": "weights"}}
                     for node in part.nodes]
    # first: Blender's importer makes only the first animation active (the others go into muted NLA tracks: with an
    # avatar's idle clip first, our face did not move), and model-viewer's autoplay plays the first
    document.setdefault("animations", []).insert(0, {"name": name or character.name, "samplers": samplers,
                                                     "channels": channels})
    document.setdefault("buffers", [{}])
    if not document["buffers"]:
        document["buffers"].append({})
    document["buffers"][0]["byteLength"] = len(blob)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(_glb(document, blob))
    return path
