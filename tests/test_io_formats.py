"""The user's files kept whole: OBJ (materials, maps, mixed UV faces, groups), glTF (primitives, nodes, materials,
images), PLY colours; after a deformation every feature is still there, compared feature by feature with the
input, and the positions are the deformation's. Files made here, and the ShapeNetCore.v2 models of the shared data.
"""

from __future__ import annotations

import json
import logging
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from helpers import height_field, make_obj

from kpd.io import Mesh, read_mesh, write_mesh
from kpd.io.gltf import read_gltf_json

SHAPENET = "shapenetcore_obj"


# --- files made here ---------------------------------------------------------------------------------------------


def affine(vertices: np.ndarray) -> np.ndarray:
    """A deformation that moves every vertex (a shear and a bend), standing in for a rig's."""
    out = vertices.copy()
    out[:, 0] += 0.3 * vertices[:, 1]
    out[:, 2] += 0.2 * vertices[:, 0] ** 2
    return out


def obj_lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def parse_numbers(lines: list[str], key: str) -> np.ndarray:
    return np.array([[float(x) for x in s.split()[1:4]] for s in lines if s.split()[:1] == [key]])


def assert_obj_kept(src: Path, out: Path, vertices: np.ndarray, *, outside: bool = False) -> None:
    """``out`` is ``src`` with only its v (and vn) lines and the names of its companions changed; the v lines hold
    ``vertices``; the .mtl and every map are there, maps byte for byte. A map outside the input's folder (``../``)
    is commented out and not copied, unless ``outside`` (it was read from a wider ``files_root``)."""
    a, b = obj_lines(src), obj_lines(out)
    assert len(a) == len(b)
    for x, y in zip(a, b):
        key = x.split()[:1]
        if key in (["v"], ["vn"]):
            assert y.split()[:1] == key
        elif key == ["mtllib"]:
            assert y == f"mtllib {out.stem}.mtl"
        else:
            assert x == y  # faces, groups, smoothing, materials, lines, comments: as they were
    np.testing.assert_allclose(parse_numbers(b, "v"), vertices, rtol=1e-8, atol=1e-12)
    normals, before = parse_numbers(b, "vn"), parse_numbers(a, "vn")
    if len(normals):  # turned, each keeping its length (ShapeNet stores some scaled by 0.0254)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), np.linalg.norm(before, axis=1), atol=1e-5)
    src_mtl = [s for s in obj_lines(src) if s.startswith("mtllib")]
    if not src_mtl:
        return
    mtl_in = (src.parent / src_mtl[0].split(None, 1)[1]).read_text().splitlines()
    mtl_out = (out.parent / f"{out.stem}.mtl").read_text().splitlines()
    assert len(mtl_in) == len(mtl_out)
    for x, y in zip(mtl_in, mtl_out):
        if x.split()[:1] and x.split()[0].lower() in ("map_kd", "bump", "map_bump", "map_ks", "map_d", "norm") and \
                x.split()[-1].startswith("../") and not outside:  # not read, not copied, not named
            assert y == f"# {x} (not read by kpd)"
            assert not (out.parent / f"{out.stem}_{Path(x.split()[-1]).name}").exists()
        elif x.split()[:1] and x.split()[0].lower() in ("map_kd", "bump", "map_bump", "map_ks", "map_d", "norm"):
            old, new = x.split()[-1], y.split()[-1]
            assert x.rsplit(None, 1)[0] == y.rsplit(None, 1)[0]  # options kept
            assert new == f"{out.stem}_{Path(old).name}"
            assert (out.parent / new).read_bytes() == (src.parent / old).read_bytes()  # a JPEG stays that JPEG
        else:
            assert x == y  # Kd, Ks, illum, comments: as they were


