"""The MaterialX and OpenUSD exports of a glTF fit read by the formats' own libraries
(PyPI `MaterialX` and `usd-core`):

- MaterialX: the document loads with the standard data libraries and `validate()` passes;
  it has one `standard_surface` whose base colour, metalness, roughness and normal come from
  image nodes that name files which exist; the provenance is JSON in the `doc` attribute.
- USD: the stage opens, its mesh is bound to a material whose surface is a
  `UsdPreviewSurface`, every `UsdUVTexture` resolves its file to an existing PNG, and the
  layer's customLayerData holds the provenance.

- USDZ (optional third argument, `gonio export --format usd OUT.usdz`): the same checks on
  the package, whose textures resolve inside it; every file is stored (not compressed) with
  its data 64-byte aligned, and `material.usda` comes first.

Usage: check_material_export.py MATERIALX_DIR USD_DIR [USDZ_FILE]
"""
import json
import os
import sys

import MaterialX as mx
from pxr import Sdf, Usd, UsdShade


def check_materialx(folder):
    path = os.path.join(folder, "material.mtlx")
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, path)
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    doc.importLibrary(lib)
    ok, msg = doc.validate()
    assert ok, f"{path}: MaterialX validate(): {msg}"
    shaders = [n for n in doc.getNodes() if n.getCategory() == "standard_surface"]
    assert len(shaders) == 1, f"{path}: {len(shaders)} standard_surface nodes"
    connected = {i.getName() for i in shaders[0].getInputs() if i.getNodeGraphString()}
    want = {"base_color", "metalness", "specular_roughness", "normal"}
    assert want <= connected, f"{path}: inputs fed by the node graph: {connected}"
    files = []
    for ng in [doc.getNodeGraph("NG_gonio")]:
        for n in ng.getNodes("image"):
            f = n.getInput("file").getValueString()
            assert os.path.isfile(os.path.join(folder, f)), f"{path}: image {n.getName()}: {f} missing"
            files.append(f)
    # An anisotropic fit (KHR_materials_anisotropy) adds specular_anisotropy and
    # specular_rotation, both fed by images.
    assert len(files) in (4, 6), files
    if len(files) == 6:
        want = {"specular_anisotropy", "specular_rotation"}
        assert want <= connected, f"{path}: anisotropy inputs fed by the node graph: {connected}"
    prov = json.loads(doc.getDocString())
    assert prov["generator"].startswith("gonio"), prov
    print(f"materialx {mx.__version__}: {path}: validate() passes, standard_surface fed by {len(files)} images, "
          f"provenance {sorted(prov)[:3]}...")


def check_usd(folder):
    usdz = folder.endswith(".usdz")
    path = folder if usdz else os.path.join(folder, "material.usda")
    if usdz:
        z = Sdf.ZipFile.Open(path)
        names = list(z.GetFileNames())
        assert names and names[0] == "material.usda", f"{path}: entries {names}"
        for n in names:
            info = z.GetFileInfo(n)
            assert info.compressionMethod == 0 and info.dataOffset % 64 == 0, f"{path}: {n}: {info.dataOffset}"
        inside = set(names)
    stage = Usd.Stage.Open(path)
    assert stage, path
    prov = json.loads(stage.GetRootLayer().customLayerData["gonio_provenance"])
    assert prov["generator"].startswith("gonio"), prov
    mesh = stage.GetPrimAtPath("/Sample/Quad")
    material, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
    assert material, f"{path}: the mesh has no bound material"
    surface = material.ComputeSurfaceSource()[0]
    assert surface and surface.GetIdAttr().Get() == "UsdPreviewSurface", f"{path}: surface {surface}"
    textures = 0
    for prim in stage.Traverse():
        if prim.GetTypeName() != "Shader":
            continue
        shader = UsdShade.Shader(prim)
        if shader.GetIdAttr().Get() != "UsdUVTexture":
            continue
        asset = shader.GetInput("file").Get()
        if usdz:
            # Resolved inside the package: `PATH[textures/x.png]`.
            assert asset.resolvedPath and asset.path in inside, f"{path}: {prim.GetPath()}: {asset.path} unresolved"
        else:
            assert asset.resolvedPath and os.path.isfile(asset.resolvedPath), f"{path}: {prim.GetPath()}: {asset.path} unresolved"
        textures += 1
    assert textures == 4, textures
    print(f"usd-core: {path}: opened, UsdPreviewSurface bound, {textures} UsdUVTexture files resolved, provenance present")


if __name__ == "__main__":
    check_materialx(sys.argv[1])
    check_usd(sys.argv[2])
    if len(sys.argv) > 3:
        check_usd(sys.argv[3])
