"""kpd.io.capture: what native code and Open3D print is captured, read for failures, and passed on otherwise."""

from __future__ import annotations

import os

import numpy as np
import open3d as o3d

from kpd.io.capture import c_stderr, failures, native_output, open3d_log


def test_native_output_captures_file_descriptors(capfd):
    with native_output((1, 2)) as said:
        os.write(1, b"\x1b[1mbanner\x1b[0m on stdout\n")
        os.write(2, b"and on stderr\n")
    assert said.lines == ["banner on stdout", "and on stderr"]
    out, err = capfd.readouterr()
    assert out == "" and err == ""  # nothing reached the terminal


def test_c_stderr_keeps_failures_and_passes_the_rest_on(capfd):
    with c_stderr() as lines:
        os.write(2, b"RPly: Failed writing to file\nsome progress note\n")
    assert lines == ["RPly: Failed writing to file", "some progress note"]
    assert capfd.readouterr().err == "some progress note\n"


def test_open3d_log_and_failures(tmp_path):
    missing = tmp_path / "missing.ply"
    with open3d_log() as messages:
        o3d.io.read_point_cloud(str(missing))
    assert messages and failures(messages)  # Open3D's own words about the failed read
    assert failures(["Read geometry::Image failed: texture.png", "all fine"]) == []
    assert failures(["Unable to open file", "Unable to open file"]) == ["Unable to open file"]
    assert np.asarray(o3d.geometry.PointCloud().points).shape == (0, 3)