def assert_same_features(a: Mesh, b: Mesh) -> None:
    """Everything but the positions and normals."""
    np.testing.assert_array_equal(a.triangles, b.triangles)
    for name in ("triangle_material_ids", "triangle_uv_mask", "vertex_colors"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_allclose(x, y, atol=1e-6, err_msg=name)
    assert (a.triangle_uvs is None) == (b.triangle_uvs is None)
    if a.triangle_uvs is not None:
        np.testing.assert_allclose(a.triangle_uvs, b.triangle_uvs, atol=1e-6)
    assert len(a.textures) == len(b.textures)
    for x, y in zip(a.textures, b.textures):
        np.testing.assert_array_equal(x, y)


# --- OBJ -----------------------------------------------------------------------------------------------------------


def test_obj_reads_the_files_vertices_materials_and_mixed_uv_faces(tmp_path):
    path = make_obj(tmp_path)
    mesh = read_mesh(path)
    text = obj_lines(path)
    np.testing.assert_allclose(mesh.vertices, parse_numbers(text, "v"))  # the file's v lines, in order
    faces = [s for s in text if s.startswith("f")]
    assert len(mesh.triangles) == len(faces)
    with_uv = np.array(["//" not in s for s in faces])
    np.testing.assert_array_equal(mesh.triangle_uv_mask, with_uv)
    # materials in order of first use: wood (a JPEG map), red (a colour), label (a PNG map)
    T = len(faces)
    assert mesh.triangle_material_ids[0] == 0 and mesh.triangle_material_ids[T // 3] == 1
    assert mesh.triangle_material_ids[-1] == 2
    assert mesh.textures[0].shape == (8, 16, 3)
    assert np.abs(mesh.textures[0][-1, 0].astype(int) - (120, 80, 40)).max() <= 6  # JPEG: close to the colour
    assert mesh.textures[0][0, 0, 0] > 240  # top row first, as in the image file
    np.testing.assert_array_equal(mesh.textures[1], [[[230, 26, 26]]])  # Kd 0.9 0.1 0.1
    np.testing.assert_array_equal(mesh.textures[2][-1, 0], (20, 60, 200))


def test_obj_deformed_keeps_everything_but_the_positions(tmp_path):
    path = make_obj(tmp_path / "in")
    mesh = read_mesh(path)
    moved = mesh.with_vertices(affine(mesh.vertices))
    out = tmp_path / "out" / "deformed.obj"
    out.parent.mkdir()
    write_mesh(out, moved)
    assert sorted(os.listdir(out.parent)) == ["deformed.mtl", "deformed.obj", "deformed_label.png",
                                              "deformed_wood.jpg"]
    assert_obj_kept(path, out, moved.vertices)
    back = read_mesh(out)
    assert_same_features(mesh, back)
    np.testing.assert_allclose(back.vertices, moved.vertices, rtol=1e-8)


def test_obj_written_unchanged_is_the_input(tmp_path):
    path = make_obj(tmp_path / "in")
    out = tmp_path / "same.obj"
    write_mesh(out, read_mesh(path))
    assert out.read_text() == path.read_text().replace("mtllib thing.mtl", "mtllib same.mtl")


def test_obj_normals_turn_with_the_surface(tmp_path):
    """Rotating the whole mesh rotates every vn line by the same rotation."""
    from scipy.spatial.transform import Rotation

    path = make_obj(tmp_path / "in")
    mesh = read_mesh(path)
    rotation = Rotation.from_euler("xyz", [30, -50, 80], degrees=True).as_matrix()
    write_mesh(tmp_path / "turned.obj", mesh.with_vertices(mesh.vertices @ rotation.T))
    before, after = parse_numbers(obj_lines(path), "vn"), parse_numbers(obj_lines(tmp_path / "turned.obj"), "vn")
    np.testing.assert_allclose(after, before @ rotation.T, atol=1e-5)  # the file's normals have 6 decimals


def test_obj_vertex_colours_round_trip_in_order(tmp_path):
    vertices, triangles = height_field(4)
    colors = np.random.default_rng(1).random((len(vertices), 3))
    text = "".join(f"v {x!r} {y!r} {z!r} {r:.6f} {g:.6f} {b:.6f}\n" for (x, y, z), (r, g, b) in zip(vertices.tolist(),
                                                                                                    colors.tolist()))
    text += "".join(f"f {a} {b} {c}\n" for a, b, c in (triangles + 1).tolist())
    (tmp_path / "c.obj").write_text(text)
    mesh = read_mesh(tmp_path / "c.obj")
    np.testing.assert_allclose(mesh.vertex_colors, colors, atol=1e-6)
    write_mesh(tmp_path / "d.obj", mesh.with_vertices(mesh.vertices * 2))
    out = obj_lines(tmp_path / "d.obj")
    assert [s.split()[4:] for s in out if s.startswith("v ")] == [s.split()[4:] for s in text.splitlines()
                                                                 if s.startswith("v ")]
    np.testing.assert_allclose(read_mesh(tmp_path / "d.obj").vertex_colors, colors, atol=1e-6)


def test_obj_companions_never_collide_and_are_checked_before_writing(tmp_path):
    from kpd.io import Outputs, mesh_companions

    path = make_obj(tmp_path / "in")
    mesh = read_mesh(path)
    names = mesh_companions(tmp_path / "a.obj", mesh)
    assert sorted(names) == ["a.mtl", "a_label.png", "a_wood.jpg"]
    write_mesh(tmp_path / "a.obj", mesh)
    write_mesh(tmp_path / "b.obj", mesh)  # a second output beside the first: its own companions
    assert len(os.listdir(tmp_path)) == 1 + 4 + 4
    (tmp_path / "c_wood.jpg").write_bytes(b"x")  # a companion's name taken: refused before any work
    with pytest.raises(Exception, match=r"c_wood\.jpg exists; pass --force"):
        with Outputs(force=False) as outputs:
            out = outputs.file(tmp_path / "c.obj")
            outputs.companions(out, mesh_companions(out, mesh))
    assert not (tmp_path / "c.obj").exists() and (tmp_path / "c_wood.jpg").read_bytes() == b"x"


def test_obj_read_other_ways_is_written_from_its_arrays(tmp_path):
    """A mesh with new topology (no source file) is written with its materials, its colours as Kd, UVs only on the
    faces that have them."""
    path = make_obj(tmp_path / "in")
    mesh = read_mesh(path)
    fresh = Mesh(mesh.vertices, mesh.triangles, mesh.vertex_normals, None, mesh.triangle_uvs, mesh.textures,
                 mesh.triangle_material_ids, mesh.triangle_uv_mask)
    write_mesh(tmp_path / "fresh.obj", fresh)
    mtl = (tmp_path / "fresh.mtl").read_text()
    assert "Kd 0.901961 0.101961 0.101961" in mtl and mtl.count("map_Kd") == 2
    back = read_mesh(tmp_path / "fresh.obj")
    assert_same_features(mesh, back)


def test_missing_material_library_and_map_are_warnings(tmp_path, caplog):
    path = make_obj(tmp_path / "in")
    (tmp_path / "in" / "models" / "images" / "label.png").unlink()
    mesh = read_mesh(path)
    assert "label.png" in caplog.text and "missing" in caplog.text
    assert mesh.textures[2].shape == (1, 1, 3)  # drawn in its colour
    write_mesh(tmp_path / "out.obj", mesh.with_vertices(mesh.vertices + 1))
    assert sorted(os.listdir(tmp_path)) == ["in", "out.mtl", "out.obj", "out_wood.jpg"]
    assert "images/label.png" in (tmp_path / "out.mtl").read_text()  # the reference kept as the input had it
    (tmp_path / "in" / "models" / "thing.mtl").unlink()
    caplog.clear()
    mesh = read_mesh(path)
    assert "material library 'thing.mtl' is missing" in caplog.text
    assert mesh.textures == [] and mesh.triangle_uv_mask is not None


@pytest.mark.parametrize("text, message", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3 4\nf 1/1 2/2 3 4\n", r"line 6: the corners of a face must"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", r"1 face has fewer than 3 vertices"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1 2 3\n", r"line 4: the corners of a face must all have the same form"),
    ("v 0 0 0\nv 1 0 x\nv 0 1 0\nf 1 2 3\n", r"line 2: a 'v' line holds something that is not a number"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n", r"a face has the vertex index 0"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/5 2/1 3/1\nvt 0 0\n", r"1 face names a texture coordinate outside 1\.\.1"),
])
def test_malformed_obj_is_one_line(tmp_path, text, message):
    from kpd.errors import InputError

    (tmp_path / "bad.obj").write_text(text)
    with pytest.raises(InputError, match=r"bad\.obj: .*" + message):
        read_mesh(tmp_path / "bad.obj")


def test_quads_and_ngons_read_as_fans_and_written_back_as_they_were(tmp_path):
    """Blender writes quads and n-gons: read as fans of triangles (materials and UVs per triangle), written back in
    the file's own lines."""
    text = ("mtllib q.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
            "usemtl a\nf 1/1 2/2 3/3 4/4\nusemtl b\nf 2 5 6 3\nf 1 2 5 6 3\n")
    (tmp_path / "q.obj").write_text(text)
    (tmp_path / "q.mtl").write_text("newmtl a\nKd 1 0 0\nnewmtl b\nKd 0 0 1\n")
    mesh = read_mesh(tmp_path / "q.obj")
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2], [0, 1, 4], [0, 4, 5],
                                                   [0, 5, 2]])
    np.testing.assert_array_equal(mesh.triangle_material_ids, [0, 0, 1, 1, 1, 1, 1])
    np.testing.assert_array_equal(mesh.triangle_uv_mask, [True, True, False, False, False, False, False])
    np.testing.assert_allclose(mesh.triangle_uvs[:6], [[0, 0], [1, 0], [1, 1], [0, 0], [1, 1], [0, 1]])
    np.testing.assert_array_equal(mesh.triangle_uvs[6:], 0.0)  # the faces without coordinates: zeros
    write_mesh(tmp_path / "out.obj", mesh.with_vertices(mesh.vertices + [0, 0, 1]))
    out = obj_lines(tmp_path / "out.obj")
    assert [s for s in out if not s.startswith(("v ", "mtllib"))] == \
        [s for s in text.splitlines() if not s.startswith(("v ", "mtllib"))]
    np.testing.assert_allclose(read_mesh(tmp_path / "out.obj").vertices, mesh.vertices + [0, 0, 1])


