"""Blendshape naming conventions and how our 16 viseme curves drive each of them.

- `visemeflow16`: one shape per viseme, named as `visemes.VISEMES` (our rigs).
- `arkit52`: Apple ARKit's 52 face blendshapes (MetaHuman, VRoid, iPhone-captured rigs, most web avatars).
- `oculus15`: the Oculus / Meta Lipsync visemes (`viseme_sil` .. `viseme_U`; Ready Player Me, TalkingHead; also
  OVRLipSync's own names `sil`, `PP`, ... `ih`, `oh`, `ou`).
- `vrm5`: the five vowel mouths of VRM avatars (VRoid's `Fcl_MTH_A` .. `Fcl_MTH_O`, VRM 1.0's `aa ih ou ee oh`, VRM
  0.x's `A I U E O`); the rest mouth is closed, so b/p/m drive nothing.
- `mapping`: any other naming, through a user's CSV `viseme,shape,weight`.
"""

from __future__ import annotations

import csv
import io
import re
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from visemeflow.rig.character import Character, CharacterError
from visemeflow.visemes import N_VISEMES, VISEMES

ARKIT_52: tuple[str, ...] = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight",
    "jawForward", "jawLeft", "jawRight", "jawOpen",
    "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight",
    "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft",
    "mouthStretchRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthPressLeft",
    "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight",
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight",
    "noseSneerLeft", "noseSneerRight",
    "tongueOut",
)
"""The 52 ARKit blendshape names in the order of Apple's ARFaceAnchor.BlendShapeLocation documentation."""

OCULUS_15: tuple[str, ...] = (
    "viseme_sil", "viseme_PP", "viseme_FF", "viseme_TH", "viseme_DD", "viseme_kk", "viseme_CH", "viseme_SS",
    "viseme_nn", "viseme_RR", "viseme_aa", "viseme_E", "viseme_I", "viseme_O", "viseme_U",
)
"""The 15 Oculus / Meta Lipsync visemes."""

VRM_5: tuple[str, ...] = ("Fcl_MTH_A", "Fcl_MTH_I", "Fcl_MTH_U", "Fcl_MTH_E", "Fcl_MTH_O")
"""VRoid Studio's five vowel mouths (VRM's lip-sync presets); a VRM avatar's rest mouth is closed."""

ALIASES: dict[str, tuple[str, ...]] = {
    # OVRLipSync's own names (Ready Player Me prefixes them with viseme_ and writes I, O, U for ih, oh, ou)
    **{f"viseme_{n}": (n,) for n in ("sil", "PP", "FF", "TH", "DD", "kk", "CH", "SS", "nn", "RR", "aa", "E")},
    "viseme_I": ("ih",), "viseme_O": ("oh",), "viseme_U": ("ou",),
    # VRM 1.0 expression presets and VRM 0.x blend shape presets, as morph target names
    "Fcl_MTH_A": ("aa", "A"), "Fcl_MTH_I": ("ih", "I"), "Fcl_MTH_U": ("ou", "U"), "Fcl_MTH_E": ("ee", "E"),
    "Fcl_MTH_O": ("oh", "O"),
}
"""Other names a rig may give a convention's shape (matched after the name itself)."""


Table = dict[str, dict[str, float]]
"""viseme -> {target shape name: weight}: curves @ table drive the target shapes."""

CONVENTIONS: tuple[str, ...] = ("visemeflow16", "arkit52", "oculus15", "vrm5")
"""The conventions detected from shape names; `mapping` (a user's CSV) is chosen by giving the CSV."""

CONVENTION_NAMES: dict[str, tuple[str, ...]] = {"visemeflow16": VISEMES, "arkit52": ARKIT_52, "oculus15": OCULUS_15,
                                                "vrm5": VRM_5}
