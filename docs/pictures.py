"""Make the pictures of the README and the docs pages (``docs/*.png``) again, from the shipped models and the data
in ``../shared/data``.

Every picture comes from a kpd command, as a user would run it (the editor in a real window on a private Xvfb,
driven with xdotool and read off the X server's screen):

    .venv/bin/python docs/pictures.py                   # all of them
    .venv/bin/python docs/pictures.py editor_chair demo  # some
    .venv/bin/python docs/pictures.py --runs runs        # also the alignment galleries from trained runs/chair...
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DOCS = Path(__file__).resolve().parent
REPO = DOCS.parent
DATA = Path(os.environ.get("KPD_DATA", REPO.parent / "shared" / "data"))
CHAIR = DATA / "modelnet10" / "chair" / "test" / "chair_0890.ply"
STOOL = DATA / "modelnet10" / "chair" / "test" / "chair_0891.ply"
SNEAKER = DATA / "scans" / "sneaker.ply"


def kpd(*args: object, cwd: Path | None = None, env: dict | None = None) -> str:
    done = subprocess.run([sys.executable, "-m", "kpd.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env)
    if done.returncode:
        raise SystemExit(f"kpd {' '.join(map(str, args))} failed: {done.stderr.strip()}")
    return done.stdout


def demo(tmp: Path) -> None:
    kpd("demo", "--out", tmp / "demo")
    shutil.copy(tmp / "demo" / "demo.png", DOCS / "demo.png")


def render_chair(tmp: Path) -> None:
    """The taller-back edit of a ModelNet10 chair, over its original shape (the ghost)."""
    from kpd.io import read_mesh
    from kpd.runtime import Model

    rig = Model.load("chair").rig(read_mesh(CHAIR))
    height = float(np.ptp(rig.mesh.vertices[:, 2]))
    tops = np.argsort(rig.keypoints[:, 2])[-2:]
    moves = [a for i in sorted(tops) for a in ("--move", f"{i}:0,0,{0.4 * height:.2f}")]
    kpd("render", "chair", CHAIR, *moves, "--ghost", "--out", DOCS / "render_chair.png", "--force")


def sample_chair(tmp: Path) -> None:
    kpd("sample", "chair", STOOL, "--n", "8", "--out", tmp / "sample")
    shutil.copy(tmp / "sample" / "contact_sheet.png", DOCS / "sample_chair.png")


def scan_chair_ambiguous(tmp: Path) -> None:
    kpd("scan", STOOL, "--model", "chair", "--out", tmp / "stool.ply", "--report", tmp / "stool.json", "--picture",
        DOCS / "scan_chair_ambiguous.png", "--force")


def scan_sneaker(tmp: Path) -> None:
    """The sneaker scan turned at random, with noise, 10% outliers and a cap cut away, against the sneaker itself
    (sampled independently), as benchmarks/bench_scan.py does."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bench_scan import corrupt
    from scipy.spatial.transform import Rotation

    from kpd.geometry import sample_surface
    from kpd.io import read_mesh, write_points

    mesh = read_mesh(SNEAKER)
    rng = np.random.default_rng(7)
    scan = corrupt(sample_surface(mesh.vertices, mesh.triangles, 20000, rng).points, rng)
    turned = scan @ Rotation.random(random_state=3).as_matrix().T * 40.0 + [100.0, -20.0, 5.0]  # another pose, in mm
    write_points(tmp / "sneaker_scan.ply", turned)
    write_points(tmp / "sneaker_reference.ply", sample_surface(mesh.vertices, mesh.triangles, 8000, 11).points)
    kpd("scan", tmp / "sneaker_scan.ply", "--reference", tmp / "sneaker_reference.ply", "--out", tmp / "aligned.ply",
        "--report", tmp / "sneaker.json", "--picture", DOCS / "scan_sneaker.png", "--force")