def test_negative_obj_indices_count_back_from_the_face(tmp_path):
    (tmp_path / "n.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 1 1 1\nf -4 -3 -1\n")
    np.testing.assert_array_equal(read_mesh(tmp_path / "n.obj").triangles, [[0, 1, 2], [0, 1, 3]])


# --- glTF ----------------------------------------------------------------------------------------------------------


def make_glb(tmp_path: Path) -> Path:
    """A .glb with two mesh nodes (one rotated and moved), several primitives, a JPEG and a PNG image, base colours,
    a sampler and extras, from the OBJ above through kpd's own writer and then edited as exporters write them."""
    obj = read_mesh(make_obj(tmp_path / "src"))
    write_mesh(tmp_path / "one.glb", obj)
    doc, chunk = read_gltf_json(tmp_path / "one.glb")
    primitive = json.loads(json.dumps(doc["meshes"][0]["primitives"][0]))
    chunk = bytearray(chunk)
    for name in ("POSITION", "NORMAL"):  # the copy's own vertex data
        accessor = dict(doc["accessors"][primitive["attributes"][name]])
        view = dict(doc["bufferViews"][accessor["bufferView"]])
        data = bytes(chunk[view["byteOffset"] : view["byteOffset"] + view["byteLength"]])
        view["byteOffset"] = len(chunk)
        chunk += data
        doc["bufferViews"].append(view)
        accessor["bufferView"] = len(doc["bufferViews"]) - 1
        doc["accessors"].append(accessor)
        primitive["attributes"][name] = len(doc["accessors"]) - 1
    chunk = bytes(chunk)
    doc["buffers"][0]["byteLength"] = len(chunk)
    doc["meshes"].append({"name": "copy", "primitives": [primitive]})
    doc["nodes"] = [{"name": "root", "children": [1, 2], "extras": {"kept": True}},
                    {"mesh": 0}, {"mesh": 1, "rotation": [0.0, 0.7071068, 0.0, 0.7071068], "translation": [2, 0, 1],
                                  "scale": [1, 2, 1]}]
    doc["scenes"] = [{"nodes": [0]}]
    doc["samplers"] = [{"magFilter": 9729, "wrapS": 10497}]
    for texture in doc.get("textures", []):
        texture["sampler"] = 0
    doc["materials"][1]["name"] = "painted red"
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(chunk), 0x004E4942) + chunk
    path = tmp_path / "scene.glb"
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    return path


