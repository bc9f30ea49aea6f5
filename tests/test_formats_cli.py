"""What the user sees of their files: pictures in the materials' colours and the file's own up axis, and one clear
line with exit status 2 for each refusal (checkpoints, folders, huge coordinates), leaving nothing behind."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import pytest
from helpers import kpd, make_obj, tall_box, two_sided_box

from kpd.io import read_mesh, write_mesh


def one_error_line(capsys, command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"kpd {command}: error: "), err
    return err[0]


# --- pictures ------------------------------------------------------------------------------------------------------


def _silhouette(image: np.ndarray) -> tuple[int, int]:
    """(height, width) of what is not background in a picture."""
    drawn = (np.abs(image.astype(int) - image[0, 0].astype(int)).sum(axis=2) > 30)
    rows, cols = np.flatnonzero(drawn.any(axis=1)), np.flatnonzero(drawn.any(axis=0))
    return int(rows[-1] - rows[0]), int(cols[-1] - cols[0])


def test_pictures_show_the_materials_colours_and_maps(tmp_path):
    """A contact sheet of a file with a wood map, a red Kd material and a blue map draws all three."""
    from kpd.io.images import read_png
    from kpd.viewer.pictures import render_sheet

    mesh = read_mesh(make_obj(tmp_path / "in"))
    render_sheet([mesh], tmp_path / "sheet.png", up="z", cell=3.0)
    image = read_png(tmp_path / "sheet.png").astype(int)
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    red = (r > 120) & (r > 2 * g) & (r > 2 * b)  # the shaded red material
    blue = (b > r + 60) & (b > g + 40)  # the label map's blue
    brown = (r > b + 40) & (g > b + 15) & (r < 220) & (np.abs(r - 2 * g) > 0)  # the wood map
    assert red.sum() > 200 and blue.sum() > 100 and brown.sum() > 100, (red.sum(), blue.sum(), brown.sum())


def test_shapenet_pictures_show_their_materials(data_dir, tmp_path):
    """Two real models drawn as kpd sample's sheet draws them: the cup's green Kd material and the bench's wood map."""
    from kpd.io.images import read_png
    from kpd.viewer.pictures import render_sheet

    root = data_dir / "shapenetcore_obj"
    cup = read_mesh(root / "cup/1f035aa5fc6da0983ecac81e09b15ea9/models/model_normalized.obj")
    bench = root / "bench/a047cb14c22517e6f33e284fed03c3fc"
    bench = read_mesh(bench / "models/model_normalized.obj")  # its maps are in ../images, ShapeNet's layout
    for mesh, name in ((cup, "cup"), (bench, "bench")):
        render_sheet([mesh], tmp_path / f"{name}.png", up="y", cell=2.4)
    r, g, b = np.moveaxis(read_png(tmp_path / "cup.png").astype(int), 2, 0)
    assert ((g > 120) & (g > r + 50) & (g > b + 80)).sum() > 2000  # Kd 0.498 1 0, shaded
    r, g, b = np.moveaxis(read_png(tmp_path / "bench.png").astype(int), 2, 0)
    assert ((r > b + 50) & (g > b + 20) & (r > 120)).sum() > 1500  # the light wood map (a flat bench)


def test_a_face_with_two_materials_shows_the_side_that_faces_the_camera(tmp_path):
    """A box stored twice, green facing out and white facing in: the outside is green, whichever material is listed
    first; an inside-out copy shows white. Never the renderer's order of geometries, which changes from run to run."""
    from kpd.io.images import read_png
    from kpd.viewer.pictures import render_sheet

    for green_first, green_out in ((False, True), (True, True), (False, False)):
        render_sheet([two_sided_box(green_out, green_first)], tmp_path / "box.png", cell=2.0)
        r, g, b = np.moveaxis(read_png(tmp_path / "box.png").astype(int), 2, 0)
        green = ((g > r + 60) & (g > b + 60)).sum()
        drawn = (np.abs(g - 255) + np.abs(r - 255) > 30).sum()
        assert drawn > 2000 and (green > 0.9 * drawn if green_out else green < 0.01 * drawn), \
            (green_first, green, drawn)


