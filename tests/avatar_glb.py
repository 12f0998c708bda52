"""The multi-mesh avatar GLB of tests/test_multimesh.py and tests/test_blender.py, built with pygltflib: a skinned
head (JOINTS_0/WEIGHTS_0, inverse bind matrices that do not cancel the joints' rest transforms), teeth with the mouth
targets in another order, two eyes with blink and mouth targets (zero deltas), a body without targets, a textured
material (an embedded PNG), a node hierarchy with translations, and an existing animation (a rotation of the eyes'
group). A Ready Player Me avatar's layout, small."""

import io
from pathlib import Path

import numpy as np
import pygltflib as gl

HEAD_TARGETS = ["jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthSmileLeft", "mouthSmileRight",
                "mouthPressLeft", "mouthPressRight", "mouthRollLower", "mouthLowerDownLeft", "mouthLowerDownRight",
                "mouthUpperUpLeft", "mouthStretchLeft", "mouthStretchRight", "eyeBlinkLeft", "eyeBlinkRight"]
TEETH_TARGETS = ["mouthClose", "jawOpen", "mouthFunnel", "tongueOut"]          # another order, one name of its own
EYE_TARGETS = ["eyeBlinkLeft", "eyeBlinkRight", "jawOpen", "mouthSmileLeft"]
HEAD_JOINT_OFFSET = np.array([0.0, 0.5, 0.0])   # world(head joint) @ its inverse bind matrix: a rest-pose shift
AVATAR_AT = np.array([1.0, 0.0, 0.0])           # the root node's translation
TEETH_AT = np.array([0.0, 1.4, 0.1])
EYES_AT = np.array([0.0, 1.6, 0.1])


class _Blob:
    def __init__(self, g: gl.GLTF2):
        self.g, self.data = g, bytearray()

    def view(self, data: bytes, target: int | None = None) -> int:
        self.data += bytes(-len(self.data) % 4)
        self.g.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(data),
                                                target=target))
        self.data += data
        return len(self.g.bufferViews) - 1

    def accessor(self, array: np.ndarray, kind: str, target: int | None = None, bounds: bool = False,
                 normalized: bool = False) -> int:
        array = np.ascontiguousarray(array)
        component = {np.dtype("float32"): gl.FLOAT, np.dtype("uint8"): gl.UNSIGNED_BYTE,
                     np.dtype("uint16"): gl.UNSIGNED_SHORT}[array.dtype]
        flat = array.reshape(len(array), -1)
        self.g.accessors.append(gl.Accessor(
            bufferView=self.view(array.tobytes(), target), componentType=component, count=len(array), type=kind,
            normalized=normalized or None, min=flat.min(0).tolist() if bounds else None,
            max=flat.max(0).tolist() if bounds else None))
        return len(self.g.accessors) - 1


def _grid(nx: int, ny: int, size: float) -> tuple[np.ndarray, np.ndarray]:
    xs, ys = np.meshgrid(np.linspace(-size, size, nx), np.linspace(-size, size, ny))
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(nx * ny)], 1).astype(np.float32)
    faces = [(r * nx + c, r * nx + c + 1, (r + 1) * nx + c + 1) for r in range(ny - 1) for c in range(nx - 1)] + \
        [(r * nx + c, (r + 1) * nx + c + 1, (r + 1) * nx + c) for r in range(ny - 1) for c in range(nx - 1)]
    return vertices, np.asarray(faces, np.uint16)


def _png() -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(np.array([[[200, 150, 120], [90, 60, 50]], [[240, 200, 180], [30, 20, 20]]], np.uint8)).save(
        out, format="PNG")
    return out.getvalue()


def _mesh(b: _Blob, name: str, vertices, faces, names: list[str], deltas, extra: dict | None = None,
          material: int = 1) -> int:
    attributes = gl.Attributes(POSITION=b.accessor(vertices, gl.VEC3, gl.ARRAY_BUFFER, bounds=True), **(extra or {}))
    targets = [{"POSITION": b.accessor(d.astype(np.float32), gl.VEC3, gl.ARRAY_BUFFER, bounds=True)} for d in deltas]
    primitive = gl.Primitive(attributes=attributes, indices=b.accessor(faces.ravel(), gl.SCALAR,
                                                                      gl.ELEMENT_ARRAY_BUFFER),
                             material=material, targets=targets or None,
                             extras={"targetNames": names} if names else {})
    b.g.meshes.append(gl.Mesh(name=name, primitives=[primitive], weights=[0.0] * len(names) if names else None,
                              extras={"targetNames": names} if names else {}))
    return len(b.g.meshes) - 1


HAIR_COLOR = [0.05, 0.1, 0.8, 1.0]             # linear; blue, so that a test can tell it from the skin
HAIR_AT = np.array([0.0, 1.75, -0.05])          # behind the head, under the root node


