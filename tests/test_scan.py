"""`kpd scan`: the command on real scans, its report and picture, and its refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scan_shapes import floor, lumpy, rotation, sphere

from kpd.cli import main
from kpd.geometry import sample_surface
from kpd.io import read_mesh, read_points, write_points
from kpd.scan import (
    rotation_angle,
)


def test_cli_writes_aligned_scan_and_report(tmp_path, capsys):
    scan = lumpy(3000, 0) @ rotation(3).T * 30.0 + 7.0
    write_points(tmp_path / "scan.ply", scan)
    write_points(tmp_path / "ref.ply", lumpy(3000, 1))
    out, report = tmp_path / "aligned.ply", tmp_path / "report.json"
    code = main(["scan", str(tmp_path / "scan.ply"), "--reference", str(tmp_path / "ref.ply"), "--out", str(out),
                 "--report", str(report), "--no-outliers"])
    assert code == 0
    assert "oriented" in capsys.readouterr().out
    aligned = read_points(out).points
    record = json.loads(report.read_text())
    inverse = np.asarray(record["inverse"])
    np.testing.assert_allclose(aligned @ inverse[:3, :3].T + inverse[:3, 3], scan, atol=1e-6)
    assert rotation_angle(np.asarray(record["rotation"]) @ rotation(3)) < 5.0
    assert record["clean"]["outliers_removed"] is None
    # a second run refuses to overwrite without --force
    code = main(["scan", str(tmp_path / "scan.ply"), "--out", str(out), "--report", str(report)])
    assert code == 2 and "exists" in capsys.readouterr().err


@pytest.mark.parametrize("bad", ["nan", "flat", "missing", "floor"])
def test_cli_bad_input_exits_2_with_one_line_and_writes_nothing(tmp_path, capsys, bad):
    path = tmp_path / "scan.npy"
    if bad == "nan":
        points = sphere(200, 0)
        points[3, 0] = np.nan
        np.save(path, points)
    elif bad == "flat":
        np.save(path, sphere(200, 0)[:, :2])
    elif bad == "floor":
        np.save(path, np.concatenate([floor(2000, 0, half=1.0), [[0.0, 0.0, 0.5]]]))
    out, report = tmp_path / "out.ply", tmp_path / "report.json"
    code = main(["scan", str(path), "--out", str(out), "--report", str(report), "--up", "z"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("kpd scan: error:")
    assert not out.exists() and not report.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == (["scan.npy"] if bad != "missing" else [])


def test_cli_refuses_mesh_output_for_points_and_bad_axis(tmp_path, capsys):
    write_points(tmp_path / "scan.ply", lumpy(500, 0))
    code = main(["scan", str(tmp_path / "scan.ply"), "--out", str(tmp_path / "a.obj"),
                 "--report", str(tmp_path / "r.json")])
    assert code == 2 and "point cloud" in capsys.readouterr().err
    code = main(["scan", str(tmp_path / "scan.ply"), "--out", str(tmp_path / "a.ply"),
                 "--report", str(tmp_path / "r.json"), "--up", "sideways"])
    assert code == 2 and "--up" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.ply"]


def test_cli_model_template(tmp_path, capsys, chair):
    from kpd.bundle import shipped_bundles

    assert "chair" in shipped_bundles()
    path = tmp_path / "chair.ply"
    write_points(path, sample_surface(chair.vertices, chair.triangles, 4000, seed=0).points @ rotation(1).T)
    code = main(["scan", str(path), "--model", "chair", "--out", str(tmp_path / "a.ply"),
                 "--report", str(tmp_path / "r.json")])
    assert code == 0
    record = json.loads((tmp_path / "r.json").read_text())
    assert "template" in record["reference"] and record["orientation"]["score"] > 0


def test_cli_picture_shows_the_scan_best_and_runner_up(tmp_path, capsys, chair):
    import matplotlib.image

    path = tmp_path / "chair.ply"
    write_points(path, sample_surface(chair.vertices, chair.triangles, 4000, seed=0).points @ rotation(2).T)
    picture = tmp_path / "check.png"
    code = main(["scan", str(path), "--model", "chair", "--out", str(tmp_path / "a.ply"),
                 "--report", str(tmp_path / "r.json"), "--picture", str(picture)])
    assert code == 0 and "check.png" in capsys.readouterr().out
    image = matplotlib.image.imread(picture)[..., :3]  # (H, W, 3) floats in [0, 1]
    assert image.shape[1] > 2 * image.shape[0]  # three panels side by side
    saturation = image.max(axis=2) - image.min(axis=2)
    grey = (saturation < 0.05) & (np.abs(image.mean(axis=2) - 0.7) < 0.12)  # the reference's points (and grid panes)
    for third in np.array_split(np.arange(image.shape[1]), 3):
        assert (saturation[:, third] > 0.3).mean() > 0.01  # the scan's coloured points in every panel
    assert grey[:, image.shape[1] // 3:].mean() > grey[:, : image.shape[1] // 3].mean()  # reference behind 2 and 3


def test_cli_picture_errors(tmp_path, capsys):
    write_points(tmp_path / "scan.ply", lumpy(500, 0))
    base = ["scan", str(tmp_path / "scan.ply"), "--out", str(tmp_path / "a.ply"), "--report", str(tmp_path / "r.json")]
    assert main(base + ["--reference", str(tmp_path / "scan.ply"), "--picture", str(tmp_path / "p.jpg")]) == 2
    assert ".png" in capsys.readouterr().err
    assert main(base + ["--picture", str(tmp_path / "p.png")]) == 2
    assert "--reference or --model" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.ply"]


@pytest.mark.parametrize("name", ["banana", "mustard_bottle", "power_drill"])
def test_cli_on_real_ycb_scans_keeps_the_mesh_and_maps_back(tmp_path, capsys, data_dir, name):
    # real textured scans (the mustard bottle's texture file is missing: read without it, with a warning)
    path = data_dir / "scans" / "ycb" / name / "textured_simple_reoriented.obj"
    scan = read_mesh(path)
    out, report = tmp_path / "aligned.obj", tmp_path / "report.json"
    code = main(["scan", str(path), "--reference", str(path), "--out", str(out), "--report", str(report)])
    assert code == 0, capsys.readouterr().err
    aligned = read_mesh(out)
    record = json.loads(report.read_text())
    inverse = np.asarray(record["inverse"])
    np.testing.assert_array_equal(aligned.triangles, scan.triangles)  # nothing of this clean scan was dropped
    np.testing.assert_allclose(aligned.vertices @ inverse[:3, :3].T + inverse[:3, 3], scan.vertices, atol=1e-6)
    assert np.abs(aligned.vertices).max() <= 1.0 + 1e-9
    assert (aligned.triangle_uvs is not None) == (scan.triangle_uvs is not None)
    assert len(aligned.textures) == len(scan.textures)
    # oriented to itself: the identity, unless the object is flagged ambiguous (the bottle is mirror-symmetric)
    assert record["orientation"]["ambiguous"] or rotation_angle(np.asarray(record["rotation"])) < 5.0
