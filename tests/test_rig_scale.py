"""The rig at scan sizes: the compiled, streamed binding gives today's rig; small rig files; old files."""

import numpy as np
import pytest

from kpd.basis import coincident_mvc_weights
from kpd.errors import InputError
from kpd.io import read_mesh
from kpd.io.integrity import HASH_KEY, content_hash
from kpd.rig import Rig, _mesh_arrays
from kpd.straighten import straighten_basis_reference
from rig_shapes import box_mesh, fps_rig


def todays_rig(rig, straighten=True):
    """The rig as kpd bound it before the compiled kernel: the (V, C) weights from the numpy kernel, their product
    with the influence, and the straightening as one sparse LU over every vertex."""
    vertices = rig.normalizer.apply(rig.mesh.vertices)
    weights = coincident_mvc_weights(vertices, rig.cage)
    basis = weights @ rig.influence.T
    correction = None
    if straighten:
        corrected = straighten_basis_reference(basis, vertices, rig.mesh.triangles)
        correction = None if corrected is basis else corrected - basis
    return Rig(rig.mesh, rig.normalizer, rig.normalizer.apply(rig.keypoints), rig.cage, rig.influence, weights,
               correction)


def edits(rig, count=6, seed=0):
    """Keypoint sets with every keypoint moved by up to half the box diagonal."""
    diagonal = float(np.linalg.norm(np.ptp(rig.mesh.vertices, axis=0)))
    rng = np.random.default_rng(seed)
    return [rig.keypoints + rng.uniform(-0.3, 0.3, (rig.num_keypoints, 3)) * diagonal for _ in range(count)], diagonal


def assert_same_edits(new, old):
    sets, diagonal = edits(new)
    for keypoints in sets:
        assert np.abs(new.deform(keypoints) - old.deform(keypoints)).max() <= 1e-6 * diagonal


@pytest.mark.parametrize("path, straighten", [
    ("modelnet10/chair/test/chair_0890.ply", True),
    ("modelnet10/table/test/table_0411.ply", True),
    ("scans/sneaker.ply", False),
])
def test_bound_rigs_deform_as_todays_within_1e6_of_the_diagonal(data_dir, path, straighten):
    rig = fps_rig(read_mesh(data_dir / path), straighten=straighten)
    assert rig._weights is None  # the bound rig holds the basis only
    assert_same_edits(rig, todays_rig(rig, straighten))


def test_the_shipped_models_rig_deforms_as_todays(data_dir):
    from kpd.runtime import Model

    model = Model.load("table", threads=1)
    rig = model.rig(read_mesh(data_dir / "modelnet10" / "table" / "test" / "table_0411.ply"))
    assert rig.basis.dtype == np.float32
    old = todays_rig(rig)
    assert_same_edits(rig, old)
    assert np.abs(rig.correction - old.correction).max() <= 1e-4


def test_saved_rigs_hold_the_basis_not_the_weights(data_dir, tmp_path):
    mesh = read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply")
    rig = fps_rig(mesh)
    rig.save(tmp_path / "rig.npz")
    with np.load(tmp_path / "rig.npz") as stored:
        assert str(stored["format"]) == "kpd-rig/3"
        assert "weights" not in stored.files and "basis_correction" not in stored.files
        assert stored["basis"].shape == (len(mesh.vertices), 12)
    back = Rig.load(tmp_path / "rig.npz")
    assert back.correction is not None  # it was straightened, and says so
    for keypoints in edits(rig)[0]:
        np.testing.assert_array_equal(back.deform(keypoints), rig.deform(keypoints))


def write_old_rig(rig, path, fmt):
    """A rig file as kpd wrote it before kpd-rig/3 (the save of kpd 0a2239f): the (V, C) weights, and in
    kpd-rig/2 the straightening's correction when there is one."""
    arrays = {
        "format": np.array(fmt),
        "keypoints": rig.normalizer.apply(rig.keypoints),
        "cage_vertices": rig.cage.vertices,
        "cage_faces": rig.cage.faces,
        "influence": rig.influence,
        "weights": rig.weights,
        **({} if rig.correction is None or fmt == "kpd-rig/1" else {"basis_correction": rig.correction}),
        "normalizer_center": rig.normalizer.center_,
        "normalizer_scale": np.array(rig.normalizer.scale_),
    }
    for name, value in _mesh_arrays(rig.mesh).items():
        arrays["mesh_" + name] = value
    arrays[HASH_KEY] = np.array(content_hash(arrays))
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)