def test_glb_with_several_primitives_and_nodes_reads_in_world_coordinates(tmp_path):
    path = make_glb(tmp_path)
    mesh = read_mesh(path)
    doc, _ = read_gltf_json(path)
    counts = [doc["accessors"][p["attributes"]["POSITION"]]["count"] for m in doc["meshes"] for p in m["primitives"]]
    assert len(mesh.vertices) == sum(counts)
    first = doc["accessors"][doc["meshes"][1]["primitives"][0]["attributes"]["POSITION"]]["count"]
    copy = mesh.vertices[-first:]  # the second node: its primitive rotated 90 degrees about y, stretched, moved
    original = mesh.vertices[:first]
    expected = (original * [1, 2, 1]) @ np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]]).T + [2, 0, 1]
    np.testing.assert_allclose(copy, expected, atol=1e-5)
    assert mesh.triangle_uv_mask is not None and not mesh.triangle_uv_mask.all() and mesh.triangle_uv_mask.any()
    assert len(mesh.textures) == 3 and mesh.textures[1].shape == (1, 1, 3)


def test_glb_deformed_keeps_every_node_primitive_material_and_image(tmp_path):
    path = make_glb(tmp_path)
    mesh = read_mesh(path)
    moved = mesh.with_vertices(affine(mesh.vertices))
    write_mesh(tmp_path / "out.glb", moved)
    before, chunk_before = read_gltf_json(path)
    after, chunk_after = read_gltf_json(tmp_path / "out.glb")
    for key in set(before) | set(after):
        if key != "accessors":
            assert before.get(key) == after.get(key), key  # nodes, meshes, materials, images, samplers, extras
    for a, b in zip(before["accessors"], after["accessors"]):
        assert {k: v for k, v in a.items() if k not in ("min", "max")} == \
            {k: v for k, v in b.items() if k not in ("min", "max")}
    for image in before["images"]:  # the image bytes themselves, JPEG kept
        view = before["bufferViews"][image["bufferView"]]
        start, stop = view.get("byteOffset", 0), view.get("byteOffset", 0) + view["byteLength"]
        assert chunk_before[start:stop] == chunk_after[start:stop]
    assert {i["mimeType"] for i in before["images"]} == {"image/jpeg", "image/png"}
    back = read_mesh(tmp_path / "out.glb")
    assert_same_features(mesh, back)
    np.testing.assert_allclose(back.vertices, moved.vertices, atol=2e-6)