def _editor_shot(tmp: Path, out: Path, args: list, *, drag: bool = True, keys: tuple = ()) -> None:
    """Open ``kpd view ARGS`` on a private Xvfb, drag its clearest keypoint up, press ``keys``, and save the screen
    (both windows) cropped to them."""
    from kpd.viewer.render import grab_screen, private_display, project, write_png

    events = tmp / f"{out.stem}.jsonl"
    fb = tmp / f"{out.stem}_fb"
    fb.mkdir()
    with private_display(1300, 760, fbdir=fb) as display:
        env = dict(os.environ, DISPLAY=display)
        window = subprocess.Popen([sys.executable, "-m", "kpd.cli", "view", *map(str, args), "--events", str(events)],
                                  env=env, cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            ready = None
            deadline = time.monotonic() + 120
            while ready is None and time.monotonic() < deadline:
                time.sleep(0.2)
                if events.exists():
                    found = [json.loads(x) for x in events.read_text().splitlines() if '"ready"' in x]
                    ready = found[0] if found else None
            if ready is None:
                raise SystemExit("the editor did not open")

            def xdo(*xargs: object) -> None:
                subprocess.run(["xdotool", *map(str, xargs)], env=env, check=True)

            if drag:
                _, _, w, h = ready["viewport"]
                pixels, _ = project(np.array(ready["keypoints"]), np.array(ready["view"]),
                                    np.array(ready["projection"]), w, h)
                top = int(np.argmin(np.where((pixels[:, 0] > 40) & (pixels[:, 0] < w - 40), pixels[:, 1], np.inf)))
                x, y = np.rint(pixels[top]).astype(int)
                xdo("mousemove", x, y)
                xdo("mousedown", 1)
                for step in range(1, 9):
                    xdo("mousemove", x, y - 6 * step)
                    time.sleep(0.05)
                xdo("mouseup", 1)
            for key in keys:
                xdo("key", key)
            time.sleep(2.0)
            screen = grab_screen(fb)
        finally:
            window.terminate()
            window.wait(10)
    used = np.flatnonzero((screen != 0).any(axis=2).any(axis=0))
    rows = np.flatnonzero((screen != 0).any(axis=2).any(axis=1))
    write_png(out, np.ascontiguousarray(screen[: rows.max() + 1, : used.max() + 1]))


def editor_chair(tmp: Path) -> None:
    from kpd.io import read_mesh
    from kpd.runtime import Model

    Model.load("chair").rig(read_mesh(CHAIR)).save(tmp / "chair_rig.npz")
    _editor_shot(tmp, DOCS / "editor_chair.png", ["--rig", tmp / "chair_rig.npz", "--model", "chair", "--prior",
                                                  "--cage"])


def editor_sneaker(tmp: Path) -> None:
    from kpd.bundle import shipped_bundles

    if "shoe" in shipped_bundles():
        _editor_shot(tmp, DOCS / "editor_sneaker.png",
                     ["shoe", SNEAKER, "--scan", "--view-up", "+y", "--azimuth", "60"])
        return
    from kpd.geometry import farthest_point_sampling, sample_surface
    from kpd.io import read_mesh
    from kpd.rig import Rig

    mesh = read_mesh(SNEAKER)
    points = sample_surface(mesh.vertices, mesh.triangles, 4000, 0).points
    Rig.bind(mesh, points[farthest_point_sampling(points, 8, seed=0)]).save(tmp / "sneaker_rig.npz")
    _editor_shot(tmp, DOCS / "editor_sneaker.png", ["--rig", tmp / "sneaker_rig.npz", "--view-up", "+y"])


def _samples(tmp: Path, category: str, name: str, out: str, scale: str = "0.5") -> None:
    mesh = DATA / "modelnet10" / category / "test" / f"{name}.ply"
    kpd("sample", category, mesh, "--n", "8", "--scale", scale, "--out", tmp / out)
    shutil.copy(tmp / out / "contact_sheet.png", DOCS / f"{out}.png")


def samples_chair(tmp: Path) -> None:
    _samples(tmp, "chair", "chair_0896", "samples_chair")


def samples_chair_scale1(tmp: Path) -> None:
    _samples(tmp, "chair", "chair_0896", "samples_chair_scale1", "1.0")


def samples_table(tmp: Path) -> None:
    _samples(tmp, "table", "table_0396", "samples_table")


def _edits(tmp: Path, category: str, names: list[str]) -> None:
    """The semantic edits of bench_edits on held-out shapes with the shipped rig, bound without and with the
    straightening of slivers (kpd.rig.straighten_basis), each keypoint of the edit moved by 0.2 of the box; the
    triangles an edit turned over are drawn red (slivers: thin lines)."""
    from kpd.io import Mesh, read_mesh
    from kpd.metrics import keypoint_roles, semantic_edits
    from kpd.metrics.edits import _turned
    from kpd.triangles import cross as triangle_cross
    from kpd.runtime import Model
    from kpd.viewer.pictures import render_sheet

    model = Model.load(category, threads=1)
    edits = semantic_edits(keypoint_roles(model.prior.mean_), category, 0.2)
    meshes, titles, keypoints = [], [], []
    for name in names:
        mesh = read_mesh(DATA / "modelnet10" / category / "test" / f"{name}.ply")
        prediction = model.predict(mesh)
        for straighten in (False, True):
            rig = model.rig(mesh, prediction=prediction, straighten=straighten)
            rest = rig.normalizer.apply(mesh.vertices)
            for edit, moves in edits.items():
                moved = rig.moved({i: np.asarray(o) * rig.normalizer.scale_ for i, o in moves.items()})
                deformed = rig.normalizer.apply(rig.deform(moved))
                turned = _turned(triangle_cross(rest, mesh.triangles), triangle_cross(deformed, mesh.triangles))
                corners = mesh.triangles.ravel()  # one vertex per corner, so that a triangle has its own colour
                colors = np.where(np.repeat(turned, 3)[:, None], [0.85, 0.1, 0.1], [0.78, 0.78, 0.8])
                meshes.append(Mesh(deformed[corners], np.arange(len(corners)).reshape(-1, 3), vertex_colors=colors))
                keypoints.append(rig.normalizer.apply(moved))
                titles.append(f"{name} {edit.replace('_', ' ')}: {turned.mean():.2%} folded")
    render_sheet(meshes, DOCS / f"edits_{category}.png", titles=titles, keypoints=keypoints,
                 columns=len(meshes) // len(names), cell=2.6,
                 title=f"{len(edits)} left: bound without straightening; {len(edits)} right: shipped (straightened);"
                       " red: triangles turned over")


def edits_chair(tmp: Path) -> None:
    _edits(tmp, "chair", ["chair_0892", "chair_0891"])


def edits_table(tmp: Path) -> None:
    _edits(tmp, "table", ["table_0411", "table_0396"])


def chair_alignment(tmp: Path) -> None:
    _alignment(tmp, "chair")


def table_alignment(tmp: Path) -> None:
    _alignment(tmp, "table")


def _alignment(tmp: Path, category: str) -> None:
    """The shipped bundle's alignment of ModelNet10 test pairs (kpd eval chamfer --gallery)."""
    kpd("eval", "chamfer", DATA / "modelnet10", "--category", category, "--model", category, "--pairs", "200",
        "--out", tmp / f"{category}.json", "--gallery", DOCS / f"{category}_alignment.png", "--gallery-pairs", "3",
        "--quiet", "--force")


def galleries(tmp: Path, runs: Path) -> None:
    """Galleries of trained runs against their farthest-point baselines (kpd eval alignment --gallery)."""
    for category in ("chair", "table"):
        run, baseline = runs / category, runs / f"{category}-fps"
        if run.is_dir() and baseline.is_dir():
            kpd("eval", "alignment", run, "--baseline", baseline, "--out", tmp / f"{category}.json", "--gallery",
                DOCS / f"{category}_runs_alignment.png", "--gallery-pairs", "3", "--quiet")


# The same edit of the same chair in Blender and in the browser editor: its backrest raised by 8 units (its two top
# keypoints, 8 and 9) through the shape keys / morph targets that `kpd rig` writes (docs/rigs.md).
RIG_EDIT = {"keypoint_8_z": 8.0, "keypoint_9_z": 8.0}
RIG_VIEW = {"azimuth": 30.0, "elevation": 20.0}  # the browser page's default camera (degrees)

BLENDER_RENDER = """
import json, math, sys
import bpy
from mathutils import Vector

glb, weights, out, azimuth, elevation = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]), float(sys.argv[5])
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=glb)
chair = next(o for o in bpy.context.scene.objects if o.type == "MESH")
for name, value in json.loads(weights).items():  # the shape keys kpd rig wrote
    key = chair.data.shape_keys.key_blocks[name]
    key.slider_min, key.slider_max = -10.0, 10.0
    key.value = value
scene = bpy.context.scene
bpy.context.view_layer.update()
evaluated = chair.evaluated_get(bpy.context.evaluated_depsgraph_get())
points = [evaluated.matrix_world @ v.co for v in evaluated.to_mesh().vertices]
lo = Vector([min(p[i] for p in points) for i in range(3)])
hi = Vector([max(p[i] for p in points) for i in range(3)])
center, radius = (lo + hi) / 2, (hi - lo).length / 2
camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
scene.collection.objects.link(camera)
camera.data.sensor_fit = "VERTICAL"
camera.data.angle_y = math.radians(35.0)  # as the browser page's camera
# the page's camera (azimuth from the front, +z up) in the chair's own frame, which Blender's world is
a, e = math.radians(azimuth), math.radians(elevation)
direction = Vector((math.sin(a) * math.cos(e), -math.cos(a) * math.cos(e), math.sin(e)))
camera.location = center + direction * radius / math.sin(camera.data.angle_y / 2) * 1.05
camera.rotation_euler = (center - camera.location).to_track_quat("-Z", "Y").to_euler()
scene.camera = camera
scene.render.engine = "BLENDER_WORKBENCH"
scene.render.resolution_x, scene.render.resolution_y = 900, 800
scene.display.shading.light = "STUDIO"
scene.display.shading.color_type = "OBJECT"
scene.display.shading.show_cavity = True
chair.color = (0.8, 0.8, 0.8, 1.0)
scene.render.filepath = out
bpy.ops.render.render(write_still=True)
"""


def rig_blender(tmp: Path) -> None:
    """The chair's rig written by kpd rig, imported by Blender's own glTF importer, edited with its shape keys and
    rendered by Blender's Workbench (bpy 4.2 in .venv-blender, made by make blender)."""
    glb = tmp / "chair.glb"
    kpd("rig", "chair", CHAIR, "--out", glb, "--force")
    (tmp / "render.py").write_text(BLENDER_RENDER)
    done = subprocess.run([str(REPO / ".venv-blender" / "bin" / "python"), str(tmp / "render.py"), str(glb),
                           json.dumps(RIG_EDIT), str(DOCS / "rig_blender.png"), str(RIG_VIEW["azimuth"]),
                           str(RIG_VIEW["elevation"])], capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"Blender's render failed: {done.stderr.strip()[-2000:]}")


def rig_browser(tmp: Path) -> None:
    """The same edit in kpd view --browser, in headless Chromium (the page as a user sees it)."""
    sys.path.insert(0, str(REPO / "tests"))
    from test_browser import open_page, start_chromium, start_editor

    process, url = start_editor("chair", str(CHAIR), "--port", "0", "--out", str(tmp / "edited.obj"))
    driver = start_chromium(str(tmp / "chromium"))
    try:
        open_page(driver, url)
        driver.execute_script("window.kpd.setWeights(arguments[0])", RIG_EDIT)
        time.sleep(0.5)
        driver.save_screenshot(str(DOCS / "rig_browser.png"))
    finally:
        driver.quit()
        process.terminate()
        process.wait(timeout=10)


def _amplify(tmp: Path, names: list[str], out: str) -> None:
    """kpd amplify's own contact sheet of ModelNet10 training chairs, four variants each."""
    folder = tmp / out
    folder.mkdir()
    for name in names:
        (folder / name).symlink_to(DATA / "modelnet10" / "chair" / "train" / name)
    kpd("amplify", "chair", folder, "--variants", "4", "--out", tmp / f"{out}_x4")
    shutil.copyfile(tmp / f"{out}_x4" / "contact_sheet.png", DOCS / f"{out}.png")


def amplify_chairs(tmp: Path) -> None:
    _amplify(tmp, [f"chair_{i:04d}.ply" for i in range(1, 5)], "amplify_chairs")


def amplify_unusual(tmp: Path) -> None:
    """Chairs whose own keypoints lie beyond the prior's typical range (0018, 0030, 0061) and one whose first draw of
    a variant folds (0062): their variants, brought into the range."""
    _amplify(tmp, ["chair_0018.ply", "chair_0030.ply", "chair_0061.ply", "chair_0062.ply"], "amplify_unusual")


PICTURES = {"demo": demo, "render_chair": render_chair, "sample_chair": sample_chair,
            "scan_chair_ambiguous": scan_chair_ambiguous, "scan_sneaker": scan_sneaker, "editor_chair": editor_chair,
            "editor_sneaker": editor_sneaker, "chair_alignment": chair_alignment, "table_alignment": table_alignment,
            "samples_chair": samples_chair, "samples_chair_scale1": samples_chair_scale1,
            "samples_table": samples_table, "edits_chair": edits_chair, "edits_table": edits_table,
            "rig_blender": rig_blender, "rig_browser": rig_browser, "amplify_chairs": amplify_chairs,
            "amplify_unusual": amplify_unusual}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", metavar="NAME", help=f"pictures to make: {', '.join(PICTURES)}")
    parser.add_argument("--runs", type=Path, default=None, help="a folder with chair, chair-fps, table, table-fps runs")
    args = parser.parse_args()
    unknown = sorted(set(args.names) - set(PICTURES))
    if unknown:
        parser.error(f"no picture called {', '.join(unknown)}")
    with tempfile.TemporaryDirectory(prefix="kpd-docs-") as tmp:
        for name in args.names or PICTURES:
            print(f"docs/{name}.png")
            PICTURES[name](Path(tmp))
        if args.runs is not None:
            galleries(Path(tmp), args.runs)


if __name__ == "__main__":
    main()
