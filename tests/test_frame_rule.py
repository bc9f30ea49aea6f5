"""One frame rule for every command that reads a shape for a model: --scan/--up everywhere, warnings that suggest
only the command's own flags, the view and the written rigs' up axis from the shape's recovered frame, the same
camera convention in the pictures, the window and the browser page, the category check kept with --scan."""

from __future__ import annotations

import argparse
import json
import re
import struct
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from helpers import kpd

from kpd.cli import build_parser
from kpd.commands._shared import category_azimuth, warn_moves
from kpd.commands.view import page_azimuth
from kpd.frame import FrameCheck, ambiguity_advice
from kpd.runtime import Model
from kpd.viewer.camera import camera_pose
from kpd.viewer.settings import ViewSettings, front_axis, up_axis

# the commands that read a shape for a model and check its frame
FRAME_COMMANDS = ("keypoints", "deform", "align", "sample", "render", "rig", "view", "demo")
MOVE_COMMANDS = ("deform", "render")
AXES = ("+x", "-x", "+y", "-y", "+z", "-z")


def _options() -> dict[str, set[str]]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {name: {o for action in parser._actions for o in action.option_strings}
            for name, parser in sub.choices.items()}


def _rotations(angles: list[tuple[str, float]]) -> list[np.ndarray]:
    from scipy.spatial.transform import Rotation

    return [Rotation.from_euler(axis, angle, degrees=True).as_matrix() for axis, angle in angles]


def _orientation(alternatives: list[tuple[str, float]]) -> SimpleNamespace:
    """An ambiguous orientation (the identity chosen) hesitating with turns about the given axes."""
    rotations = _rotations(alternatives)
    hypotheses = [SimpleNamespace(rotation=r, score=1.01) for r in rotations]
    return SimpleNamespace(ambiguous=True, score=1.0, rotation=np.eye(3), hypotheses=hypotheses)


def _warnings(capsys) -> dict[str, list[str]]:
    """Every warning each kind of command can print, triggered: the frame check's (turned, foreign), the ambiguity
    advice with and without --up and alternatives, and the move check's."""
    check = FrameCheck(0.3, 0.1, np.eye(3), 90.0, True, "y", 0.2, 0.1, 0.1, False)
    frame = [*check.warnings("chair", "a.obj"), *check._replace(up=None).warnings("chair"),
             *check._replace(foreign=True).warnings("chair")]
    ambiguous = []
    for up_given in (False, True):
        ambiguous.append(ambiguity_advice(up_given))
        for alternatives in ([("z", 180)], [("z", 90)], [("x", 90)], [("x", 90), ("z", 180)]):
            ambiguous.append(ambiguity_advice(up_given, _orientation(alternatives), "+z"))
    warn_moves({3: np.array([0.0, 0.0, 5.0])}, np.random.default_rng(0).uniform(0, 0.6, (50, 3)))
    moves = capsys.readouterr().err.splitlines()
    assert moves and all("--move" in line for line in moves)
    return {"frame": frame + ambiguous, "ambiguous": ambiguous, "move": moves}


def test_every_flag_a_warning_suggests_is_an_option_of_its_command(capsys):
    options = _options()
    texts = _warnings(capsys)
    assert any("--scan" in t for t in texts["frame"]) and any("--up" in t for t in texts["frame"])
    # kpd scan prints the ambiguity advice too
    for kind, commands in (("frame", FRAME_COMMANDS), ("ambiguous", ("scan",)), ("move", MOVE_COMMANDS)):
        for text in texts[kind]:
            # "kpd scan --picture": another command named with its own flag
            for other, flags in re.findall(r"kpd (\w+)((?: --[\w-]+)+)", text):
                assert set(flags.split()) <= options[other], (other, text)
            own = re.sub(r"kpd \w+(?: --[\w-]+)+", "", text)
            for command in commands:
                missing = set(re.findall(r"--[a-z][\w-]*", own)) - options[command]
                assert not missing, f"kpd {command} has no {sorted(missing)}, which its warning suggests: {text}"


