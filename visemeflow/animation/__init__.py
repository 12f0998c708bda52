"""Animation: viseme curves put on characters and exported for engines and DCC tools (paper section 6).

- `load`: a character from a file (GLB/glTF, npz, mesh folder); the `Character` type is `rig.character`'s and the
  naming conventions are `shapes.conventions` (both re-exported here).
- `apply`: curve checks, resampling to another rate, chunked deformation to vertices; `lips`: the lip gap on the mesh.
- exporters, one table of them in `package` (`EXPORTERS`): `gltf_asset` (GLB), `usd` (UsdSkel), Live Link CSV
  (`shapes.livelink`), `webjson` (TalkingHead), `export` (the 16 curves as CSV/JSON); `package` writes one
  utterance's set of them with the audio beside.
- `preview`: side-by-side MP4 previews (H.264 + AAC) drawn with the rasteriser of `render.raster`.
- `transfer`: deformation transfer (Sumner and Popovic 2004) of a viseme rig's shapes onto a new neutral mesh, with
  automatic markers (`automarkers`: FaceMesh of `tracking` on rendered faces).
- `bones`: SSDR bone poses from the visemes (py-dem-bones), per-frame pose blending and skinning, pose tables;
  `skinned_gltf` (skinned GLB) and `usd_skel` (UsdSkel SkelAnimation with joints) write the bone animation.

Pure: arrays in, files out; imports `visemes`, `rig`, `shapes`, `render`, `tracking` (FaceMesh, for the markers) and
`atomic`, never Prefect or the store.
"""

from visemeflow.rig.character import Character, CharacterError, character_from_rig
from visemeflow.animation.load import load_character
from visemeflow.shapes.conventions import ARKIT_52, OCULUS_15, Binding, arkit_weights, bind, detect_convention
from visemeflow.animation.export import FORMATS, CurveTrack, curves_csv, curves_json, export_text, write_export

__all__ = [
    "ARKIT_52", "FORMATS", "OCULUS_15", "Binding", "Character", "CharacterError", "CurveTrack", "arkit_weights",
    "bind", "character_from_rig", "curves_csv", "curves_json", "detect_convention", "export_text", "load_character",
    "write_export",
]
