"""A glTF avatar's own skeleton in its USD: the joints of its skins as one UsdSkel Skeleton, its skinned meshes bound
to them as the file skins them, so that a body animation put on that skeleton in Omniverse, Maya or Houdini moves
the avatar, and our blend shapes play on the face it moves.

`usd.build_stage` asks `avatar_skeleton` for the skins of the meshes it writes (the driven parts and the scene's
other meshes). The Skeleton then holds:

- `joints`: every joint of those skins, as paths of prim-valid names from the topmost joint (`Hips/Spine/Neck/Head`),
  each joint's parent the nearest ancestor node that is a joint; parents before children;
- `bindTransforms`: each joint's inverse bind matrix inverted (glTF's bind, in the skeleton's space, which is the
  scene's: the Skeleton and the SkelRoot carry no transform);
- `restTransforms`: each joint's rest pose, local to its parent joint (a topmost joint's also carries the nodes
  above it that are not joints, such as an `Armature` turned and scaled 0.01).

Our SkelAnimation animates the blend shape weights and no joint (`joints` empty): UsdSkel then poses every joint at
its rest transform, a double-precision matrix, where a joint listed in a SkelAnimation takes half-float scales
(0.01 is stored as 0.0100021, which put the head of a Mixamo armature 0.2 mm off). A user's body animation lists
the joints it moves. The Skeleton prim and the SkelRoot carry no transform of their own: Blender's importer leaves
a Skeleton's transform off the meshes it skins (the avatar came in 1 m off).

A skinned mesh is written as the file stores it (positions and target deltas before skinning) with its JOINTS_0 /
WEIGHTS_0 as `primvars:skel:jointIndices` / `jointWeights` (4 a vertex) and the tokens of its skin's joints as
`skel:joints`: UsdSkel then skins it exactly as glTF does (blend shapes before skinning, linear blend skinning
after), so at rest it lies where the scene shows it, also when the file's bind pose is not its rest pose. A mesh on
a node without a skin is bound rigidly to the nearest joint above its node (else to the first topmost joint), with
`geomBindTransform` set so that it lies where the scene shows it at rest and follows that joint when it moves.

A skinned mesh whose stored arrays UsdSkel would not skin to where the scene shows it (a vertex whose weights sum
to 0: glTF leaves it where its node puts it, UsdSkel at the origin) is bound rigidly instead, as placed
(`AvatarSkeleton.as_placed`); a mesh under a joint scaled to 0 (a hidden hat) is bound to the first joint above it
that is not.

Left out, with a note (the meshes then lie where the scene shows them, as before, on a skeleton of one joint): skins
whose shared joints disagree on their bind matrices, a skin that lists a joint twice, a joint whose rest transform
has a shear, a node with two parents or a cycle of nodes, more than `MAX_JOINTS` joints or a chain deeper than
`MAX_DEPTH`. Units: the scene's metres times `scale` (the character's unit), translations included.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pxr import Gf, UsdGeom, UsdSkel, Vt

from visemeflow.rig.gltf import GltfMesh, GltfScene, _local_matrix, _node_order
from visemeflow.rig.model import RigError

__all__ = ["MAX_DEPTH", "MAX_JOINTS", "AvatarSkeleton", "avatar_skeleton"]

MAX_JOINTS = 4096
"""The most joints (of the skins written) and the deepest joint chain an avatar's USD skeleton takes: a MetaHuman body
has about 1,000 joints, a Ready Player Me avatar 67; a file past either keeps its meshes posed at rest on a
one-joint skeleton (a joint's token is its whole path, so a chain of 50,000 would spell gigabytes of names)."""
MAX_DEPTH = 256

_BIND_TOLERANCE = 1e-5
"""Largest difference (metres, or unitless in the linear part) between two skins' bind matrices of one joint."""


def usd_matrix(m: np.ndarray) -> Gf.Matrix4d:
    """A 4 x 4 column-vector (numpy, glTF) matrix as USD's row-vector Gf.Matrix4d."""
    return Gf.Matrix4d(np.asarray(m, np.float64).T.tolist())


@dataclass
class AvatarSkeleton:
    """The joints of a glTF scene's skins, ready for a UsdSkel Skeleton (see the module doc)."""

    nodes: list[int]
    """The joints' glTF nodes, parents before children."""
    tokens: list[str]
    """Each joint's path token (`Hips/Spine`)."""
    bind: np.ndarray
    """(J, 4, 4) column-vector bind transforms in the skeleton's space (the scene's, in the character's unit)."""
    rest_world: np.ndarray
    """(J, 4, 4) the joints' rest transforms in the same space."""
    rest_local: np.ndarray
    """(J, 4, 4) each joint's rest transform relative to its parent joint (a topmost joint's: `rest_world`)."""
    inverse_bind: np.ndarray
    """(J, 4, 4) the inverse of `bind`: the glTF inverse bind matrices, in the character's unit."""
    parents: list[int | None]
    """Each joint's parent joint (an index into `nodes`), None for a topmost joint."""
    names: list[str]
    """Each joint's glTF node name as the file spells it (`mixamorig:Hips`): the Skeleton's `jointNames`, which
    retargeting tools match by."""
    scene: GltfScene
    scale: float
    skin_joints: dict[int, list[int]] = field(default_factory=dict)
    """Per skin: its joints' indices into `nodes`, in the skin's order (JOINTS_0 indexes this)."""
    parent_of: dict[int, int] = field(default_factory=dict)
    """glTF node -> its parent node."""

    def __post_init__(self) -> None:
        self._index = {n: k for k, n in enumerate(self.nodes)}

    def joint_above(self, node: int | None) -> int | None:
        """The index of the nearest joint at or above `node`, None when no node above it is a joint."""
        seen = set()
        while node is not None and node not in seen:
            if node in self._index:
                return self._index[node]
            seen.add(node)
            node = self.parent_of.get(node)
        return None

    def rigid_joint(self, node: int | None) -> int | None:
        """The joint a mesh on `node` is bound to rigidly: the nearest above it whose rest transform can be inverted
        (a joint scaled to 0, a hidden hat, cannot carry a mesh), else the first such topmost joint; None if none."""
        k = self.joint_above(node)
        while k is not None and abs(np.linalg.det(self.rest_world[k][:3, :3])) <= 1e-18:
            k = self.parents[k]
        if k is None:
            k = next((j for j, p in enumerate(self.parents)
                      if p is None and abs(np.linalg.det(self.rest_world[j][:3, :3])) > 1e-18), None)
        return k

    def as_placed(self, skin: int, source: GltfMesh, placed: np.ndarray) -> bool:
        """Whether UsdSkel's skinning of `source` as stored (by `skin`, the skeleton at rest) puts its vertices at
        `placed`: false for a vertex whose weights sum to 0 (the file leaves it where its node puts it, UsdSkel at
        the origin) or anything else the stored arrays do not give."""
        if source.joints is None or source.weights is None or source.neutral.shape != placed.shape:
            return False
        joints = np.asarray(self.skin_joints[skin])
        if source.joints.size and int(source.joints.max()) >= len(joints):
            return False
        per_joint = self.rest_world @ self.inverse_bind
        worst = 0.0
        for start in range(0, len(placed), 1 << 16):       # (n, 4, 4, 4) at a time: bounded memory
            end = start + (1 << 16)
            blend = np.einsum("vk,vkij->vij", source.weights[start:end].astype(np.float64),
                              per_joint[joints[source.joints[start:end]]])
            p = source.neutral[start:end].astype(np.float64) * self.scale
            got = np.einsum("vij,vj->vi", blend[:, :3, :3], p) + blend[:, :3, 3]
            worst = max(worst, float(np.abs(got - placed[start:end]).max(initial=0.0)))
        return worst <= 1e-5 * max(1.0, self.scale)

    def define(self, skeleton: UsdSkel.Skeleton, animation: UsdSkel.Animation) -> None:
        """The joints, bind and rest transforms on `skeleton`; `animation` animates none of them (see the module)."""
        tokens = Vt.TokenArray(self.tokens)
        skeleton.CreateJointsAttr(tokens)
        skeleton.CreateJointNamesAttr(Vt.TokenArray(self.names))
        skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([usd_matrix(m) for m in self.bind]))
        skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([usd_matrix(m) for m in self.rest_local]))
        animation.CreateJointsAttr(Vt.TokenArray([]))
        animation.CreateTranslationsAttr(Vt.Vec3fArray([]))
        animation.CreateRotationsAttr(Vt.QuatfArray([]))
        animation.CreateScalesAttr(Vt.Vec3hArray([]))

    def skinned_source(self, mesh_index: int, placed: np.ndarray) -> tuple[int, GltfMesh] | None:
        """(its skin, the mesh as stored) for a mesh of the scene that a skin of the skeleton moves and whose rest
        pose is `placed` (the character's vertices of it); None for a mesh on a node without a skin, or one whose
        stored arrays UsdSkel would not skin to `placed` (`as_placed`): it is then bound rigidly, as placed."""
        info = next((i for i in self.scene.meshes if i.index == mesh_index), None)
        if info is None or info.skin not in self.skin_joints:
            return None
        source = self.scene.placed_mesh(mesh_index)[0]
        return (info.skin, source) if self.as_placed(info.skin, source, placed) else None

    def bind_skinned(self, mesh: UsdGeom.Mesh, skeleton: UsdSkel.Skeleton, skin: int, source: GltfMesh) -> None:
        """`mesh` (written from `source`'s stored positions) skinned by `skin` as the file skins it."""
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
        binding.CreateJointsAttr(Vt.TokenArray([self.tokens[k] for k in self.skin_joints[skin]]))
        binding.CreateJointIndicesPrimvar(False, 4).Set(
            Vt.IntArray.FromNumpy(np.ascontiguousarray(source.joints, dtype=np.int32).reshape(-1)))
        binding.CreateJointWeightsPrimvar(False, 4).Set(
            Vt.FloatArray.FromNumpy(np.ascontiguousarray(source.weights, dtype=np.float32).reshape(-1)))
        binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))

    def bind_rigid(self, mesh: UsdGeom.Mesh, skeleton: UsdSkel.Skeleton, node: int | None) -> None:
        """`mesh` (points where the scene shows it at rest) bound wholly to the nearest joint above `node` (else the
        first topmost joint; `rigid_joint`): it stays there at rest and follows that joint. Where no joint can
        carry it, it is bound to the skeleton without joints (its blend shapes still play)."""
        k = self.rigid_joint(node)
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
        if k is None:
            return
        binding.CreateJointsAttr(Vt.TokenArray([self.tokens[k]]))
        binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
        binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
        # UsdSkel: skinned point = rest_world[k] @ inv(bind[k]) @ geomBind @ point; at rest that must be the point
        binding.CreateGeomBindTransformAttr(usd_matrix(self.bind[k] @ np.linalg.inv(self.rest_world[k])))

    def undriven(self, static, skeleton: UsdSkel.Skeleton):
        """`define_static` for `usd_scene.dress_gltf_scene` from `static(path, points, faces)`: a mesh no target moves
        skinned by its skin (written as stored), bound rigidly to the joint above its node, or left static."""
        def define(path, points: np.ndarray, faces: np.ndarray, node: int | None = None, skin=None,
                   source: GltfMesh | None = None) -> UsdGeom.Mesh:
            if skin in self.skin_joints and source is not None and self.as_placed(skin, source, points):
                mesh = static(path, source.neutral * np.float32(self.scale), faces)
                self.bind_skinned(mesh, skeleton, skin, source)
                return mesh
            mesh = static(path, points, faces)
            if self.joint_above(node) is not None:
                self.bind_rigid(mesh, skeleton, node)
            return mesh
        return define

    def stored(self, source: GltfMesh) -> tuple[np.ndarray, np.ndarray]:
        """(positions, target deltas) of a skinned mesh as the file stores them, in the character's unit."""
        return source.neutral * np.float32(self.scale), source.deltas * np.float32(self.scale)


