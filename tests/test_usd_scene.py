"""A glTF character's USD is the user's whole scene (visemeflow/animation/usd_scene.py), read back through usd-core:
texture coordinates, materials bound per primitive (GeomSubsets), the material's inputs as the glTF states them,
textures inside the USDZ package, the meshes no target moves placed as the scene shows them, and what cannot be
carried named in the layer. Blender's own import of the avatar's USD and USDZ is in tests/test_blender.py."""

import io
import zipfile

import numpy as np
import pygltflib as gl
import pytest
from factories import usd_validation_errors
from scene_glb import EYE_AT, make_scene
from PIL import Image
from pxr import Usd, UsdGeom, UsdShade

from visemeflow.animation.load import load_character
from visemeflow.animation.usd import write_usd, write_usdz

@pytest.fixture()
def scene(tmp_path):
    arrays = make_scene(tmp_path / "scene.glb")
    character = load_character(tmp_path / "scene.glb")
    weights = np.random.default_rng(0).random((6, character.n_shapes)).astype(np.float32)
    return character, weights, arrays


def surface_inputs(material: UsdShade.Material) -> dict:
    """The UsdPreviewSurface's inputs: a value, or `(shader id, output, its inputs)` where one is connected."""
    surface = material.ComputeSurfaceSource()[0]
    out = {}
    for put in surface.GetInputs():
        if put.HasConnectedSource():
            source, output, _ = put.GetConnectedSource()
            shader = UsdShade.Shader(source.GetPrim())
            out[put.GetBaseName()] = (shader.GetIdAttr().Get(), output,
                                      {i.GetBaseName(): i.Get() for i in shader.GetInputs()})
        else:
            out[put.GetBaseName()] = put.Get()
    return out


def test_the_usdz_holds_the_whole_scene_with_its_textures(tmp_path, scene):
    character, weights, arrays = scene
    path = write_usdz(tmp_path / "take.usdz", character, weights, 30.0, name="take")
    assert sorted(zipfile.ZipFile(path).namelist()) == ["take.usdc", "textures/0_skin.png", "textures/1_normals.jpg",
                                                        "textures/2_glow.png"]     # the WebP, as PNG
    glow = Image.open(io.BytesIO(zipfile.ZipFile(path).read("textures/2_glow.png")))
    assert glow.format == "PNG" and glow.getpixel((1, 1)) == (9, 9, 9)
    stage = Usd.Stage.Open(str(path))
    assert usd_validation_errors(stage) == []
    meshes = {p.GetName(): UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}
    assert sorted(meshes) == ["EyeL", "EyeR", "Mesh"]     # the eye once per node that instances it, by node
    for k, name in enumerate(("EyeL", "EyeR")):
        points = np.asarray(meshes[name].GetPointsAttr().Get())
        np.testing.assert_allclose(points, arrays["eye"] + np.float32(EYE_AT[k]), atol=1e-6)
        assert UsdShade.MaterialBindingAPI(meshes[name]).ComputeBoundMaterial()[0].GetPath().name == "plain"
    head = meshes["Mesh"]                                         # a single driven mesh is `Mesh`, as ever
    st = np.asarray(UsdGeom.PrimvarsAPI(head).GetPrimvar("st").Get())
    np.testing.assert_allclose(st, np.c_[arrays["uv"][:, 0], 1 - arrays["uv"][:, 1]], atol=1e-7)
    assert head.GetDoubleSidedAttr().Get()                       # one of its materials is double-sided
    subsets = {UsdShade.MaterialBindingAPI(s.GetPrim()).ComputeBoundMaterial()[0].GetPath().name:
               list(s.GetIndicesAttr().Get()) for s in UsdShade.MaterialBindingAPI(head).GetMaterialBindSubsets()}
    assert subsets == {"skin": [0, 1, 2], "plain": [3, 4]}      # each primitive's triangles, in the file's order
    materials = {m.GetPath().name: UsdShade.Material(m) for m in stage.Traverse() if m.IsA(UsdShade.Material)}
    skin = surface_inputs(materials["skin"])
    kind, output, texture = skin["diffuseColor"]
    assert (kind, output, texture["sourceColorSpace"]) == ("UsdUVTexture", "rgb", "sRGB")
    assert texture["file"].path == "./textures/0_skin.png" and tuple(texture["scale"]) == pytest.approx((1, .9, .8, 1))
    assert (texture["wrapS"], texture["wrapT"]) == ("clamp", "mirror")
    assert skin["opacity"][1] == "a" and skin["opacityThreshold"] == pytest.approx(0.3)      # MASK, alphaCutoff
    kind, output, normal = skin["normal"]
    assert normal["sourceColorSpace"] == "raw" and normal["file"].path == "./textures/1_normals.jpg"
    assert tuple(normal["scale"]) == (1, 1, 2, 1) and tuple(normal["bias"]) == (-0.5, -0.5, -1, 0)   # its scale 0.5
    assert skin["metallic"] == 0 and skin["roughness"] == pytest.approx(0.6)
    assert skin["emissiveColor"][2]["file"].path == "./textures/2_glow.png"
    assert "occlusion" not in skin                              # its KTX2 image: left out, and said so
    assert "image 3 (KTX2) cannot be decoded (not an image Pillow knows; " in stage.GetRootLayer().documentation
    assert "BytesIO" not in stage.GetRootLayer().documentation      # Pillow's name of its buffer, not the user's
    plain = surface_inputs(materials["plain"])
    assert tuple(plain["diffuseColor"]) == pytest.approx((0.2, 0.3, 0.4))
    assert "opacity" not in plain and plain["metallic"] == pytest.approx(0.1)
    # the driven head still plays our weights: UsdSkel's own blend of its shapes (the eyes stay where they are)
    from pxr import Gf, UsdSkel

    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, 5))
    for k in (0, 5):
        expected = character.neutral + np.einsum("s,svc->vc", weights[k], character.deltas)
        np.testing.assert_allclose(np.asarray(head.GetPointsAttr().Get(k)), expected, atol=1e-6)


