"""Blender (bpy 4.2, in .venv-blender made by ``make blender``) imports kpd's glTF rig with its own importer: the
shape keys carry kpd's target names and setting their values reproduces the rig's edits."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np

from kpd.io import read_mesh
from kpd.runtime import Model

from test_morph import REPO, TOLERANCE, corresponding, kpd, needs

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
json.dump({"shape_keys": [k.name for k in keys], "meshes": len(meshes), "empties": empties}, open(out + ".json", "w"))
"""


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
    (tmp_path / "weights.json").write_text(json.dumps(weights))
    (tmp_path / "import.py").write_text(IMPORT)
    out = tmp_path / "blender.npz"
    subprocess.run([str(BLENDER_PYTHON), str(tmp_path / "import.py"), str(glb), str(tmp_path / "weights.json"),
                    str(out)], check=True, capture_output=True, timeout=300)
    info = json.loads(Path(str(out) + ".json").read_text())
    names = read_gltf_names(glb)
    assert info["meshes"] == 1 and info["shape_keys"] == ["Basis", *names]
    assert len(names) == 6 * rig.num_keypoints + len(prior.components_)
    result = np.load(out)
    index = corresponding(result["rest"], mesh)  # Blender's world = the chair's own frame (+z up)
    assert np.abs(result["moved"] - expected[index]).max() < TOLERANCE * diagonal
    assert np.abs(result["moved"] - result["rest"]).max() > 0.05 * diagonal  # the shape keys did move it
    empties = info["empties"]
    blender_keypoints = np.array([empties[f"keypoint_{i}"] for i in range(rig.num_keypoints)])
    assert np.abs(blender_keypoints - rig.keypoints).max() < TOLERANCE * diagonal


def read_gltf_names(path: Path) -> list[str]:
    from kpd.morph import read_gltf

    return read_gltf(path).names
