"""kpd.viewer.shots: pictures of several shots with one window, the triangles of a sheet's variants worked out once."""

import numpy as np
from helpers import subdivided_box


def test_a_sheet_of_variants_draws_each_as_a_new_mesh_would_with_the_triangles_worked_out_once(data_dir, tmp_path,
                                                                                               monkeypatch):
    """A contact sheet of the sneaker scan and its variants (the same triangles, moved vertices, coincident ones kept
    together) makes one ShadedMesh for them all, and one more for a variant where two vertices that were apart now
    coincide (its welding differs): the same picture as a ShadedMesh made for each. A mesh drawn in parts (a
    3-material ShapeNet bench) gets one for each cell, as the legacy renderer's order of parts follows their objects."""
    from kpd.io import read_mesh
    from kpd.viewer import shots
    from kpd.viewer.pictures import render_sheet

    made = []
    real = shots.ShadedMesh

    def counted(*args, **kwargs):
        made.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(shots, "ShadedMesh", counted)
    mesh = read_mesh(data_dir / "scans" / "sneaker.ply")
    v = mesh.vertices
    variants = [mesh.with_vertices(v + 0.05 * np.sin(3 * v[:, [1, 2, 0]])),
                mesh.with_vertices(v * [1.0, 1.2, 0.9])]
    first, inverse = mesh.position_groups()
    merged = v.copy()
    merged[inverse == inverse[first[1]]] = v[first[0]]  # the second position's vertices moved onto the first's
    variants.append(mesh.with_vertices(merged))
    render_sheet([mesh, *variants], tmp_path / "reused.png", up="y", cell=2.0)
    assert [id(m) for m in made] == [id(mesh), id(variants[2])]
    bench = read_mesh(data_dir / "shapenetcore_obj" / "bench" / "50db85e4889831dff155d75bbf62b80" / "models" /
                      "model_normalized.obj")
    assert len(bench.textures) == 3
    made.clear()
    bench_variants = [bench, bench.with_vertices(bench.vertices * 1.1)]
    render_sheet(bench_variants, tmp_path / "bench.png", up="y", cell=2.0)
    assert [id(m) for m in made] == [id(m) for m in bench_variants]
    monkeypatch.setattr(shots, "_shaded_layer", lambda shaded, slot, m, color, *, override: real(
        m, color, override=override, once=True))
    render_sheet([mesh, *variants], tmp_path / "fresh.png", up="y", cell=2.0)
    assert (tmp_path / "reused.png").read_bytes() == (tmp_path / "fresh.png").read_bytes()


def test_a_sheet_holds_one_mesh_at_a_time_of_those_made_as_asked_for(tmp_path):
    """render_sheet over a sequence whose meshes are made when asked for (kpd sample's variants) holds a few at
    once, not all of them (16 variants of a 1.37M-vertex mesh held were 0.5 GB), and draws what the list of the same
    meshes draws."""
    import weakref
    from collections.abc import Sequence

    from kpd.io import Mesh
    from kpd.viewer.pictures import render_sheet

    base = subdivided_box((0.3, 0.6, 0.3), 2, 0.15)  # a tall box
    alive, most = set(), [0]

    class Made(Sequence):
        def __len__(self):
            return 8

        def __getitem__(self, i):
            if not 0 <= i < 8:
                raise IndexError(i)
            mesh = Mesh(base.vertices * (1 + 0.1 * i), base.triangles)
            alive.add(id(mesh))
            weakref.finalize(mesh, alive.discard, id(mesh))
            most[0] = max(most[0], len(alive))
            return mesh

    keypoints = [base.vertices[:4] * (1 + 0.1 * i) for i in range(8)]
    render_sheet(Made(), tmp_path / "made.png", keypoints=keypoints, cell=1.5)
    assert 1 <= most[0] <= 3, most[0]
    render_sheet(list(Made()), tmp_path / "list.png", keypoints=keypoints, cell=1.5)
    assert (tmp_path / "made.png").read_bytes() == (tmp_path / "list.png").read_bytes()


