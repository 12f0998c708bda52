"""The avatar's own clips in its USD: each glTF animation that moves the skeleton's joints (an `idle` that turns the
neck) as a SkelAnimation of its own, `/<Root>/Clips/<name>`, beside our speech animation.

The Skeleton plays one SkelAnimation (`skel:animationSource`), and ours stays that one: it carries the face. A clip is
there to be used as the user's tool uses animations: bound in place of ours (`skel:animationSource`), layered in
Omniverse's animation graph, or retargeted by joint name. Each holds the joints the clip moves (a joint moves when a
channel animates it or a node between it and the joint above it), sampled at the stage's frame rate from time code 0
(the clip's time 0) to its last key, with glTF's interpolations (STEP, LINEAR with spherical interpolation of
rotations, CUBICSPLINE); the local transform of each joint is the product of its nodes' animated local transforms,
as `usd_joints` builds the rest transforms. UsdSkel stores a joint's animated scale as a half float, so a joint
whose local transform carries a scale other than 1 (a topmost joint under an `Armature` scaled 0.01) is off by up to
2e-4 of its scale when a clip moves it (about 0.2 mm on a Mixamo head).

Not carried, each with a note in the layer's documentation: channels of morph target weights, channels of nodes no
joint hangs from (a group of eye meshes), a clip whose keys are broken (times not increasing, a NaN, a wrong count)
or that would cost more than `MAX_CLIP_VALUES`, a joint whose animated transform is sheared. A joint a clip scales to 0
(a part hidden) is carried.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Gf, Sdf, Usd, UsdSkel, Vt

from visemeflow.animation.skinned_asset import _continuous, _quaternion
from visemeflow.animation.usd_names import unique_prim_names
from visemeflow.animation.usd_joints import AvatarSkeleton
from visemeflow.rig.gltf import _local_matrix, _quaternion_matrix
from visemeflow.rig.model import RigError

__all__ = ["CLIPS", "MAX_CLIP_VALUES", "Clip", "avatar_clips", "define_clips", "sample_channel"]

CLIPS = "Clips"
MAX_CLIP_VALUES = 4_000_000
"""The most the clips of one avatar may cost in its USD, counted per frame as its joints plus its channels plus the
nodes of those joints' chains (about 100 bytes each while a clip is made, the arrays of one joint at a time on top):
a 2-minute clip at 30 fps moving the 67 joints of a Ready Player Me skeleton costs about 500,000; beyond the limit a
clip is left out with a note (a file whose last key lies a year away included)."""

_WIDTH = {"translation": 3, "rotation": 4, "scale": 3}


@dataclass
class Clip:
    """One glTF animation sampled on the skeleton: `joints` (indices into the skeleton), per frame their local
    translations (F, J, 3), rotations (F, J, 4; w, x, y, z) and scales (F, J, 3)."""

    name: str
    joints: list[int]
    translations: np.ndarray
    rotations: np.ndarray
    scales: np.ndarray


def sample_channel(times: np.ndarray, values: np.ndarray, interpolation: str, at: np.ndarray,
                   rotation: bool = False) -> np.ndarray:
    """(len(at), width) values of a glTF sampler (`times` (K,) increasing, `values` (K, width), or (3K, width) of
    in-tangent, value, out-tangent for CUBICSPLINE) at the times `at`, held at its ends; rotations (x, y, z, w) by
    spherical interpolation and normalised."""
    times = np.asarray(times, np.float64)
    values = np.asarray(values, np.float64)
    at = np.asarray(at, np.float64)
    cubic = interpolation == "CUBICSPLINE"
    points = values[1::3] if cubic else values
    # glTF stores times as float32 (0.1 s is 0.100000001): a sample within a microsecond of a key is at that key
    slack = np.minimum(1e-3, 1e-6 * (1.0 + np.abs(at)))
    k = np.clip(np.searchsorted(times, at + slack, side="right") - 1, 0, len(times) - 1)
    nxt = np.minimum(k + 1, len(times) - 1)
    span = times[nxt] - times[k]
    s = np.where(span > 0, (at - times[k]) / np.where(span > 0, span, 1.0), 0.0)
    s = np.clip(s, 0.0, 1.0)[:, None]
    a, b = points[k], points[nxt]
    if interpolation == "STEP":
        out = a
    elif cubic:
        d = span[:, None]
        out_tangent, in_tangent = values[2::3][k], values[0::3][nxt]
        s2, s3 = s * s, s * s * s
        out = (2 * s3 - 3 * s2 + 1) * a + (s3 - 2 * s2 + s) * d * out_tangent + (-2 * s3 + 3 * s2) * b + \
            (s3 - s2) * d * in_tangent
    elif rotation:                    # LINEAR rotations: slerp along the shorter arc
        dot = np.sum(a * b, axis=1, keepdims=True)
        b = np.where(dot < 0, -b, b)
        dot = np.abs(dot)
        angle = np.arccos(np.clip(dot, -1.0, 1.0))
        small = angle < 1e-6
        sin = np.where(small, 1.0, np.sin(angle))
        wa = np.where(small, 1 - s, np.sin((1 - s) * angle) / sin)
        wb = np.where(small, s, np.sin(s * angle) / sin)
        out = wa * a + wb * b
    else:
        out = (1 - s) * a + s * b
    before, after = at <= times[0], at + slack >= times[-1]
    out = np.where(before[:, None], points[0], np.where(after[:, None], points[-1], out))
    if rotation:
        norm = np.linalg.norm(out, axis=1, keepdims=True)
        out = out / np.where(norm > 0, norm, 1.0)
    return out


def _chain(avatar: AvatarSkeleton, k: int) -> list[int]:
    """The nodes whose local transforms make joint k's local one: k's node up to (not including) its parent joint's,
    or every node above a topmost joint."""
    stop = None if avatar.parents[k] is None else avatar.nodes[avatar.parents[k]]
    chain, node, seen = [], avatar.nodes[k], set()
    while node is not None and node != stop and node not in seen:
        seen.add(node)
        chain.append(node)
        node = avatar.parent_of.get(node)
    return chain


def avatar_clips(avatar: AvatarSkeleton, fps: float) -> tuple[list[Clip], list[str]]:
    """The scene's animations that move the skeleton's joints, sampled at `fps` (see the module), and a note for
    each thing left out."""
    gltf, reader = avatar.scene.gltf, avatar.scene.reader
    nodes = gltf.nodes or []
    chains = [_chain(avatar, k) for k in range(len(avatar.nodes))]
    moves: dict[int, list[int]] = {}            # node -> the joints whose local transform it is part of
    for k, chain in enumerate(chains):
        for node in chain:
            moves.setdefault(node, []).append(k)
    unit = np.diag([avatar.scale] * 3 + [1.0])
    inverse_unit = np.diag([1.0 / avatar.scale] * 3 + [1.0])
    clips, notes, budget = [], [], MAX_CLIP_VALUES
    for a, animation in enumerate(gltf.animations or []):
        label = f"clip {animation.name or a!r}"
        tracks: dict[tuple[int, str], tuple[np.ndarray, np.ndarray, str]] = {}
        skipped: set[str] = set()
        try:
            for channel in animation.channels or []:
                node, path = channel.target.node, channel.target.path
                if path == "weights":
                    skipped.add("its morph target weights")
                    continue
                if path not in _WIDTH or not isinstance(node, int) or not 0 <= node < len(nodes):
                    skipped.add(f"a channel of {path!r} on node {node!r}")
                    continue
                if node not in moves:
                    skipped.add(f"node {nodes[node].name or node!r}, which no joint hangs from")
                    continue
                samplers = animation.samplers or []
                if not isinstance(channel.sampler, int) or not 0 <= channel.sampler < len(samplers):
                    raise ValueError(f"{label}: a channel names sampler {channel.sampler!r}, which does not exist")
                sampler = samplers[channel.sampler]
                interpolation = sampler.interpolation or "LINEAR"
                times = reader.accessor(sampler.input, f"{label} input", ("SCALAR",))[:, 0].astype(np.float64)
                values = reader.accessor(sampler.output, f"{label} output", ("VEC3", "VEC4"))
                if values.dtype.kind != "f":       # normalized integers (KHR_animation quantization): rotations
                    values = np.clip(values / float(np.iinfo(values.dtype).max), -1.0, 1.0)
                values = values.astype(np.float64)
                want = len(times) * (3 if interpolation == "CUBICSPLINE" else 1)
                if interpolation not in ("LINEAR", "STEP", "CUBICSPLINE") or len(times) == 0 or \
                        values.shape != (want, _WIDTH[path]) or not np.isfinite(times).all() or \
                        not np.isfinite(values).all() or (np.diff(times) <= 0).any():
                    raise ValueError(f"{label}: the keys of its {path} channel of node {node} are broken "
                                     f"({len(times)} times, {values.shape[0]} values, {interpolation})")
                tracks[(node, path)] = (times, values, interpolation)
        except (RigError, ValueError, IndexError, TypeError) as exc:
            message = str(exc)
            notes.append(f"{message if label in message else f'{label}: {message}'}: left out")
            continue
        if skipped:
            notes.append(f"{label}: {', '.join(sorted(skipped))} not carried")
        joints = sorted({k for node, _ in tracks for k in moves[node]})
        if not joints:
            continue
        end = max(0.0, max(float(t[-1]) for t, _, _ in tracks.values()))
        n_frames = int(np.floor((end + min(1e-3, 1e-6 * (1 + end))) * fps)) + 1   # its last key too (float32)
        # what sampling it costs, counted before anything of that size is made: per frame, each joint's transforms,
        # each channel, each node of the joints' chains
        cost = n_frames * (len(joints) + len(tracks) + sum(len(chains[k]) for k in joints))
        if cost > budget:
            plural = "s" * (len(joints) != 1)
            notes.append(f"{label}: {n_frames:,} frames of {len(joints)} joint{plural}, more than the USD takes "
                         "here: left out")
            continue
        budget -= cost
        at = np.arange(n_frames) / fps
        sampled = {key: sample_channel(t, v, i, at, rotation=key[1] == "rotation")
                   for key, (t, v, i) in tracks.items()}
        translations = np.empty((len(at), len(joints), 3))
        rotations = np.empty((len(at), len(joints), 4))
        scales = np.empty((len(at), len(joints), 3))
        sheared = None
        for c, k in enumerate(joints):
            local = np.tile(np.eye(4), (len(at), 1, 1))
            for node in chains[k]:           # from the joint up: local = parent-side @ ... @ joint's own
                local = np.einsum("fij,fjk->fik", _node_locals(nodes[node], node, sampled, len(at)), local)
            local = np.einsum("ij,fjk,kl->fil", unit, local, inverse_unit)
            t, q, s, ok = _decompose(local)
            if not ok:
                sheared = nodes[avatar.nodes[k]].name or avatar.nodes[k]
                break
            translations[:, c], rotations[:, c], scales[:, c] = t, q, s
        if sheared is not None:
            notes.append(f"{label}: joint {sheared!r} is sheared in it (a parent scaled unevenly): left out")
            continue
        clips.append(Clip(animation.name or f"clip_{a}", joints, translations, rotations, scales))
    return clips, notes


def _node_locals(node, index: int, sampled: dict, n: int) -> np.ndarray:
    """(n, 4, 4) a node's local transform at each sample: its animated TRS where a channel moves it, else its own."""
    if not any((index, p) in sampled for p in _WIDTH):
        return np.broadcast_to(_local_matrix(node), (n, 4, 4))
    rest = _local_matrix(node)
    if node.matrix is not None and len(node.matrix) == 16:        # glTF: a node with a matrix is not animated;
        return np.broadcast_to(rest, (n, 4, 4))                  # a file that does anyway keeps the matrix
    t = sampled.get((index, "translation"), np.broadcast_to(node.translation or (0.0, 0.0, 0.0), (n, 3)))
    r = sampled.get((index, "rotation"), np.broadcast_to(node.rotation or (0.0, 0.0, 0.0, 1.0), (n, 4)))
    s = sampled.get((index, "scale"), np.broadcast_to(node.scale or (1.0, 1.0, 1.0), (n, 3)))
    out = np.zeros((n, 4, 4))
    out[:, :3, :3] = _quaternion_matrix(r) * np.asarray(s, np.float64)[:, None, :]
    out[:, :3, 3] = t
    out[:, 3, 3] = 1.0
    return out