def test_gltf_draws_y_up_unless_view_up_says_otherwise(tmp_path, capsys):
    from kpd.io.images import read_png

    write_mesh(tmp_path / "tall.glb", tall_box(1))  # tall along y, as a glTF file is
    assert kpd("render", "chair", tmp_path / "tall.glb", "--size", "240x240", "--no-labels", "--out",
               tmp_path / "a.png") == 0
    height, width = _silhouette(read_png(tmp_path / "a.png"))
    assert height > 1.5 * width, (height, width)
    # seen from the side (azimuth 90: from +x for z up), so that the box's length along y lies across the picture
    assert kpd("render", "chair", tmp_path / "tall.glb", "--size", "240x240", "--no-labels", "--view-up", "+z",
               "--azimuth", "90", "--out", tmp_path / "b.png") == 0
    height, width = _silhouette(read_png(tmp_path / "b.png"))
    assert width > 1.5 * height, (height, width)  # an explicit --view-up wins: the box lies on its side


def test_scan_up_axis_draws_upright(tmp_path):
    """An OBJ that is y up (as ShapeNet's): with --scan --up +y the picture is upright without --view-up."""
    from kpd.io.images import read_png

    write_mesh(tmp_path / "tall.obj", tall_box(1))
    assert kpd("render", "chair", tmp_path / "tall.obj", "--scan", "--up", "+y", "--size", "240x240",
               "--no-labels", "--out", tmp_path / "a.png") == 0
    height, width = _silhouette(read_png(tmp_path / "a.png"))
    assert height > 1.5 * width, (height, width)


# --- refusals ------------------------------------------------------------------------------------------------------


def test_a_folder_given_as_a_mesh_says_so(tmp_path, capsys):
    (tmp_path / "chairs").mkdir()
    for command, extra in (("render", ["--out", tmp_path / "r.png"]), ("deform", ["--out", tmp_path / "o.obj"]),
                           ("keypoints", [])):
        assert kpd(command, "chair", tmp_path / "chairs", *extra) == 2
        line = one_error_line(capsys, command)
        assert "chairs: is a folder, not a" in line and "no such file" not in line
    assert sorted(os.listdir(tmp_path)) == ["chairs"]


def test_coordinates_near_the_float_range_are_one_line(tmp_path, capsys):
    vertices = np.array([[1e300, 0, 0], [-1e300, 1, 0], [0, 1e300, 1], [0, 0, 1e300]])
    text = "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in vertices.tolist()) + "f 1 2 3\nf 1 3 4\nf 1 2 4\nf 2 3 4\n"
    (tmp_path / "huge.obj").write_text(text)
    for command, extra in (("keypoints", []), ("deform", ["--move", "0:0,0,1", "--out", tmp_path / "o.obj"]),
                           ("render", ["--out", tmp_path / "o.png"])):
        assert kpd(command, "chair", tmp_path / "huge.obj", *extra) == 2
        line = one_error_line(capsys, command)
        assert "4 vertices have coordinates beyond 1e+18" in line and "huge.obj" in line
    assert sorted(os.listdir(tmp_path)) == ["huge.obj"]


