"""MTL material libraries (kpd.io.mtl)."""

from __future__ import annotations

import logging

from kpd.io import mtl


def test_a_library_gives_each_material_its_colour_and_map(tmp_path):
    (tmp_path / "wood.png").write_bytes(b"not read here")
    (tmp_path / "m.mtl").write_text("# a comment\nnewmtl a\nKd 1 0.5 2 # clipped\nnewmtl b\nKd 0.25\n"
                                    "map_Kd -s 1 1 1 wood.png\nnewmtl c\n")
    materials = mtl.read_library(tmp_path / "m.obj", tmp_path / "m.mtl")
    assert list(materials) == ["a", "b", "c"]
    assert materials["a"].kd == (1.0, 0.5, 1.0)
    assert materials["b"].kd == (0.25, 0.25, 0.25)
    assert materials["b"].map_kd_name == "wood.png" and materials["b"].map_kd == tmp_path / "wood.png"
    assert materials["c"].kd == mtl.DEFAULT_KD and materials["c"].map_kd is None


def test_an_unreadable_colour_is_grey_with_a_warning(tmp_path, caplog):
    (tmp_path / "m.mtl").write_text("newmtl a\nKd red green blue\n")
    with caplog.at_level(logging.WARNING):
        materials = mtl.read_library(tmp_path / "m.obj", tmp_path / "m.mtl")
    assert materials["a"].kd == mtl.DEFAULT_KD
    assert "unreadable Kd" in caplog.text


def test_map_statements_are_every_file_naming_key_and_rename_in_place():
    data = (b"newmtl a\nmap_Kd -o 0 0 0 a b.png # the map\nmap_Ks s.png\nBUMP -bm 2 n.png\nKd 1 1 1\n"
            b"map_Kd\n")
    statements = mtl.map_statements(data)
    assert [i for i, _ in statements] == [1, 2, 3]
    assert [mtl.map_file(arguments) for _, arguments in statements] == [b"b.png", b"s.png", b"n.png"]
    renamed = mtl.renamed_library(data, {"b.png": "out_b.png", "n.png": "out_n.png"})
    assert renamed.split(b"\n")[1:4] == [b"map_Kd -o 0 0 0 a out_b.png # the map", b"map_Ks s.png",
                                         b"BUMP -bm 2 out_n.png"]


def test_a_library_statement_may_name_several_files_or_one_with_spaces(tmp_path):
    (tmp_path / "a.mtl").write_text("")
    (tmp_path / "my lib.mtl").write_text("")
    obj = tmp_path / "m.obj"
    assert mtl.library_files(obj, "my lib.mtl") == [("my lib.mtl", tmp_path / "my lib.mtl")]
    assert mtl.library_files(obj, "a.mtl b.mtl") == [("a.mtl", tmp_path / "a.mtl"), ("b.mtl", None)]
