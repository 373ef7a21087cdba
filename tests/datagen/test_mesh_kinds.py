"""Every kind of mesh a user brings renders in every layout and every material (issue 41).

Mesh kinds: each BOP family in ``../shared/meshes`` (vertex colours: IC-BIN, TUD-L; UV texture:
YCB-V 10; neither: ITODD, T-LESS), and meshes written here with vertex colours, a UV texture or
neither, each with and without normals. References: Mitsuba renders of a plain colour (the
vertex colours must give the same image as the same colour set as the material's), and the
datagen command's own exit.
"""

import json
import shutil

import numpy as np
import pytest
import trimesh

import threept_jax.render.mitsuba_backend as mb
from datagen import generate
from datagen import scene as S
from datagen.meshes import build_pool
from threept_jax.render.mesh import load_mesh
from threept_jax.render.mitsuba_backend import (
    Material,
    MeshRenderError,
    MitsubaScene,
    check_renders,
)

#: One mesh per BOP family, with the attributes its file carries.
FAMILIES = {"icbin": "obj_000002", "itodd": "obj_000001", "tless": "obj_000004",
            "tudl": "obj_000003", "ycbv": "obj_000010"}


def _family_folders(bop_models_dir, tmp_path):
    """One folder per family holding its one mesh (and texture) and its models_info entry."""
    folders = []
    for family, stem in FAMILIES.items():
        src = bop_models_dir / family / "models"
        dst = tmp_path / family
        dst.mkdir()
        for f in src.glob(stem + ".*"):
            shutil.copy(f, dst / f.name)
        info = json.loads((src / "models_info.json").read_text())
        key = str(int(stem.split("_")[1]))
        (dst / "models_info.json").write_text(json.dumps({key: info[key]}))
        folders.append(dst)
    return folders


def test_every_family_renders_in_every_material(bop_models_dir):
    for family, stem in FAMILIES.items():
        mesh = load_mesh(bop_models_dir / family / "models" / f"{stem}.ply")
        has = {"tudl": "colors", "icbin": "colors", "ycbv": "texture"}.get(family)
        if has == "colors":
            assert mesh.colors is not None and mesh.texture is None, family
        elif has == "texture":
            assert mesh.texture is not None, family
        else:
            assert mesh.colors is None and mesh.texture is None, family
        check_renders(mesh)  # diffuse, plastic and conductor with the mesh's own colours


def _box_file(tmp_path, kind: str, normals: bool):
    """A 40 mm box written as PLY with vertex colours, a UV texture, or neither."""
    box = trimesh.creation.box((40.0, 30.0, 20.0))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    colors = uv = None
    tex = None
    if kind == "colors":
        colors = np.tile([0.8, 0.1, 0.1], (len(v), 1))
    elif kind == "texture":
        uv = (v[:, :2] - v[:, :2].min(0)) / np.ptp(v[:, :2], 0)
        tex = f"box_{normals}.png"
        import cv2

        img = np.zeros((16, 16, 3), np.uint8)
        img[..., 2] = 200  # red in OpenCV's BGR
        cv2.imwrite(str(tmp_path / tex), img)
    path = tmp_path / f"box_{kind}_{normals}.ply"
    S.write_ply(path, v, f, colors, uv, tex)
    if normals:  # rewrite through trimesh with vertex normals in the file
        m = trimesh.load(path, process=False)
        m.vertex_normals  # noqa: B018 - computed and then exported
        data = trimesh.exchange.ply.export_ply(m, vertex_normal=True, include_attributes=True)
        path.write_bytes(data)
    return path


@pytest.mark.parametrize("normals", [False, True])
@pytest.mark.parametrize("kind", ["colors", "texture", "plain"])
def test_attribute_kinds_render_in_every_material(tmp_path, kind, normals):
    path = _box_file(tmp_path, kind, normals)
    mesh = load_mesh(path)
    assert (mesh.colors is not None) == (kind == "colors")
    check_renders(mesh)


def _plastic_view(mesh, color):
    scene = MitsubaScene(max_depth=3)
    scene.add_object(mesh, np.eye(4), Material("plastic", color=color, roughness=0.3))
    scene.set_environment((1.0, 1.0, 1.0))
    K = np.array([[60.0, 0, 16], [0, 60.0, 16], [0, 0, 1]])
    T = np.eye(4)
    T[2, 3] = 120.0
    return scene.render(K, T, (32, 32), spp=64, seed=0, outputs=("rgb", "mask"), linear=True)


def test_vertex_colours_reach_plastic_renders(tmp_path):
    """A plastic box in its own red vertex colours renders as the same box with that red as the
    material's colour (same seed), not grey: the colours a part has reach the image."""
    mesh = load_mesh(_box_file(tmp_path, "colors", False))
    own = _plastic_view(mesh, None)
    ref = _plastic_view(mesh.replace(colors=None), (0.8, 0.1, 0.1))
    m = own["mask"]
    assert m.sum() > 100
    np.testing.assert_allclose(own["rgb"][m], ref["rgb"][m], atol=0.02)
    r, g, b = own["rgb"][m].mean(0)
    assert r > 2 * g and r > 2 * b, (r, g, b)


def test_a_mesh_mitsuba_refuses_is_named_by_adapts_check(bop_models_dir, tmp_path, monkeypatch):
    """Mitsuba's own vertex-colour texture (the cause of issue 41) put back: the check says which
    file and why in one line each, before any workdir exists."""
    from train import adapt

    def old_albedo(mi, mesh, raw):
        if mesh.colors is not None:
            return {"type": "mesh_attribute", "name": "vertex_color"}
        return {"type": "rgb", "value": [0.5] * 3}

    monkeypatch.setattr(mb, "_albedo_texture_dict", old_albedo)
    mesh = load_mesh(bop_models_dir / "tudl" / "models" / "obj_000003.ply")
    with pytest.raises(MeshRenderError, match=r"Texture::mean\(\)"):
        check_renders(mesh)
    work = tmp_path / "w"
    with pytest.raises(SystemExit, match=r"(?s)no usable mesh.*obj_000003.ply: does not render "
                                         r"in Mitsuba: .*Texture::mean\(\)"):
        adapt.main(["--meshes", str(bop_models_dir / "tudl" / "models"), "--workdir", str(work),
                    "--from", "scratch"])
    assert not work.exists()
    pool = build_pool([bop_models_dir / "itodd" / "models"])
    assert S.render_problems(pool, [0]) == {}  # no vertex colours: unaffected


@pytest.mark.parametrize("layout", S.LAYOUTS)
def test_every_layout_with_every_family(bop_models_dir, tmp_path, layout):
    """``datagen --layout L`` over one mesh of each BOP family at a tiny resolution."""
    folders = _family_folders(bop_models_dir, tmp_path)
    out = tmp_path / "out"
    generate.main(["--meshes", *map(str, folders), "--out", str(out), "--num-scenes", "1",
                   "--layout", layout, "--resolution", "64", "48", "--spp", "1",
                   "--max-depth", "2", "--instances", "5", "--distinct", "5", "5", "--seed", "1",
                   "--image-format", "png", "--quiet"])
    gt = json.loads((out / "train_pbr" / "000000" / "scene_gt.json").read_text())
    ids = {g["obj_id"] for rows in gt.values() for g in rows}
    assert len(ids) == 5, ids