def test_glb_data_shared_by_two_placements_is_split_not_overwritten(tmp_path):
    """Two nodes whose meshes share one POSITION accessor, placed apart: each keeps its own deformed positions."""
    obj = read_mesh(make_obj(tmp_path / "src"))
    write_mesh(tmp_path / "one.glb", obj)
    doc, chunk = read_gltf_json(tmp_path / "one.glb")
    doc["meshes"].append({"primitives": [dict(doc["meshes"][0]["primitives"][0])]})
    doc["nodes"] = [{"mesh": 0}, {"mesh": 1, "translation": [3, 0, 0]}]
    doc["scenes"] = [{"nodes": [0, 1]}]
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(chunk), 0x004E4942) + chunk
    (tmp_path / "shared.glb").write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    mesh = read_mesh(tmp_path / "shared.glb")
    moved = mesh.with_vertices(affine(mesh.vertices))
    write_mesh(tmp_path / "out.glb", moved)
    back = read_mesh(tmp_path / "out.glb")
    np.testing.assert_allclose(back.vertices, moved.vertices, atol=2e-6)
    assert_same_features(mesh, back)


def test_gltf_is_y_up():
    from kpd.io import file_up

    assert file_up("a.glb") == file_up("b.GLTF") == "+y" and file_up("c.obj") is None


# --- PLY colours ---------------------------------------------------------------------------------------------------


def test_ply_colours_and_order_survive_a_deformation(tmp_path):
    vertices, triangles = height_field(5)
    colors = np.random.default_rng(2).integers(0, 256, (len(vertices), 3)) / 255.0
    mesh = Mesh(vertices, triangles, vertex_colors=colors)
    write_mesh(tmp_path / "c.ply", mesh)
    read = read_mesh(tmp_path / "c.ply")
    write_mesh(tmp_path / "d.ply", read.with_vertices(affine(read.vertices)))
    back = read_mesh(tmp_path / "d.ply")
    np.testing.assert_array_equal(back.triangles, triangles)
    np.testing.assert_allclose(back.vertex_colors, colors, atol=0.5 / 255)
    np.testing.assert_array_equal(back.vertices, affine(vertices))


# --- the ShapeNetCore.v2 models --------------------------------------------------------------------------------------


def shapenet_files(data_dir: Path) -> list[Path]:
    files = sorted((data_dir / SHAPENET).glob("*/*/models/model_normalized.obj"))
    if not files:
        pytest.skip(f"{data_dir / SHAPENET} holds no models")
    return files


