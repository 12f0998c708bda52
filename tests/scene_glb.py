"""The glTF scene of tests/test_usd_scene.py and tests/test_preview.py, built with pygltflib: a head of two
primitives with two materials (textured, masked, normal-mapped skin; a plain double-sided one) and an eye mesh
that two nodes show."""

import io
from pathlib import Path

import numpy as np
import pygltflib as gl
from PIL import Image

TARGETS = ["jawOpen", "mouthClose", "mouthPressLeft", "mouthPressRight", "mouthFunnel"]
EYE_AT = ([-0.03, 1.6, 0.1], [0.03, 1.6, 0.1])


def _image(kind: str, rgb) -> bytes:
    out = io.BytesIO()
    Image.fromarray(np.full((4, 4, 3), rgb, np.uint8)).save(out, format=kind)
    return out.getvalue()


def make_scene(path: Path, eye_targets: bool = False) -> dict:
    """A head of two primitives with two materials (a textured, masked skin with a normal map, a WebP emissive map
    and an occlusion map whose KTX2 image nobody here decodes; a plain double-sided one) and an eye mesh without
    targets that two nodes instance."""
    g = gl.GLTF2(asset=gl.Asset(version="2.0"))
    blob = bytearray()

    def view(data: bytes) -> int:
        blob.extend(bytes(-len(blob) % 4))
        g.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data)))
        blob.extend(data)
        return len(g.bufferViews) - 1

    def accessor(array: np.ndarray, kind: str) -> int:
        array = np.ascontiguousarray(array)
        component = gl.FLOAT if array.dtype == np.float32 else gl.UNSIGNED_SHORT
        flat = array.reshape(len(array), -1)
        g.accessors.append(gl.Accessor(bufferView=view(array.tobytes()), componentType=component, count=len(array),
                                       type=kind, min=flat.min(0).tolist() if kind == gl.VEC3 else None,
                                       max=flat.max(0).tolist() if kind == gl.VEC3 else None))
        return len(g.accessors) - 1

    rng = np.random.default_rng(2)
    head = rng.normal(0, 0.05, (8, 3)).astype(np.float32) + np.float32([0, 1.5, 0])
    uv = rng.uniform(0, 1, (8, 2)).astype(np.float32)
    deltas = rng.normal(0, 0.005, (len(TARGETS), 8, 3)).astype(np.float32)
    front = np.array([[0, 1, 2], [2, 3, 0], [1, 2, 3]], np.uint16)     # three triangles: the skin
    back = np.array([[4, 5, 6], [6, 7, 4]], np.uint16)                 # two: the plain material
    position, texcoord = accessor(head, gl.VEC3), accessor(uv, gl.VEC2)
    targets = [{"POSITION": accessor(d, gl.VEC3)} for d in deltas]
    primitives = [gl.Primitive(attributes=gl.Attributes(POSITION=position, TEXCOORD_0=texcoord), targets=targets,
                               indices=accessor(f.ravel(), gl.SCALAR), material=m) for f, m in ((front, 0), (back, 1))]
    g.meshes.append(gl.Mesh(name="Head", primitives=primitives, extras={"targetNames": TARGETS}))
    eye = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], np.float32)
    eye_delta = [{"POSITION": accessor(np.full((3, 3), 0.002, np.float32), gl.VEC3)}] if eye_targets else None
    g.meshes.append(gl.Mesh(name="Eye", primitives=[gl.Primitive(
        attributes=gl.Attributes(POSITION=accessor(eye, gl.VEC3)), indices=accessor(np.arange(3, dtype=np.uint16),
                                                                                   gl.SCALAR), material=1,
        targets=eye_delta)], extras={"targetNames": ["jawOpen"]} if eye_targets else None))
    g.images = [gl.Image(name="skin", mimeType="image/png", bufferView=view(_image("PNG", (200, 150, 120)))),
                gl.Image(name="normals", mimeType="image/jpeg", bufferView=view(_image("JPEG", (128, 128, 255)))),
                gl.Image(name="glow", mimeType="image/webp", bufferView=view(_image("WEBP", (9, 9, 9)))),
                gl.Image(name="dark", mimeType="image/ktx2", bufferView=view(b"\xabKTX 20\xbb\r\n\x1a\n" + bytes(60)))]
    g.samplers = [gl.Sampler(wrapS=gl.CLAMP_TO_EDGE, wrapT=gl.MIRRORED_REPEAT)]
    g.textures = [gl.Texture(source=0, sampler=0), gl.Texture(source=1),
                  gl.Texture(extensions={"EXT_texture_webp": {"source": 2}}),   # as RPM writes WebP: no plain source
                  gl.Texture(source=3)]
    g.materials = [
        gl.Material(name="skin", alphaMode=gl.MASK, alphaCutoff=0.3, normalTexture=gl.NormalMaterialTexture(
                        index=1, scale=0.5), emissiveTexture=gl.TextureInfo(index=2), emissiveFactor=[1, 1, 1],
                    occlusionTexture=gl.OcclusionTextureInfo(index=3),
                    pbrMetallicRoughness=gl.PbrMetallicRoughness(baseColorTexture=gl.TextureInfo(index=0),
                                                                 baseColorFactor=[1, 0.9, 0.8, 1],
                                                                 metallicFactor=0.0, roughnessFactor=0.6)),
        gl.Material(name="plain", doubleSided=True, pbrMetallicRoughness=gl.PbrMetallicRoughness(
            baseColorFactor=[0.2, 0.3, 0.4, 1.0], metallicFactor=0.1, roughnessFactor=0.9))]
    g.nodes = [gl.Node(name="HeadNode", mesh=0), gl.Node(name="EyeL", mesh=1, translation=EYE_AT[0]),
               gl.Node(name="EyeR", mesh=1, translation=EYE_AT[1])]
    g.scenes, g.scene = [gl.Scene(nodes=[0, 1, 2])], 0
    g.buffers = [gl.Buffer(byteLength=len(blob))]
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(path))
    return {"uv": uv, "eye": eye}