def test_warnings_name_the_users_file_in_kpds_form(tmp_path):
    """Writing a textured mesh to STL warns once, naming --out (not kpd's staging folder), as 'warning: ...' (the
    command's own process: its log lines as the user sees them)."""
    import subprocess
    import sys

    obj = make_obj(tmp_path / "in")
    run = subprocess.run([sys.executable, "-m", "kpd.cli", "deform", "chair", str(obj), "--move", "0:0,0,0", "--out",
                          str(tmp_path / "o.stl")], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    err = [s for s in run.stderr.splitlines() if "cannot store" in s]
    assert err == [f"warning: {tmp_path / 'o.stl'}: .stl cannot store UVs and textures and vertex normals; written "
                   "without them"]
    assert ".kpd-tmp" not in "".join(err)


def test_a_progress_bar_is_erased_before_an_error():
    from tqdm import tqdm

    from kpd.cli import _close_progress_bars

    screen = io.StringIO()
    bar = tqdm(total=10, file=screen, desc="meshes")
    bar.update(3)
    _close_progress_bars()
    assert bar.disable or getattr(bar, "_instances", None) is None or bar not in tqdm._instances
    assert screen.getvalue().endswith("\r")  # the line erased: the error starts at its beginning


@pytest.mark.parametrize("command", ["alignment", "keypoints"])
def test_eval_help_has_an_example(command, capsys):
    assert kpd("eval", command, "--help") == 0
    out = capsys.readouterr().out
    assert f"example:\n  kpd eval {command} runs/chair" in out


def test_help_lists_every_shipped_model(capsys):
    from kpd.bundle import shipped_bundles

    assert "shoe" in shipped_bundles()
    for command in ("deform", "view", "render", "keypoints", "align", "sample"):
        assert kpd(command, "--help") == 0
        out = " ".join(capsys.readouterr().out.split())
        assert ", ".join(shipped_bundles()) in out, command


def test_train_makes_the_run_folders_parents(tmp_path, monkeypatch):
    import argparse

    from kpd.commands.train import check_run_folder
    from kpd.errors import InputError

    monkeypatch.chdir(tmp_path)
    data = tmp_path / "data"
    data.mkdir()
    args = argparse.Namespace(resume=False, force=False, data=str(data), split_file=None, cache=None)
    check_run_folder(args, Path("runs/2026/chair"))
    assert (tmp_path / "runs" / "2026").is_dir() and not (tmp_path / "runs" / "2026" / "chair").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="file is a file, not a folder"):
        check_run_folder(args, Path("file/run"))


class Thing:
    """A Python object in a checkpoint (pickled; kpd never loads it)."""


@pytest.mark.parametrize("kind", ["text", "empty", "truncated", "pickled"])
def test_a_bad_checkpoint_is_one_line(kind, tmp_path, capsys):
    torch = pytest.importorskip("torch")
    path = tmp_path / "checkpoint.pt"
    if kind == "text":
        path.write_text("epoch 10 loss 0.1\n")
    elif kind == "empty":
        path.write_bytes(b"")
    else:
        torch.save({"weights": torch.zeros(200), **({"thing": Thing()} if kind == "pickled" else {})}, path)
        if kind == "truncated":
            path.write_bytes(path.read_bytes()[:-300])
    assert kpd("export", path, "--out", tmp_path / "m.kpd") == 2
    line = one_error_line(capsys, "export")
    expected = {"text": "a text file, not a PyTorch checkpoint", "empty": "the file is empty (0 bytes)",
                "truncated": "the file is truncated or damaged", "pickled": "it holds pickled Python objects"}[kind]
    assert f"cannot load checkpoint {path}: {expected}" in line and "weights_only" not in line
    assert sorted(os.listdir(tmp_path)) == ["checkpoint.pt"]


def test_editor_checks_the_companions_of_its_output_before_opening(tmp_path, capsys, monkeypatch):
    """kpd view --out x.obj on a file with maps: a companion already there (x_wood.jpg) is refused at start, as the
    other commands refuse it, not overwritten by the first 'save mesh'."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    obj = make_obj(tmp_path / "in")
    (tmp_path / "x_wood.jpg").write_bytes(b"mine")
    assert kpd("view", "chair", obj, "--out", tmp_path / "x.obj") == 2
    errors = [s for s in capsys.readouterr().err.splitlines() if s.startswith("kpd view: error")]
    line = errors[-1]  # after the frame check's warning (a flat test shape is no chair)
    assert len(errors) == 1 and "its companion file" in line and "x_wood.jpg exists; pass --force" in line
    assert (tmp_path / "x_wood.jpg").read_bytes() == b"mine"