def test_every_shapenet_model_keeps_its_materials_maps_and_uvs_through_a_deformation(data_dir, tmp_path, caplog):
    """All 38 models: the deformed output is the input's own file with new v and vn lines, its .mtl and every map
    beside it, and reads back with the same materials, textures, UVs and UV mask. ShapeNet keeps its maps in
    ``../images`` beside the ``models`` folder: that layout is read as it is, with no warning, and reads as the
    model's own folder named as ``files_root`` does."""
    files = shapenet_files(data_dir)
    mixed = textured = 0
    for i, path in enumerate(files):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            mesh = read_mesh(path)
        assert not [r for r in caplog.records if "is not read" in r.getMessage()], path
        trusted = read_mesh(path, files_root=path.parents[1])
        assert len(mesh.textures) == len(trusted.textures)
        assert all(np.array_equal(a, b) for a, b in zip(mesh.textures, trusted.textures))
        moved = mesh.with_vertices(affine(mesh.vertices))
        out = tmp_path / f"m{i}" / "out.obj"
        out.parent.mkdir()
        write_mesh(out, moved)
        assert_obj_kept(path, out, moved.vertices, outside=True)
        assert_same_features(mesh, read_mesh(out))
        mixed += mesh.triangle_uv_mask is not None and bool(mesh.triangle_uv_mask.any())
        textured += any(t.shape[0] > 1 for t in mesh.textures)
    assert len(files) == 38 and mixed >= 12 and textured == 20


def test_shapenet_deformed_by_a_rig_writes_the_rigs_positions(data_dir, tmp_path):
    """kpd deform on real models (y up, --scan --up +y): the written v lines are Rig.deform's positions."""
    from kpd.cli import main
    from kpd.frame import ScanFrame
    from kpd.runtime import Model

    model = Model.load("chair")
    files = shapenet_files(data_dir)
    for path in (files[2], files[21]):  # a bench and a cup, both with faces with and without UVs
        out = tmp_path / path.parts[-3] / "out.obj"
        out.parent.mkdir()
        assert main(["deform", "chair", str(path), "--scan", "--up", "+y", "--move", "8:0,0.05,0", "--out",
                     str(out)]) == 0
        mesh = read_mesh(path)
        scan = ScanFrame(model, mesh, "+y")
        work = mesh.with_vertices(scan.to_aligned(mesh.vertices))
        rig = model.rig(work, seed=0)
        vertices = rig.deform(rig.moved({8: scan.vector_to_aligned(np.array([0, 0.05, 0]))}))
        expected = mesh.vertices + scan.vector_to_original(vertices - work.vertices)
        assert_obj_kept(path, out, expected, outside=True)


def test_gltf_with_external_buffer_and_images_keeps_them_beside_the_output(tmp_path):
    """A .gltf whose buffer and images are files beside it: the output's buffer holds the new positions, its images
    are the input's bytes, both under the output's name, and the companions are named before writing."""
    from kpd.io import mesh_companions

    glb = make_glb(tmp_path)
    doc, chunk = read_gltf_json(glb)
    folder = tmp_path / "scene"
    folder.mkdir()
    for i, image in enumerate(doc["images"]):
        view = doc["bufferViews"][image.pop("bufferView")]
        name = f"map {i}.{'jpg' if image.pop('mimeType') == 'image/jpeg' else 'png'}"
        (folder / name).write_bytes(chunk[view["byteOffset"] : view["byteOffset"] + view["byteLength"]])
        image["uri"] = name.replace(" ", "%20")
    (folder / "data.bin").write_bytes(chunk)
    doc["buffers"][0]["uri"] = "data.bin"
    (folder / "scene.gltf").write_text(json.dumps(doc))
    mesh = read_mesh(folder / "scene.gltf")
    moved = mesh.with_vertices(affine(mesh.vertices))
    out = tmp_path / "out" / "moved.gltf"
    out.parent.mkdir()
    names = mesh_companions(out, moved)
    write_mesh(out, moved)
    assert sorted(os.listdir(out.parent)) == sorted(["moved.gltf", *names])
    assert sorted(names) == ["moved_data.bin", "moved_map 0.jpg", "moved_map 1.png"]
    for i in range(2):
        suffix = "jpg" if i == 0 else "png"
        assert (out.parent / f"moved_map {i}.{suffix}").read_bytes() == (folder / f"map {i}.{suffix}").read_bytes()
    back = read_mesh(out)
    assert_same_features(mesh, back)
    np.testing.assert_allclose(back.vertices, moved.vertices, atol=2e-6)
    assert (folder / "data.bin").read_bytes() == chunk  # the input untouched