def test_ambiguity_advice_names_the_alternatives():
    turn = ambiguity_advice(True, _orientation([("z", 180)]), "+z")
    assert "a half turn about the up axis (z)" in turn and "no --up settles" in turn and "toe and heel" in turn
    quarter = ambiguity_advice(True, _orientation([("z", 90)]), "+z")
    assert "a turn of 90 degrees about the up axis (z)" in quarter and "toe" not in quarter
    other = ambiguity_advice(False, _orientation([("x", 90)]), "+z")
    assert "(y instead of z)" in other or "(-y instead of z)" in other
    assert "pass --up" in other and "no --up settles" not in other
    assert "x, y, z" in ambiguity_advice(False)  # without the candidates: what --up takes


@pytest.mark.parametrize("up", AXES)
def test_front_is_the_axis_a_gltf_file_turns_to_its_front(up):
    from scipy.spatial.transform import Rotation

    from kpd.morph import up_rotation

    quaternion = up_rotation(up)
    turn = Rotation.identity() if quaternion is None else Rotation.from_quat(quaternion)
    np.testing.assert_allclose(turn.apply(front_axis(up)), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(turn.apply(up_axis(up)), [0, 1, 0], atol=1e-12)


def _page_direction(settings: ViewSettings) -> np.ndarray:
    """(3,) from the shape towards the browser page's camera, in the shape's frame (viewer/web/app.js frameCamera:
    glTF's +Y up, azimuth 0 from +Z, then the glTF file's up rotation undone)."""
    from scipy.spatial.transform import Rotation

    from kpd.morph import up_rotation

    az, el = np.radians(page_azimuth(settings)), np.radians(settings.elevation)
    page = np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])
    quaternion = up_rotation(settings.up)
    return page if quaternion is None else Rotation.from_quat(quaternion).inv().apply(page)


@pytest.mark.parametrize("up", AXES)
def test_pictures_window_and_page_see_the_same_side(up):
    points = np.random.default_rng(1).normal(size=(200, 3))
    u = up_axis(up)
    fronts = [None] + [a for a in AXES if abs(up_axis(a) @ u) < 0.5]
    for front in fronts:
        for azimuth, elevation in [(0, 0), (30, 20), (-75, 10), (200, 45)]:
            settings = ViewSettings(up=up, front=front, azimuth=azimuth, elevation=elevation)
            camera = camera_pose(points, settings)
            seen = (camera.eye - camera.center) / np.linalg.norm(camera.eye - camera.center)
            np.testing.assert_allclose(seen, _page_direction(settings), atol=1e-9, err_msg=f"{up} {front} {azimuth}")
            if azimuth == elevation == 0:
                np.testing.assert_allclose(seen, front_axis(up) if front is None else up_axis(front), atol=1e-9)


def test_front_across_up_is_checked():
    from kpd.errors import InputError

    with pytest.raises(InputError, match="front must be an axis across up"):
        ViewSettings(up="+z", front="-z")


def test_the_default_camera_shows_a_shoe_from_its_side():
    assert category_azimuth(Model.load("chair")) == 30.0
    assert category_azimuth(Model.load("shoe")) == 60.0  # long front to back: its heel would face the camera


def test_bench_runs_the_shipped_chair_without_a_model():
    assert build_parser().parse_args(["bench"]).model == "chair"


def test_a_move_larger_than_the_shape_is_warned_with_its_size(toy, chair_file, tmp_path, capsys):
    from kpd.io import read_mesh

    size = float(np.ptp(read_mesh(chair_file).vertices, axis=0).max())
    assert kpd("deform", toy, chair_file, "--move", f"1:0,0,{0.5 * size}", "--out", tmp_path / "a.ply") == 0
    assert "--move" not in capsys.readouterr().err
    assert kpd("deform", toy, chair_file, "--move", f"1:0,0,{2 * size}", "--out", tmp_path / "b.ply") == 0
    err = capsys.readouterr().err
    assert f"more than the shape's size ({size:.3g}" in err and "--move 1" in err


