"""Animation: viseme curves made usable outside the store (paper section 6).

Today the curve exports (`export.py`: CSV with one row per frame, JSON with one list per viseme) that
`visemeflow predict --out` and `visemeflow curves export` write; curves applied to meshes and bone poses and
engine exports (glTF, Live Link) come next. Pure: arrays in, text or files out; imports only `visemes`, `rig`
and the standard helpers (`atomic`), never Prefect or the store.
"""

from visemeflow.animation.export import FORMATS, CurveTrack, curves_csv, curves_json, export_text, write_export

__all__ = ["FORMATS", "CurveTrack", "curves_csv", "curves_json", "export_text", "write_export"]