# --- the vectorised OBJ reader against a line-by-line reading -------------------------------------------------------


def _reference(text: str):
    """The plain reading of an OBJ, line by line: vertices, triangles (polygons as fans), per-triangle UV presence and
    material."""
    v, vt, faces, has_uv, material, current = [], [], [], [], [], None
    for line in text.splitlines():
        line = line.split("#")[0].strip()
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            v.append([float(x) for x in parts[1:4]])
        elif parts[0] == "vt":
            vt.append([float(x) for x in parts[1:3]])
        elif parts[0] == "usemtl":
            current = parts[1]
        elif parts[0] == "f":
            corners = [c.split("/") for c in parts[1:]]

            def index(s, n):
                i = int(s)
                return i - 1 if i > 0 else n + i

            polygon = [index(c[0], len(v)) for c in corners]
            for i in range(1, len(polygon) - 1):  # a fan from the first corner
                faces.append([polygon[0], polygon[i], polygon[i + 1]])
                has_uv.append(all(len(c) > 1 and c[1] != "" for c in corners))
                material.append(current)
    return np.array(v), np.array(faces), np.array(has_uv), material


@st.composite
def obj_texts(draw):
    n = draw(st.integers(3, 12))
    rows = draw(st.lists(st.tuples(*[st.floats(-100, 100, allow_nan=False, width=32)] * 3), min_size=n, max_size=n))
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in rows]
    lines += [f"vt {i / 10} {i / 20}" for i in range(4)] + ["vn 0 0 1"]
    newline = draw(st.sampled_from(["\n", "\r\n"]))
    for _ in range(draw(st.integers(1, 15))):
        kind = draw(st.sampled_from(["v", "v/vt", "v/vt/vn", "v//vn", "usemtl", "g", "comment", "blank"]))
        if kind == "usemtl":
            lines.append(f"usemtl m{draw(st.integers(0, 2))}")
        elif kind == "g":
            lines.append("g part  # a group")
        elif kind == "comment":
            lines.append("# f 1 2 3 is not a face")
        elif kind == "blank":
            lines.append("  ")
        else:
            corners = []
            for _ in range(draw(st.integers(3, 5))):
                a = draw(st.integers(1, n))
                a = str(a) if draw(st.booleans()) else str(a - n - 1)  # relative: -1 is the last v so far
                t = str(draw(st.integers(1, 4)))
                corners.append({"v": a, "v/vt": f"{a}/{t}", "v/vt/vn": f"{a}/{t}/1", "v//vn": f"{a}//1"}[kind])
            sep = draw(st.sampled_from([" ", "\t", "  "]))
            lines.append("f" + sep + sep.join(corners) + draw(st.sampled_from(["", " # comment"])))
    if not any(s.startswith("f") for s in lines):
        lines.append("f 1 2 3")
    return newline.join(lines) + draw(st.sampled_from(["", newline]))


@settings(max_examples=60, deadline=None)
@given(obj_texts())
def test_obj_reader_agrees_with_a_line_by_line_reading(tmp_path_factory, text):
    path = tmp_path_factory.mktemp("obj") / "h.obj"
    path.write_bytes(text.encode())
    mesh = read_mesh(path)
    v, faces, has_uv, material = _reference(text)
    np.testing.assert_array_equal(mesh.vertices, v)
    np.testing.assert_array_equal(mesh.triangles, faces)
    mask = np.ones(len(faces), bool) if mesh.triangle_uv_mask is None else mesh.triangle_uv_mask
    if mesh.triangle_uvs is None:
        assert not has_uv.any()
    else:
        np.testing.assert_array_equal(mask, has_uv)
    write_mesh(path.with_name("w.obj"), mesh.with_vertices(mesh.vertices * 2))
    written = path.with_name("w.obj").read_bytes().decode()
    assert [s for s in written.splitlines() if not s.startswith("v ")] == \
        [s for s in text.splitlines() if not s.startswith("v ")]  # line endings and everything else kept
    np.testing.assert_allclose(read_mesh(path.with_name("w.obj")).vertices, v * 2, rtol=1e-8)