def make_avatar(path: Path, body_targets: list[str] | None = None, hair: bool = False) -> dict:
    """Write the multi-mesh avatar GLB (see the module doc); returns the arrays it holds, by mesh name. `hair`: a
    static "Wolf3D_Hair" plane (no targets, a blue material) behind the head, larger than it."""
    rng = np.random.default_rng(3)
    g = gl.GLTF2(asset=gl.Asset(version="2.0", generator="test avatar"))
    b = _Blob(g)
    head, head_faces = _grid(6, 5, 0.1)
    head[:, 1] += 1.5
    head_deltas = rng.normal(0, 0.01, (len(HEAD_TARGETS), len(head), 3)).astype(np.float32)
    joints = np.zeros((len(head), 4), np.uint8)
    head_weight = np.linspace(0.0, 1.0, len(head)).astype(np.float32)      # from the hips joint to the head joint
    joints[:, 1] = head_weight > 0
    weights = np.zeros((len(head), 4), np.float32)
    weights[:, 0], weights[:, 1] = 1 - head_weight, head_weight
    uv = np.c_[np.linspace(0, 1, len(head)), np.linspace(1, 0, len(head))].astype(np.float32)
    teeth, teeth_faces = _grid(3, 2, 0.03)
    teeth_deltas = rng.normal(0, 0.005, (len(TEETH_TARGETS), len(teeth), 3)).astype(np.float32)
    eye, eye_faces = _grid(2, 2, 0.01)
    body, body_faces = _grid(3, 3, 0.3)
    body_names = body_targets or []

    g.images.append(gl.Image(bufferView=b.view(_png()), mimeType="image/png", name="skin"))
    g.samplers.append(gl.Sampler(magFilter=gl.LINEAR, minFilter=gl.LINEAR))
    g.textures.append(gl.Texture(sampler=0, source=0))
    g.materials.append(gl.Material(name="skin", pbrMetallicRoughness=gl.PbrMetallicRoughness(
        baseColorTexture=gl.TextureInfo(index=0), metallicFactor=0.0, roughnessFactor=0.7)))
    g.materials.append(gl.Material(name="plain", pbrMetallicRoughness=gl.PbrMetallicRoughness(metallicFactor=0.0)))
    _mesh(b, "Wolf3D_Head", head, head_faces, HEAD_TARGETS, head_deltas, {
        "TEXCOORD_0": b.accessor(uv, gl.VEC2, gl.ARRAY_BUFFER),
        "JOINTS_0": b.accessor(joints, gl.VEC4, gl.ARRAY_BUFFER),
        "WEIGHTS_0": b.accessor(weights, gl.VEC4, gl.ARRAY_BUFFER)}, material=0)
    _mesh(b, "Wolf3D_Teeth", teeth, teeth_faces, TEETH_TARGETS, teeth_deltas)
    _mesh(b, "EyeLeft", eye, eye_faces, EYE_TARGETS, np.zeros((len(EYE_TARGETS), len(eye), 3)))
    _mesh(b, "EyeRight", eye, eye_faces, EYE_TARGETS, np.zeros((len(EYE_TARGETS), len(eye), 3)))
    _mesh(b, "Wolf3D_Body", body, body_faces, body_names,
          rng.normal(0, 0.01, (len(body_names), len(body), 3)))
    if hair:
        g.materials.append(gl.Material(name="hair", pbrMetallicRoughness=gl.PbrMetallicRoughness(
            baseColorFactor=HAIR_COLOR, metallicFactor=0.0)))
        hair_plane, hair_faces = _grid(4, 4, 0.25)
        _mesh(b, "Wolf3D_Hair", hair_plane, hair_faces, [], [], material=2)

    hips_world = np.eye(4)
    hips_world[:3, 3] = AVATAR_AT
    head_world = hips_world.copy()
    head_world[:3, 3] += [0, 1.0, 0]
    head_inverse_bind = np.linalg.inv(head_world)
    head_inverse_bind[:3, 3] += HEAD_JOINT_OFFSET     # world(head joint) @ this = a shift by HEAD_JOINT_OFFSET
    ibm = np.stack([np.linalg.inv(hips_world), head_inverse_bind]).transpose(0, 2, 1).astype(np.float32)
    g.nodes = [
        gl.Node(name="Avatar", translation=AVATAR_AT.tolist(), children=[1, 4, 5, 8]),             # 0
        gl.Node(name="Hips", children=[2]),                                                         # 1
        gl.Node(name="HeadJoint", translation=[0.0, 1.0, 0.0]),                                    # 2
        gl.Node(name="HeadNode", mesh=0, skin=0),                                                   # 3
        gl.Node(name="TeethNode", mesh=1, translation=TEETH_AT.tolist()),                           # 4
        gl.Node(name="Eyes", translation=EYES_AT.tolist(), children=[6, 7]),                        # 5
        gl.Node(name="EyeLeftNode", mesh=2, translation=[-0.03, 0.0, 0.0]),                         # 6
        gl.Node(name="EyeRightNode", mesh=3, translation=[0.03, 0.0, 0.0]),                         # 7
        gl.Node(name="BodyNode", mesh=4),                                                           # 8
    ]
    if hair:
        g.nodes.append(gl.Node(name="HairNode", mesh=5, translation=HAIR_AT.tolist()))             # 9
        g.nodes[0].children.append(9)
    g.skins.append(gl.Skin(name="Armature", joints=[1, 2], skeleton=1,
                           inverseBindMatrices=b.accessor(ibm.reshape(2, 16), gl.MAT4)))
    times = np.array([0.0, 1.0], np.float32)
    turn = np.array([[0, 0, 0, 1], [0, np.sin(0.2), 0, np.cos(0.2)]], np.float32)
    g.animations.append(gl.Animation(name="idle", samplers=[gl.AnimationSampler(
        input=b.accessor(times, gl.SCALAR, bounds=True), output=b.accessor(turn, gl.VEC4), interpolation="LINEAR")],
        channels=[gl.AnimationChannel(sampler=0, target=gl.AnimationChannelTarget(node=5, path="rotation"))]))
    g.scenes = [gl.Scene(name="Scene", nodes=[0, 3])]    # a skinned node at the root, as the validator asks
    g.scene = 0
    b.data += bytes(-len(b.data) % 4)
    g.buffers = [gl.Buffer(byteLength=len(b.data))]
    g.set_binary_blob(bytes(b.data))
    g.save_binary(str(path))
    return {"head": head, "head_deltas": head_deltas, "head_weight": head_weight, "teeth": teeth,
            "teeth_deltas": teeth_deltas, "eye": eye}