def _decompose(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """(F, 4, 4) column-vector matrices as translations, rotations (w, x, y, z) and per-axis scales; False where one
    is sheared (not a rotation times a scale along its own axes)."""
    linear = m[:, :3, :3]
    scale = np.linalg.norm(linear, axis=1)                       # column norms: the scale of each axis
    zero = scale <= 1e-12
    rotation = linear / np.where(zero, 1.0, scale)[:, None, :]
    for f in np.flatnonzero(zero.any(axis=1)):                   # an axis scaled to 0 (a part hidden): its
        rotation[f] = _completed(rotation[f], zero[f])           # direction is free, the others keep theirs
    det = np.linalg.det(rotation)
    if (det < 0).any():                                          # a mirror: one axis negative
        flip = np.where(det < 0, -1.0, 1.0)
        scale[:, 0] *= flip
        rotation[:, :, 0] *= flip[:, None]
    gram = np.einsum("fji,fjk->fik", rotation, rotation)
    ok = bool(np.abs(gram - np.eye(3)).max() <= 1e-5)
    return m[:, :3, 3], _continuous(_quaternion(rotation)), scale, ok


def _completed(rotation: np.ndarray, zero: np.ndarray) -> np.ndarray:
    """A 3x3 whose columns flagged `zero` are filled to make it a rotation with the other (unit) columns kept."""
    out = rotation.copy()
    kept = [i for i in range(3) if not zero[i]]
    if not kept:
        return np.eye(3)
    if len(kept) == 1:
        i = kept[0]
        c = out[:, i]
        other = np.eye(3)[int(np.argmin(np.abs(c)))]
        e = np.cross(c, other)
        out[:, (i + 1) % 3] = e / np.linalg.norm(e)
        out[:, (i + 2) % 3] = np.cross(c, out[:, (i + 1) % 3])
        return out
    m = next(i for i in range(3) if zero[i])
    out[:, m] = np.cross(out[:, (m + 1) % 3], out[:, (m + 2) % 3])
    return out


def define_clips(stage: Usd.Stage, root: Sdf.Path, avatar: AvatarSkeleton, fps: float) -> list[str]:
    """`avatar_clips` written as SkelAnimation prims under `<root>/Clips` (not bound: the speech animation stays the
    skeleton's `animationSource`); returns the notes of what was left out."""
    clips, notes = avatar_clips(avatar, fps)
    if not clips:
        return notes
    folder = root.AppendChild(CLIPS)
    stage.DefinePrim(folder, "Scope")
    names, taken = [], set()
    for name in unique_prim_names(c.name for c in clips):      # two clips of one name (glTF allows it) get two prims
        base, k = name, 1
        while name in taken:
            name, k = f"{base}_{k}", k + 1
        taken.add(name)
        names.append(name)
    for name, clip in zip(names, clips):
        anim = UsdSkel.Animation.Define(stage, folder.AppendChild(name))
        anim.GetPrim().SetDocumentation(f"the avatar's own clip {clip.name!r}, {len(clip.translations)} frames at "
                                        f"{fps:g} fps from time code 0: bind it as the Skeleton's "
                                        "skel:animationSource to play it")
        anim.CreateJointsAttr(Vt.TokenArray([avatar.tokens[k] for k in clip.joints]))
        t_attr, r_attr, s_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr(), anim.CreateScalesAttr()
        with Sdf.ChangeBlock():
            for f in range(len(clip.translations)):
                code = Usd.TimeCode(f)
                t_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(clip.translations[f], np.float32)), code)
                r_attr.Set(Vt.QuatfArray([Gf.Quatf(*map(float, q)) for q in clip.rotations[f]]), code)
                s_attr.Set(Vt.Vec3hArray([Gf.Vec3h(*map(float, s)) for s in clip.scales[f]]), code)
    return notes