_TABLE_FILES = {"arkit52": "arkit_visemes.csv", "oculus15": "oculus_visemes.csv", "vrm5": "vrm_visemes.csv"}
# How many of a convention's names a character must have to be taken for that convention: every viseme of ours,
# most Oculus visemes, a useful set of ARKit mouth shapes (rigs often carry a subset of the 52), the five vowels.
_MIN_MATCHES = {"visemeflow16": 16, "oculus15": 10, "arkit52": 8, "vrm5": 5}
# What a viseme that a character cannot make costs the viewer (`Binding.warnings`)
_CONTACTS = {"MBP": "the lips will not close at b/p/m", "FFF": "the lower lip will not touch the teeth at f/v",
             "AHH": "the mouth will hardly open at open vowels (a, ah)"}


def normalize_shape_name(name: str) -> str:
    """The key names are matched on: the part after a namespace (`blendShape1.jawOpen`, `head:jawOpen`,
    `Face|jawOpen`), lower case, `_L`/`_R` (and `_left`/`_right`) suffixes as `left`/`right`, no `_`, `-` or
    spaces. So `JawOpen`, `jaw_open` and `jawOpen` match, and ICT's `mouthStretch_L` is ARKit's
    `mouthStretchLeft`."""
    base = re.split(r"[.:|]", name.strip())[-1].lower()
    base = re.sub(r"[_\-\s](l|left)$", "left", base)
    base = re.sub(r"[_\-\s](r|right)$", "right", base)
    return re.sub(r"[_\-\s]", "", base)


def parse_table(text: str, source: str, *, every_viseme: bool = False) -> Table:
    """A table `viseme,shape,weight` (CSV with that header; `#` lines are comments) -> {viseme: {shape: weight}}.

    A viseme may list several shapes and a shape may serve several visemes; weights must be finite and >= 0.
    Errors name the file and line."""
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    reader = csv.DictReader(io.StringIO("\n".join(lines)))
    if reader.fieldnames is None or [f.strip().lower() for f in reader.fieldnames][:3] != ["viseme", "shape", "weight"]:
        raise CharacterError(f"{source}: expected the header 'viseme,shape,weight', got {reader.fieldnames}")
    table: Table = {}
    for line, row in enumerate(reader, start=2):
        viseme, shape = ((row[key] or "").strip() for key in reader.fieldnames[:2])
        if viseme not in VISEMES:
            raise CharacterError(f"{source} line {line}: unknown viseme {viseme!r}; expected one of {', '.join(VISEMES)}")
        if not shape:
            raise CharacterError(f"{source} line {line}: no target shape for {viseme}")
        try:
            weight = float(row[reader.fieldnames[2]])
        except (TypeError, ValueError):
            raise CharacterError(f"{source} line {line}: weight {row[reader.fieldnames[2]]!r} is not a number") from None
        if not np.isfinite(weight) or weight < 0:
            raise CharacterError(f"{source} line {line}: weight must be finite and >= 0, got {weight}")
        if shape in table.get(viseme, {}):
            raise CharacterError(f"{source} line {line}: {viseme} lists {shape!r} twice")
        table.setdefault(viseme, {})[shape] = weight
    if not table:
        raise CharacterError(f"{source}: no rows")
    missing = [v for v in VISEMES if v not in table]
    if every_viseme and missing:
        raise CharacterError(f"{source}: no row for viseme(s) {', '.join(missing)}")
    return table