def test_sample_and_align_take_scan(toy, chair_file, tmp_path, capsys):
    other = chair_file.with_name("chair_0891.ply")
    assert kpd("sample", toy, chair_file, "--scan", "--up", "z", "--n", "2", "--out", tmp_path / "v") == 0
    record = json.loads((tmp_path / "v" / "keypoints.json").read_text())
    assert "scan" in record and len(record["variants"]) == 2
    assert kpd("align", toy, chair_file, other, "--scan", "--out", tmp_path / "a.ply", "--keypoints",
               tmp_path / "a.json") == 0
    assert json.loads((tmp_path / "a.json").read_text())["scan"] is True
    assert kpd("align", toy, chair_file, other, "--up", "z", "--out", tmp_path / "b.ply") == 2
    assert "--up goes with --scan" in capsys.readouterr().err


def test_demo_takes_scan_with_its_own_mesh(toy, chair_file, tmp_path, capsys):
    assert kpd("demo", "--model", toy, "--mesh", chair_file, "--scan", "--up", "z", "--out", tmp_path / "d") == 0
    record = json.loads((tmp_path / "d" / "keypoints.json").read_text())
    assert "scan" in record and not (tmp_path / "d" / "rig.npz").exists()  # a .npz rig holds no scan frame
    assert "--scan" in capsys.readouterr().out.splitlines()[-1]  # the next command orients the mesh alike
    assert kpd("demo", "--model", toy, "--scan", "--out", tmp_path / "e") == 2
    assert "--scan goes with --mesh" in capsys.readouterr().err


def _gltf_root_rotation(path: Path):
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20:20 + length])
    root = document["nodes"][document["scenes"][document.get("scene", 0)]["nodes"][0]]
    return root.get("rotation")


def test_rigs_stand_up_in_the_shapes_own_frame(data_dir, tmp_path):
    shoe = sorted((data_dir / "gso_shoes").glob("*/model.obj"))[0]
    assert kpd("rig", "shoe", shoe, "--targets", "keypoint", "--out", tmp_path / "shoe.glb") == 0
    assert _gltf_root_rotation(tmp_path / "shoe.glb") is None  # the shoe model's frame is y up, as glTF's
    chair = data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply"
    assert kpd("rig", "chair", chair, "--targets", "keypoint", "--out", tmp_path / "chair.glb") == 0
    assert _gltf_root_rotation(tmp_path / "chair.glb") is not None  # z up turned to glTF's +Y
    assert kpd("rig", "chair", chair, "--targets", "keypoint", "--view-up", "+y", "--out", tmp_path / "y.glb") == 0
    assert _gltf_root_rotation(tmp_path / "y.glb") is None  # --view-up still wins


def test_rig_with_scan_takes_the_recovered_up_axis(data_dir, tmp_path):
    chair = (data_dir / "keypointnet" / "models" / "03001627" / "88382b877be91b2a572f8e1c1caad99e"
             / "model_normalized.obj")
    assert kpd("rig", "chair", chair, "--scan", "--targets", "keypoint", "--out", tmp_path / "y.glb") == 0
    assert _gltf_root_rotation(tmp_path / "y.glb") is None  # ShapeNet: y up, found by --scan


def test_scan_keeps_the_category_check(data_dir, capsys):
    plane = sorted((data_dir / "keypointnet" / "pcds" / "02691156").glob("*.pcd"))[0]
    assert kpd("keypoints", "chair", plane) == 0
    assert "probably not a chair" in capsys.readouterr().err
    assert kpd("keypoints", "chair", plane, "--scan") == 0
    err = capsys.readouterr().err
    assert "probably not a chair" in err and "pass --scan" not in err
