"""Animation: viseme curves put on characters and exported for engines and DCC tools (paper section 6).

- `load`: a character from a file (GLB/glTF, npz, mesh folder); the `Character` type is `rig.character`'s and the
  naming conventions are `shapes.conventions` (both re-exported here).
- `apply`: curve checks, resampling to another rate, chunked deformation to vertices; `lips`: the lip gap on the mesh.
- exporters, one table of them in `formats` (`EXPORTERS`, written through by `package`): `gltf_asset` (GLB), `usd` (UsdSkel), Live Link CSV
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

from visemeflow.lazy import lazy_exports

# imported from their modules on first use, so `animation.config` (read by the CLI and the flows' parameters)
# imports without the character readers
_EXPORTS = {
    **dict.fromkeys(("Character", "CharacterError", "character_from_rig"), "visemeflow.rig.character"),
    "load_character": ".load",
    **dict.fromkeys(("ARKIT_52", "OCULUS_15", "Binding", "arkit_weights", "bind", "detect_convention"),
                    "visemeflow.shapes.conventions"),
    **dict.fromkeys(("FORMATS", "CurveTrack", "curves_csv", "curves_json", "export_text", "write_export"), ".export"),
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