def test_a_plain_usd_carries_the_materials_without_images(tmp_path, scene):
    """A .usd is one file: no image in it, so the materials keep their factors, and the texture coordinates and
    the undriven meshes are there as in the USDZ."""
    character, weights, _ = scene
    path = write_usd(tmp_path / "take.usda", character, weights, 30.0, name="take")
    stage = Usd.Stage.Open(str(path))
    assert usd_validation_errors(stage) == []
    assert not [p for p in stage.Traverse() if p.IsA(UsdShade.Shader) and
                UsdShade.Shader(p).GetIdAttr().Get() == "UsdUVTexture"]
    skin = surface_inputs(UsdShade.Material(stage.GetPrimAtPath("/take/Materials/skin")))
    assert tuple(skin["diffuseColor"]) == pytest.approx((1, 0.9, 0.8)) and skin["opacity"] == 1
    assert sorted(p.GetName() for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)) == ["EyeL", "EyeR", "Mesh"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.glb", "take.usda"]    # nothing written beside it


def test_a_character_not_from_gltf_makes_a_usdz_of_its_stage_alone(tmp_path):
    from visemeflow.rig import load_demo_rig
    from visemeflow.rig.character import character_from_rig

    demo_character = character_from_rig(load_demo_rig())
    weights = np.zeros((3, demo_character.n_shapes), np.float32)
    path = write_usdz(tmp_path / "demo.usdz", demo_character, weights, 30.0)
    assert zipfile.ZipFile(path).namelist() == ["demo.usdc"]
    stage = Usd.Stage.Open(str(path))
    assert usd_validation_errors(stage) == []
    assert [p.GetName() for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)] == ["Mesh"]
    with pytest.raises(ValueError, match="ends in .usdz"):
        write_usdz(tmp_path / "demo.usd", demo_character, weights, 30.0)


