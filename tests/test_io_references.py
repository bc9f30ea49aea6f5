"""Which files a file may name (kpd.io.references)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from kpd.io import references


@pytest.fixture
def folder(tmp_path):
    inside = tmp_path / "in"
    (inside / "maps").mkdir(parents=True)
    (inside / "maps" / "a.png").write_bytes(b"x")
    (tmp_path / "out.png").write_bytes(b"x")
    (inside / "out_link.png").symlink_to(tmp_path / "out.png")
    (inside / "in_link.png").symlink_to(inside / "maps" / "a.png")
    (inside / "loop").symlink_to(inside / "loop")
    os.mkfifo(inside / "fifo")
    return inside


@pytest.mark.parametrize("name, refused", [
    ("maps/a.png", None), ("maps/../maps/a.png", None), ("in_link.png", None), ("missing.png", None), ("", None),
    ("../out.png", "outside the input's folder"), ("out_link.png", "outside the input's folder"),
    ("/etc/passwd", "an absolute path"), ("\\\\server\\share", "an absolute path"), ("C:\\x.png", "an absolute path"),
    ("a\0.png", "control character"), ("fifo", "not a regular file"), ("maps", "not a regular file"),
    ("loop", "cannot be examined"), ("x" * 5000, "cannot be examined"),
])
def test_locate(folder, name, refused):
    found = references.locate(folder, folder, name)
    assert found.refused is None if refused is None else refused in found.refused
    if refused is None and name in ("maps/a.png", "maps/../maps/a.png", "in_link.png"):
        assert found.path == (folder / "maps" / "a.png").resolve()
    if refused is not None or name in ("missing.png", ""):
        assert found.path is None


def test_system_files_are_refused_wherever_the_input_lies():
    assert references.locate(Path("/proc/self"), Path("/proc/self"), "environ").refused == "a system file"
    assert references.locate(Path("/"), Path("/"), "dev/zero").refused == "a system file"


@pytest.mark.parametrize("uri, refused", [
    ("maps/a.png", None), ("maps%2Fa.png", None), ("%2Fetc%2Fpasswd", "an absolute path"),
    ("..%2Fout.png", "outside"), ("%00x.png", "control character"), ("file:///etc/passwd", "scheme 'file'"),
    ("https://example.org/a.png", "scheme 'https'"),
])
def test_locate_uri_decodes_first(folder, uri, refused):
    found = references.locate_uri(folder, folder, uri)
    assert found.refused is None if refused is None else refused in found.refused


def test_read_named_checks_the_open_file(folder, tmp_path):
    assert references.read_named(folder / "maps" / "a.png", 1) == b"x"
    big = tmp_path / "big"
    big.write_bytes(b"12345")
    assert "over the 4" in references.read_named(big, 4)
    assert "cannot be opened" in references.read_named(folder / "out_link.png", 10)  # a symlink put in place


def test_is_text():
    assert references.is_text(b"newmtl a\r\n\tKd 1 1 1\x0c\x1b")
    assert not references.is_text(b"newmtl a\0") and not references.is_text(b"\x01\x02")


def test_shapenet_layout_reaches_the_images_folder_beside_models_and_nothing_else(tmp_path):
    """ShapeNetCore keeps <model>/models/model_normalized.obj and its maps in <model>/images/: that sibling folder is
    accepted, the rest of the parent is not, and a bundle (dataset_layouts=False) gets no such exception."""
    models = tmp_path / "model" / "models"
    (tmp_path / "model" / "images").mkdir(parents=True)
    models.mkdir()
    (tmp_path / "model" / "images" / "texture0.jpg").write_bytes(b"x")
    (tmp_path / "model" / "secret.jpg").write_bytes(b"x")
    (tmp_path / "model" / "imagesX").mkdir()
    (tmp_path / "model" / "imagesX" / "t.jpg").write_bytes(b"x")
    found = references.locate(models, models, "../images/texture0.jpg")
    assert found.refused is None and found.path == (tmp_path / "model" / "images" / "texture0.jpg").resolve()
    for name in ("../secret.jpg", "../images/../secret.jpg", "../imagesX/t.jpg", "../../model/secret.jpg"):
        assert references.locate(models, models, name).refused == "outside the input's folder", name
    assert references.locate(models, models, "../images/texture0.jpg",
                             dataset_layouts=False).refused == "outside the input's folder"
    other = tmp_path / "model" / "meshes"  # the exception is for a folder named models only
    other.mkdir()
    assert references.locate(other, other, "../images/texture0.jpg").refused == "outside the input's folder"