def load_mapping_csv(path: str | Path) -> Table:
    """A user's mapping CSV (`viseme,shape,weight`); visemes without a row drive nothing."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise CharacterError(f"{path}: cannot read the mapping CSV ({exc})") from None
    return parse_table(text, str(path))


def builtin_table(convention: str) -> Table:
    """The shipped table of a convention (`visemeflow16` is the identity)."""
    if convention == "visemeflow16":
        return {v: {v: 1.0} for v in VISEMES}
    if convention not in _TABLE_FILES:
        raise CharacterError(f"unknown convention {convention!r}; known: {', '.join(CONVENTIONS)} or a mapping CSV")
    name = _TABLE_FILES[convention]
    text = resources.files("visemeflow.shapes").joinpath("data", name).read_text("utf-8")
    return parse_table(text, f"visemeflow/shapes/data/{name}", every_viseme=True)


def table_matrix(table: Table, target_names: tuple[str, ...] | list[str]) -> np.ndarray:
    """(16, len(target_names)) float32: curves (T, 16) @ matrix = target weights; shapes not in the list dropped."""
    index = {n: i for i, n in enumerate(target_names)}
    matrix = np.zeros((N_VISEMES, len(target_names)), np.float32)
    for i, viseme in enumerate(VISEMES):
        for shape, weight in table.get(viseme, {}).items():
            if shape in index:
                matrix[i, index[shape]] += weight
    return matrix


def arkit_weights(curves: np.ndarray) -> np.ndarray:
    """(T, 16) viseme curves -> (T, 52) ARKit weights in `ARKIT_52` order, through the shipped table, in [0, 1]."""
    matrix = table_matrix(builtin_table("arkit52"), ARKIT_52)
    return np.clip(np.asarray(curves, np.float32) @ matrix, 0.0, 1.0)


def _match_names(names: tuple[str, ...], wanted: tuple[str, ...] | list[str], where: str) -> dict[str, str]:
    """wanted name -> the character's name for it (exact match first, else by `normalize_shape_name`)."""
    exact = set(names)
    by_key: dict[str, list[str]] = {}
    for n in names:
        by_key.setdefault(normalize_shape_name(n), []).append(n)
    found = {}
    for w in wanted:
        spellings = (w, *ALIASES.get(w, ()))
        same = [s for s in spellings if s in exact]
        if same:
            found[w] = same[0]
            continue
        for spelling in spellings:
            hits = by_key.get(normalize_shape_name(spelling), [])
            if len(hits) > 1:
                raise CharacterError(f"{where}: shapes {', '.join(map(repr, hits))} all read as {w!r}; rename one "
                                     "or give a mapping CSV")
            if hits:
                found[w] = hits[0]
                break
    return found


def detect_convention(character: Character) -> str:
    """The convention whose names the character's shapes follow; CharacterError listing the names otherwise."""
    scores = {}
    for convention, wanted in CONVENTION_NAMES.items():
        matched = len(_match_names(character.shape_names, wanted, character.where()))
        if matched >= _MIN_MATCHES[convention]:
            scores[convention] = matched / len(wanted)
    if not scores:
        shown = ", ".join(character.shape_names[:40]) + (" ..." if character.n_shapes > 40 else "")
        raise CharacterError(
            f"{character.where()}: its {character.n_shapes} shape names follow no known convention "
            f"(names found: {shown}); known conventions: visemeflow16 (our 16 visemes: {', '.join(VISEMES)}), "
            f"arkit52 (ARKit blendshapes such as jawOpen, mouthFunnel), oculus15 (viseme_sil .. viseme_U, or sil, PP "
            f".. ou), vrm5 (Fcl_MTH_A .. Fcl_MTH_O, or aa ih ou ee oh); give a mapping CSV (--mapping FILE.csv, rows "
            "viseme,shape,weight), or --convention NAME for a rig with fewer of a convention's shapes than "
            "detection asks"
            + (f"; {character.describe()}" if character.parts else ""))
    return max(scores, key=lambda c: (scores[c], -CONVENTIONS.index(c)))


