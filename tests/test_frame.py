"""The frame and category check (kpd.frame) on real shapes with the shipped chair model, and its warning line in the
commands that run without --scan."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import TURN_ONTO_SIDE

from kpd.cli import main
from kpd.frame import FrameCheck, calibrate, check_frame, keypoint_fit
from kpd.io import Mesh, read_mesh, read_shape, write_mesh


@pytest.fixture(scope="module")
def test_chair(data_dir):
    return read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply")


def test_upright_chair_is_silent_and_a_turned_one_is_warned(chair_model, test_chair):
    upright = check_frame(chair_model, test_chair)
    assert isinstance(upright, FrameCheck)
    assert not upright.turned and upright.angle < 30 and upright.warnings("chair") == []
    side = check_frame(chair_model, Mesh(test_chair.vertices @ TURN_ONTO_SIDE.T, test_chair.triangles))
    assert side.turned and 60 < side.angle < 120
    assert side.up == "y"  # the input's axis that the best rotation turns up
    assert side.given_score > 1.15 * side.best_score
    (line,) = side.warnings("chair", "side.ply")
    assert "--scan" in line and "--scan --up y" in line and "side.ply" in line


def test_category_limits(chair_model, data_dir, test_chair):
    """Limits calibrated on a few training chairs: a test chair passes, the YCB banana is flagged as no chair."""
    files = sorted((data_dir / "modelnet10" / "chair" / "train").glob("*.ply"))[::100][:8]
    points = [chair_model.sample(read_mesh(f))[1] for f in files]
    limits = calibrate(chair_model.template_points, chair_model.up, points, lambda p: chair_model.run(p)[0])
    assert limits["shapes"] == len(files) and limits["score_limit"] > limits["median_score"] > 0
    assert limits["keypoint_limit"] > limits["median_keypoint_fit"] > 0
    from kpd.frame import _aligner, _check

    aligner = _aligner(chair_model.template_points, chair_model.up)
    run = lambda p: chair_model.run(p)[0]  # noqa: E731
    chair = _check(aligner, run, chair_model.sample(test_chair)[1], chair_model.up, limits)
    assert not chair.foreign
    banana = read_shape(data_dir / "scans" / "ycb" / "banana" / "textured_simple_reoriented.obj")
    flagged = _check(aligner, run, chair_model.sample(banana)[1], chair_model.up, limits)
    assert flagged.foreign and flagged.keypoint_fit > chair.keypoint_fit
    (line,) = flagged.warnings("chair", "banana.obj")
    assert "probably not a chair" in line


def test_keypoint_fit_is_zero_on_the_points():
    points = np.random.default_rng(0).uniform(-1, 1, (200, 3))
    assert keypoint_fit(lambda p: p[:12], points) == 0.0
    assert keypoint_fit(lambda p: p[:12] + [0.0, 0.0, 5.0], points) > 3.0


def test_commands_warn_about_a_turned_chair(test_chair, tmp_path, capsys):
    turned = tmp_path / "turned.ply"
    write_mesh(turned, Mesh(test_chair.vertices @ TURN_ONTO_SIDE.T, test_chair.triangles))
    upright = tmp_path / "upright.ply"
    write_mesh(upright, test_chair)
    assert main(["keypoints", "chair", str(turned)]) == 0
    err = capsys.readouterr().err
    assert err.count("warning:") == 1 and "--scan --up y" in err
    assert main(["deform", "chair", str(upright), "--move", "0:0,0,0.1", "--out", str(tmp_path / "d.ply")]) == 0
    assert "warning" not in capsys.readouterr().err
    assert main(["align", "chair", str(upright), str(turned), "--out", str(tmp_path / "a.ply")]) == 0
    err = capsys.readouterr().err
    assert err.count("warning:") == 1 and str(turned) in err
    # with --scan the shape is oriented first: no frame warning
    assert main(["keypoints", "chair", str(turned), "--scan", "--up", "y"]) == 0
    assert "clearly better turned" not in capsys.readouterr().err
