"""Blender (bpy 4.2, in .venv-blender made by ``make blender``) imports kpd's glTF rig with its own importer: the
shape keys carry kpd's target names and setting their values reproduces the rig's edits."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np

from kpd.io import read_mesh
from kpd.runtime import Model

from helpers import REPO, TOLERANCE, corresponding, kpd, needs

BLENDER_PYTHON = REPO / ".venv-blender" / "bin" / "python"

# Runs inside Blender's Python: import the file, set shape key values, write the evaluated mesh in world space.
IMPORT = """
import json, sys
import bpy
import numpy as np

glb, weights_file, out = sys.argv[1:4]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=glb)
meshes = [o for o in bpy.context.scene.objects if o.type == "MESH"]
obj = meshes[0]
keys = obj.data.shape_keys.key_blocks


def world():
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    mesh = evaluated.to_mesh()
    co = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", co)
    matrix = np.array(evaluated.matrix_world)
    evaluated.to_mesh_clear()
    return co.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]


rest = world()
for name, value in json.load(open(weights_file)).items():
    key = keys[name]
    key.slider_min, key.slider_max = -10.0, 10.0  # Blender's limits for a shape key's value
    key.value = value
bpy.context.view_layer.update()
moved = world()
np.savez(out, rest=rest, moved=moved)
empties = {o.name: list(o.matrix_world.translation) for o in bpy.context.scene.objects if o.type == "EMPTY"}
json.dump({"shape_keys": [k.name for k in keys], "meshes": len(meshes), "empties": empties,
           "uv_layers": len(obj.data.uv_layers), "images": [list(image.size) for image in bpy.data.images],
           "color_attributes": len(obj.data.color_attributes)}, open(out + ".json", "w"))
"""


def run_blender(path: Path, weights: dict, tmp_path: Path) -> tuple[dict, dict]:
    """Import ``path`` in Blender, set ``weights`` on its shape keys; the evaluated mesh and what Blender saw."""
    (tmp_path / "weights.json").write_text(json.dumps(weights))
    (tmp_path / "import.py").write_text(IMPORT)
    out = tmp_path / "blender.npz"
    subprocess.run([str(BLENDER_PYTHON), str(tmp_path / "import.py"), str(path), str(tmp_path / "weights.json"),
                    str(out)], check=True, capture_output=True, timeout=300)
    return dict(np.load(out)), json.loads(Path(str(out) + ".json").read_text())


def test_blender_reads_the_gltf_with_its_bin_texture_and_colours(tmp_path):
    """A textured, coloured mesh far from the origin as .gltf + .bin: Blender's import has its UVs, image, colours and
    shape keys, and the keys edit it as kpd does."""
    needs(BLENDER_PYTHON, "Blender as a Python module (bpy)")
    from kpd.io import Mesh
    from kpd.morph import MorphRig, write_gltf
    from kpd.procedural import procedural_chair

    chair = procedural_chair(edge=2.0)
    t = len(chair.triangles)
    texture = np.random.default_rng(1).integers(0, 255, (8, 8, 3), dtype=np.uint8)
    mesh = Mesh(vertices=chair.vertices + [1000.0, -500.0, 20.0], triangles=chair.triangles,
                vertex_colors=chair.vertex_colors, triangle_uvs=np.random.default_rng(0).uniform(0, 1, (3 * t, 2)),
                textures=[texture], triangle_material_ids=np.zeros(t, np.int64))
    model = Model.load("chair")
    rig = model.rig(mesh)
    path = tmp_path / "chair.gltf"
    write_gltf(path, MorphRig.from_rig(rig, None))
    weights = {"keypoint_3_z": 2.5, "keypoint_0_x": -1.0}
    result, info = run_blender(path, weights, tmp_path)
    assert info["uv_layers"] == 1 and info["images"] == [[8, 8]] and info["color_attributes"] == 1
    assert info["shape_keys"] == ["Basis", *[f"keypoint_{i}_{a}" for i in range(rig.num_keypoints) for a in "xyz"]]
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    # Blender's world coordinates are float32 (its object matrix): about 1e-7 of 1000, a few 1e-6 of this chair
    index = corresponding(result["rest"], mesh, TOLERANCE)
    expected = rig.deform(rig.moved({3: [0.0, 0.0, 2.5], 0: [-1.0, 0.0, 0.0]}))[index]
    assert np.abs(result["moved"] - expected).max() < TOLERANCE * diagonal


def test_blender_imports_the_rig_and_its_shape_keys_edit_like_kpd(data_dir, tmp_path):
    needs(BLENDER_PYTHON, "Blender as a Python module (bpy)")
    chair = data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply"
    glb = tmp_path / "chair.glb"
    assert kpd("rig", "chair", chair, "--out", glb) == 0  # --view-up +z: Blender's world frame is the chair's own
    model = Model.load("chair")
    mesh = read_mesh(chair)
    rig = model.rig(mesh)
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    rng = np.random.default_rng(0)
    offsets = rng.uniform(-3.0, 3.0, size=(rig.num_keypoints, 3))  # in the chair's units (its diagonal: ~70)
    weights = {f"keypoint_{i}_{a}": float(offsets[i, j]) for i in range(rig.num_keypoints) for j, a in enumerate("xyz")}
    weights.update({"prior_9_z": 4.0, "pca_0": 1.5, "pca_3": -2.0})
    prior = model.prior
    keypoints = rig.keypoints + offsets
    keypoints += model.sync(rig, {9: rig.keypoints[9] + [0.0, 0.0, 4.0]}) - rig.keypoints
    for c, weight in ((0, 1.5), (3, -2.0)):
        keypoints += weight * rig.normalizer.invert_vectors(np.sqrt(prior.explained_variance_[c])
                                                            * prior.components_[c])
    expected = rig.deform(keypoints)
    result, info = run_blender(glb, weights, tmp_path)
    names = read_gltf_names(glb)
    assert info["meshes"] == 1 and info["shape_keys"] == ["Basis", *names]
    assert len(names) == 6 * rig.num_keypoints + len(prior.components_)
    index = corresponding(result["rest"], mesh)  # Blender's world = the chair's own frame (+z up)
    assert np.abs(result["moved"] - expected[index]).max() < TOLERANCE * diagonal
    assert np.abs(result["moved"] - result["rest"]).max() > 0.05 * diagonal  # the shape keys did move it
    empties = info["empties"]
    blender_keypoints = np.array([empties[f"keypoint_{i}"] for i in range(rig.num_keypoints)])
    assert np.abs(blender_keypoints - rig.keypoints).max() < TOLERANCE * diagonal


def read_gltf_names(path: Path) -> list[str]:
    from kpd.morph import read_gltf

    return read_gltf(path).names