@dataclass(frozen=True)
class Binding:
    """How the 16 curves drive one character: weights (T, S) = clip(curves (T, 16) @ matrix, 0, 1)."""

    character: str
    convention: str
    """visemeflow16, arkit52, oculus15 or mapping."""
    table_source: str
    shape_names: tuple[str, ...]
    """The character's shapes, in its order (the columns of `matrix`)."""
    matrix: np.ndarray = field(repr=False)
    """(16, S) float32."""
    driven: tuple[str, ...]
    """The character's shapes the curves move (the others stay at 0)."""
    missing: tuple[str, ...]
    """Shapes the table names that the character lacks (their share of the motion is lost)."""
    unmapped: tuple[str, ...]
    """Visemes that move no shape of this character."""
    lost: dict[str, tuple[float, tuple[str, ...]]] = field(default_factory=dict, repr=False)
    """viseme -> (the share of its table weight on shapes the character lacks, those shapes), where any is lacking."""

    def warnings(self) -> list[str]:
        """What the viewer will miss: a b/p/m closure or an f/v contact whose shapes the character mostly lacks (half
        or more of the table's weight for it), with what to do."""
        out = []
        for viseme, consequence in _CONTACTS.items():
            share, shapes = self.lost.get(viseme, (0.0, ()))
            if share >= 0.5:
                out.append(f"{self.character}: {consequence}: it lacks {', '.join(shapes)}, {share:.0%} of what the "
                           f"{self.convention} table drives for {viseme}; give --mapping FILE.csv with a shape of "
                           f"yours that does it (a row `{viseme},YOUR_SHAPE,1.0`)")
        return out

    def weights(self, curves: np.ndarray) -> np.ndarray:
        """(T, 16) curves -> (T, S) float32 shape weights in [0, 1]."""
        curves = np.asarray(curves, np.float32)
        if curves.ndim != 2 or curves.shape[1] != N_VISEMES:
            raise ValueError(f"curves must be (frames, {N_VISEMES}), got {curves.shape}")
        return np.clip(curves @ self.matrix, 0.0, 1.0)

    def summary(self) -> dict:
        return {"character": self.character, "convention": self.convention, "table": self.table_source,
                "driven": list(self.driven), "missing": list(self.missing), "unmapped": list(self.unmapped)}


def bind(character: Character, convention: str | None = None, mapping: str | Path | None = None) -> Binding:
    """Bind the 16 visemes to the character's shapes: by a mapping CSV if given, else by `convention` (detected
    from the names when None). A mapping naming shapes the character lacks is an error listing them."""
    where = character.where()
    if mapping is not None:
        table, convention, source = load_mapping_csv(mapping), "mapping", str(mapping)
        wanted = sorted({s for row in table.values() for s in row})
        found = _match_names(character.shape_names, wanted, where)
        unknown = [s for s in wanted if s not in found]
        if unknown:
            raise CharacterError(f"{mapping}: names shape(s) {', '.join(map(repr, unknown))} that {where} lacks; "
                                 f"its shapes: {', '.join(character.shape_names[:60])}")
    else:
        convention = convention or detect_convention(character)
        if convention not in CONVENTIONS:
            raise CharacterError(f"unknown convention {convention!r}; known: {', '.join(CONVENTIONS)} "
                                 "(or give a mapping CSV)")
        table, source = builtin_table(convention), (
            "identity" if convention == "visemeflow16" else f"visemeflow/shapes/data/{_TABLE_FILES[convention]}")
        wanted = sorted({s for row in table.values() for s in row})
        found = _match_names(character.shape_names, wanted, where)
        if not found:
            raise CharacterError(f"{where}: none of its shapes has a name of the {convention} convention "
                                 f"(names found: {', '.join(character.shape_names[:40])})")
    renamed = {v: {found[s]: w for s, w in row.items() if s in found} for v, row in table.items()}
    matrix = table_matrix(renamed, character.shape_names)
    driven = tuple(n for i, n in enumerate(character.shape_names) if matrix[:, i].any())
    unmapped = tuple(v for i, v in enumerate(VISEMES) if not matrix[i].any())
    lost = {}
    for viseme, row in table.items():
        total = sum(row.values())
        gone = [s for s, w in row.items() if s not in found and w > 0]
        if gone and total > 0:
            lost[viseme] = (sum(row[s] for s in gone) / total, tuple(gone))
    return Binding(character.name, convention, source, tuple(character.shape_names), matrix, driven,
                   tuple(s for s in wanted if s not in found), unmapped, lost)