@pytest.mark.parametrize("fmt", ["kpd-rig/1", "kpd-rig/2"])
def test_old_rig_files_load_and_deform_as_before(data_dir, tmp_path, fmt):
    mesh = read_mesh(data_dir / "modelnet10" / "table" / "test" / "table_0411.ply")
    old = todays_rig(fps_rig(mesh), straighten=fmt == "kpd-rig/2")
    write_old_rig(old, tmp_path / "old.npz", fmt)
    back = Rig.load(tmp_path / "old.npz")
    assert back.basis.dtype == np.float64
    np.testing.assert_array_equal(back.weights, old.weights)
    assert (back.correction is None) == (fmt == "kpd-rig/1")
    for keypoints in edits(old)[0]:
        offsets = keypoints - old.keypoints
        expected = mesh.vertices + (old.weights @ old.influence.T
                                    + (0 if back.correction is None else old.correction)) @ offsets
        np.testing.assert_allclose(back.deform(keypoints), expected, rtol=0, atol=1e-12 * old.normalizer.scale_)


def test_a_rig_with_both_or_neither_of_weights_and_basis_is_refused():
    rig = fps_rig(box_mesh(), k=8, straighten=False)
    args = (rig.mesh, rig.normalizer, rig.normalizer.apply(rig.keypoints), rig.cage, rig.influence)
    with pytest.raises(InputError, match="either the MVC weights"):
        Rig(*args)
    with pytest.raises(InputError, match="either the MVC weights"):
        Rig(*args, rig.weights, basis=rig.basis)
    with pytest.raises(InputError, match=r"edit basis must be \(V, K\) = \(8, 8\)"):
        Rig(*args, basis=np.zeros((8, 3)))


def test_deforming_some_rows_writes_those_rows_only():
    rig = fps_rig(box_mesh(), k=8, straighten=False)
    keypoints = rig.moved({2: [0.1, 0.2, -0.3]})
    out = np.full_like(rig.mesh.vertices, 7.0)
    rows = np.array([5, 1, 6])
    assert rig.deform(keypoints, out=out, rows=rows) is out
    full = rig.deform(keypoints)
    np.testing.assert_array_equal(out[rows], full[rows])
    assert (np.delete(out, rows, axis=0) == 7.0).all()
    with pytest.raises(InputError, match=r"rows must be \(P,\) vertex indices in \[0, 8\)"):
        rig.deform(keypoints, rows=np.array([8]))


def test_a_large_npz_is_read_on_two_threads_as_in_one(tmp_path, monkeypatch):
    """load_numpy reads a large .npz's members on two threads (a scan's rig: deflated triangles beside the stored
    basis): the same arrays in the file's order as one thread reads them, and a damaged member is still one
    InputError; the content hash over the arrays' memory is the hash of their bytes."""
    import hashlib
    import threading
    import zipfile

    from kpd.io.integrity import load_numpy

    rng = np.random.default_rng(0)
    arrays = {"format": np.array("kpd-rig/3"), "basis": rng.normal(size=(400_000, 6)).astype(np.float32),
              "mesh_triangles": rng.integers(0, 400_000, (600_000, 3)).astype(np.int32), "scale": np.array(2.5),
              "mesh_vertices": rng.normal(size=(400_000, 3)), "flags": np.array([True, False])}
    path = tmp_path / "large.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for name, value in arrays.items():
            member = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            member.compress_type = zipfile.ZIP_STORED if value.dtype.kind == "f" else zipfile.ZIP_DEFLATED
            with archive.open(member, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, value, allow_pickle=False)
    assert path.stat().st_size > 16 << 20
    readers = set()
    getitem = np.lib.npyio.NpzFile.__getitem__

    def recorded(self, key):
        readers.add(threading.current_thread().name)
        return getitem(self, key)

    monkeypatch.setattr(np.lib.npyio.NpzFile, "__getitem__", recorded)
    read = load_numpy(path)
    assert list(read) == list(arrays) and all(np.array_equal(read[k], v) and read[k].dtype == v.dtype
                                              for k, v in arrays.items())
    assert len(readers) == 2 and all(name.startswith("kpd-npz") for name in readers)
    for value in (arrays["basis"], arrays["mesh_vertices"].T, arrays["flags"]):
        by_copy = hashlib.sha256()
        by_copy.update(b"[1")
        contiguous = np.ascontiguousarray(value)
        by_copy.update(f"a{contiguous.dtype.str}{contiguous.shape}".encode() + contiguous.tobytes() + b"]")
        assert content_hash([value]) == by_copy.hexdigest()
    data = bytearray(path.read_bytes())
    for member in ("basis.npy", "mesh_triangles.npy"):  # a stored member (CRC) and a deflated one (zlib or CRC)
        with zipfile.ZipFile(path) as archive:
            info = archive.getinfo(member)
        damaged = bytearray(data)
        damaged[info.header_offset + 30 + len(member) + info.compress_size // 2] ^= 0xFF
        bad = tmp_path / f"bad_{member}.npz"
        bad.write_bytes(bytes(damaged))
        with pytest.raises(InputError, match="damaged .npz"):
            load_numpy(bad)