def avatar_skeleton(scene: GltfScene, skins: set[int], scale: float, prim_name
                    ) -> tuple[AvatarSkeleton | None, str | None]:
    """The skeleton of `skins` (see the module doc), or (None, why) where it cannot be one UsdSkel Skeleton; (None,
    None) without skins. `prim_name(text)`: a valid prim name of a joint's node name."""
    gltf = scene.gltf
    nodes = gltf.nodes or []
    skins = sorted(s for s in skins if isinstance(s, int) and 0 <= s < len(gltf.skins or []))
    if not skins:
        return None, None
    parent_of: dict[int, int] = {}
    for i, node in enumerate(nodes):
        for child in node.children or []:
            if child in parent_of:
                return None, f"node {child} has two parents: the avatar's skeleton is left out of the USD"
            parent_of[child] = i
    unit = np.diag([scale, scale, scale, 1.0])
    inverse_unit = np.diag([1.0 / scale, 1.0 / scale, 1.0 / scale, 1.0])
    binds: dict[int, np.ndarray] = {}
    per_skin: dict[int, list[int]] = {}
    for s in skins:
        skin = gltf.skins[s]
        joints = [j for j in skin.joints or [] if isinstance(j, int) and 0 <= j < len(nodes)]
        if len(joints) != len(skin.joints or []):
            return None, f"skin {s} names a node that does not exist: the avatar's skeleton is left out of the USD"
        try:
            inverse = np.broadcast_to(np.eye(4), (len(joints), 4, 4)) if skin.inverseBindMatrices is None else \
                scene.reader.matrices(skin.inverseBindMatrices, f"skin {s} inverseBindMatrices")
        except RigError as exc:
            return None, f"{exc}: the avatar's skeleton is left out of the USD"
        if len(inverse) != len(joints):
            return None, (f"skin {s} has {len(joints)} joints but {len(inverse)} inverse bind matrices: the avatar's "
                          "skeleton is left out of the USD")
        for j, ibm in zip(joints, inverse):
            try:
                bind = unit @ np.linalg.inv(np.asarray(ibm, np.float64)) @ inverse_unit
            except np.linalg.LinAlgError:
                return None, f"skin {s}: the inverse bind matrix of node {j} is singular: the avatar's skeleton is " \
                             "left out of the USD"
            if j in binds and np.abs(binds[j] - bind).max() > _BIND_TOLERANCE * max(1.0, scale):
                name = nodes[j].name or f"node {j}"
                return None, (f"joint {name!r} has different bind matrices in two skins: the avatar's skeleton is "
                              "left out of the USD")
            binds.setdefault(j, bind)
        if len(set(joints)) != len(joints):        # glTF 2.0 asks for unique joints; UsdSkel would pose one copy
            return None, f"skin {s} lists a joint twice: the avatar's skeleton is left out of the USD"
        per_skin[s] = joints

    if not binds:                # skins without joints: nothing to make a skeleton of
        return None, None
    if len(binds) > MAX_JOINTS:
        return None, (f"the skins have {len(binds):,} joints, more than the {MAX_JOINTS:,} a USD skeleton is made "
                      "of here: the avatar's skeleton is left out of the USD")
    joint_parents: dict[int, int | None] = {}
    for j in binds:              # the nearest joint above each joint (nodes that are not joints skipped)
        p, seen = parent_of.get(j), {j}
        while p is not None and p not in binds and p not in seen:
            seen.add(p)
            p = parent_of.get(p)
        joint_parents[j] = p if p in binds and p not in seen else None
    depths: dict[int, int] = {}
    for j in binds:              # each joint's depth below its topmost joint; a cycle (glTF forbids one) refused
        chain, p = [], j
        while p is not None and p not in depths:
            if p in chain:
                return None, (f"the nodes above joint {nodes[j].name or j!r} form a cycle: the avatar's skeleton is "
                              "left out of the USD")
            chain.append(p)
            p = joint_parents[p]
        d = -1 if p is None else depths[p]
        for q in reversed(chain):
            d += 1
            depths[q] = d

    if max(depths.values()) >= MAX_DEPTH:
        return None, (f"a chain of {max(depths.values()) + 1} joints, deeper than the {MAX_DEPTH} a USD skeleton is "
                      "made of here: the avatar's skeleton is left out of the USD")

    def joint_parent(j: int) -> int | None:
        return joint_parents[j]

    position = {n: k for k, n in enumerate(_node_order(gltf))}
    order = sorted(binds, key=lambda j: (depths[j], position.get(j, len(position) + j)))
    names: dict[int, str] = {}
    siblings: dict[int | None, set[str]] = {}
    for j in order:
        parent = joint_parent(j)
        base = name = prim_name(nodes[j].name or f"joint_{j}")
        taken = siblings.setdefault(parent, set())
        k = 1
        while name in taken:
            name, k = f"{base}_{k}", k + 1
        taken.add(name)
        names[j] = name if parent is None else f"{names[parent]}/{name}"
    rest_world = np.stack([unit @ scene.world_matrix(j) @ inverse_unit for j in order])
    index = {j: k for k, j in enumerate(order)}
    rest_local = np.empty_like(rest_world)
    for k, j in enumerate(order):
        parent = joint_parent(j)
        if parent is None:
            rest_local[k] = rest_world[k]
        else:            # the nodes' own local transforms from the parent joint down: nothing inverted (a joint
            local, node = np.eye(4), j          # scaled to 0, a hidden hat, has children all the same)
            while node != parent:
                local = _local_matrix(nodes[node]) @ local
                node = parent_of[node]
            rest_local[k] = unit @ local @ inverse_unit
        linear = rest_local[k][:3, :3]
        gram = linear.T @ linear
        if np.abs(gram - np.diag(np.diag(gram))).max() > 1e-6 * max(1.0, float(np.abs(gram).max())):
            return None, (f"joint {nodes[j].name or j!r} is sheared at rest (a parent scaled unevenly): the avatar's "
                          "skeleton is left out of the USD")
    bind = np.stack([binds[j] for j in order])
    return AvatarSkeleton(order, [names[j] for j in order], bind, rest_world, rest_local, np.linalg.inv(bind),
                          [None if joint_parent(j) is None else index[joint_parent(j)] for j in order],
                          [nodes[j].name or names[j].rpartition("/")[2] for j in order], scene, float(scale),
                          {s: [index[j] for j in js] for s, js in per_skin.items()}, parent_of), None