def test_an_image_that_cannot_be_read_costs_its_texture_not_the_animation(tmp_path):
    """A .gltf whose texture file is missing beside it: the USDZ is written with that texture left out and named."""
    import json

    make_scene(tmp_path / "scene.glb")
    g = gl.GLTF2().load(str(tmp_path / "scene.glb"))
    g.convert_buffers(gl.BufferFormat.DATAURI)
    g.images[0].bufferView, g.images[0].uri = None, "skin.png"      # an external image that is not there
    text = json.loads(g.to_json())
    (tmp_path / "scene.gltf").write_text(json.dumps(text))
    character = load_character(tmp_path / "scene.gltf")
    path = write_usdz(tmp_path / "take.usdz", character, np.zeros((3, character.n_shapes), np.float32), 30.0,
                      name="take")
    assert sorted(zipfile.ZipFile(path).namelist()) == ["take.usdc", "textures/1_normals.jpg", "textures/2_glow.png"]
    stage = Usd.Stage.Open(str(path))
    assert usd_validation_errors(stage) == []
    note = stage.GetRootLayer().documentation
    assert "image 0 cannot be read" in note and "skin.png" in note, note
    skin = surface_inputs(UsdShade.Material(stage.GetPrimAtPath("/take/Materials/skin")))
    assert tuple(skin["diffuseColor"]) == pytest.approx((1, 0.9, 0.8))      # the factor alone


def test_broken_texture_coordinates_cost_the_texture_not_the_character(tmp_path):
    """NaN in TEXCOORD_0: the character loads and speaks as before (texture coordinates only colour it); the USD has
    no st on that mesh and says why."""
    make_scene(tmp_path / "scene.glb")
    g = gl.GLTF2().load(str(tmp_path / "scene.glb"))
    uv = g.accessors[g.meshes[0].primitives[0].attributes.TEXCOORD_0]
    blob = bytearray(g.binary_blob())
    view = g.bufferViews[uv.bufferView]
    blob[view.byteOffset:view.byteOffset + 4] = np.float32(np.nan).tobytes()
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(tmp_path / "broken.glb"))
    character = load_character(tmp_path / "broken.glb")
    assert character.n_vertices == 8
    path = write_usd(tmp_path / "take.usda", character, np.zeros((2, character.n_shapes), np.float32), 30.0,
                     name="take")
    stage = Usd.Stage.Open(str(path))
    assert not UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/take/Mesh")).GetPrimvar("st").IsDefined()
    assert "NaN or infinite texture coordinates" in stage.GetRootLayer().documentation


def test_a_driven_mesh_that_two_nodes_show_is_driven_at_both(tmp_path):
    """One eye mesh (with a jawOpen target, so it is driven) shown by two nodes: the USD has a driven Mesh for each
    node, placed by it, that UsdSkel deforms by the same weights (tests/test_preview.py: the preview draws both)."""
    from pxr import Gf, UsdSkel

    from visemeflow.animation.textures import appearance_notes

    arrays = make_scene(tmp_path / "eyes.glb", eye_targets=True)
    character = load_character(tmp_path / "eyes.glb")
    eye_part = next(p for p in character.parts if p.name == "Eye")
    assert len(eye_part.nodes) == 2
    weights = np.random.default_rng(0).random((4, character.n_shapes)).astype(np.float32)
    stage = Usd.Stage.Open(str(write_usd(tmp_path / "take.usda", character, weights, 30.0, name="take")))
    assert usd_validation_errors(stage) == []
    meshes = {p.GetName(): UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}
    assert sorted(meshes) == ["Eye", "EyeR", "Head"]
    assert UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetDefaultPrim()), Gf.Interval(0, 3))
    jaw = character.shape_names.index("jawOpen")
    for name, at in (("Eye", EYE_AT[0]), ("EyeR", EYE_AT[1])):
        for k in (0, 3):
            expected = arrays["eye"] + np.float32(at) + weights[k, jaw] * 0.002
            np.testing.assert_allclose(np.asarray(meshes[name].GetPointsAttr().Get(k)), expected, atol=1e-6)
    assert not any("nodes" in n for n in appearance_notes(character))     # the preview draws both now
