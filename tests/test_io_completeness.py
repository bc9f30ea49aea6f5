"""kpd.io.ply, kpd.io.pcd, kpd.io.off: a file holding less than its header declares is refused, before Open3D
returns a half-read geometry; a complete file passes."""

from __future__ import annotations

import numpy as np
import pytest

from kpd.errors import InputError
from kpd.io import off, pcd, ply, write_points


def _ply(tmp_path, binary: bool, vertices: int = 5, faces: int = 2):
    fmt = "binary_little_endian" if binary else "ascii"
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n"
            f"element face {faces}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    if binary:
        body = np.arange(15, dtype="<f4").tobytes() + (b"\x03" + np.array([0, 1, 2], "<i4").tobytes()) * 2
    else:
        body = "".join(f"{i} {i} {i}\n" for i in range(5)).encode() + b"3 0 1 2\n3 1 2 3\n"
    path = tmp_path / ("b.ply" if binary else "a.ply")
    path.write_bytes(head + body)
    return path, len(head) + len(body)


@pytest.mark.parametrize("binary", [True, False])
def test_ply(tmp_path, binary):
    path, size = _ply(tmp_path, binary)
    ply.check_complete(path)
    data = path.read_bytes()
    path.write_bytes(data[: size - (5 if binary else 8)])
    with pytest.raises(InputError, match="the file is truncated: its header declares 5 'vertex' and 2 'face'"):
        ply.check_complete(path)
    path.write_bytes(b"solid not a ply\n")
    with pytest.raises(InputError, match="not a PLY file"):
        ply.check_complete(path)


def test_pcd(tmp_path):
    path = tmp_path / "p.pcd"
    write_points(path, np.random.default_rng(0).normal(size=(100, 3)))
    pcd.check_complete(path)
    data = path.read_bytes()
    path.write_bytes(data[:-24])
    with pytest.raises(InputError, match="its header declares 100 points"):
        pcd.check_complete(path)


def test_off(tmp_path):
    path = tmp_path / "m.off"
    path.write_text("OFF\n# a comment\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 2 3\n")
    off.check_complete(path)
    path.write_text("OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n")
    with pytest.raises(InputError, match=r"declares 4 vertices and 2 faces \(6 rows\) but 5 rows follow"):
        off.check_complete(path)
