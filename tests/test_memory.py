"""The memory budget of binding: a mesh too large ends in one line, before any work; ``ulimit -v`` caps what is
available."""

import pytest

from kpd.cage import Cage
from kpd.errors import InputError
from kpd.io import write_mesh
from kpd.memory import bind_memory
from rig_shapes import box_mesh, fps_rig


def test_a_mesh_larger_than_memory_allows_ends_in_one_line(tmp_path, monkeypatch, capsys):
    import kpd.memory
    from kpd.cli import main

    mesh = box_mesh()
    need = bind_memory(8, 12, 8)
    monkeypatch.setattr(kpd.memory, "available_memory", lambda: need - 1)
    with pytest.raises(InputError, match=r"a mesh of 8 vertices and 12 triangles needs about .* to bind; "
                                         r".* of memory is available"):
        fps_rig(mesh, k=8)
    write_mesh(tmp_path / "box.ply", mesh)
    code = main(["deform", "chair", str(tmp_path / "box.ply"), "--move", "0:0,0,0.1", "--out",
                 str(tmp_path / "out.ply")])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    errors = [line for line in lines if "error" in line]  # (a warning on the box's frame may come first)
    assert errors == lines[-1:] and "Traceback" not in "".join(lines)
    assert errors[0].startswith("kpd deform: error: a mesh of 8 vertices and 12 triangles needs about")
    assert not (tmp_path / "out.ply").exists()
    monkeypatch.setattr(kpd.memory, "available_memory", lambda: need)
    assert isinstance(fps_rig(mesh, k=8).cage, Cage)


def test_a_limit_on_the_address_space_caps_the_memory_available():
    """``ulimit -v`` (RLIMIT_AS, as some batch schedulers set it) caps what binding may have: a real limit 300 MiB
    above what the process maps, and a mesh that needs more is refused in one line naming both."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        import resource
        from kpd.errors import InputError
        from kpd.memory import available_memory, check_bind_memory
        unlimited = available_memory()
        with open("/proc/self/status") as fh:
            size = next(int(line.split()[1]) * 1024 for line in fh if line.startswith("VmSize:"))
        resource.setrlimit(resource.RLIMIT_AS, (size + 300 * 2**20, resource.getrlimit(resource.RLIMIT_AS)[1]))
        print(unlimited, available_memory())
        try:
            check_bind_memory(2_000_000, 4_000_000, 12)
        except InputError as exc:
            print(exc)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    first, message = proc.stdout.splitlines()
    unlimited, limited = map(int, first.split())
    assert 250 * 2**20 < limited <= 300 * 2**20 < unlimited
    assert message.startswith("a mesh of 2,000,000 vertices and 4,000,000 triangles needs about 1.4 GiB to bind; ")
    assert message.endswith("MiB of address space is left under this process's limit (simplify the mesh, or raise "
                            "the limit: ulimit -v)")


def test_the_memory_is_checked_once_per_binding(tmp_path, monkeypatch):
    """Checked at the door and trusted inside: ``Rig.bind``, ``Model.rig`` and ``kpd deform`` each ask for the
    memory available once."""
    import kpd.memory
    from kpd.cli import main
    from kpd.runtime import Model

    asked = []
    monkeypatch.setattr(kpd.memory, "available_memory", lambda: asked.append(1) or 1 << 40)
    mesh = box_mesh()
    fps_rig(mesh, k=8)
    assert len(asked) == 1
    Model.load("chair", threads=1).rig(mesh)
    assert len(asked) == 2
    write_mesh(tmp_path / "box.ply", mesh)
    assert main(["deform", "chair", str(tmp_path / "box.ply"), "--move", "0:0,0,0.1", "--out",
                 str(tmp_path / "out.ply")]) == 0
    assert len(asked) == 3
    # kpd render binds later, beside getting the mesh ready to draw: the memory is asked for once there too
    assert main(["render", "chair", str(tmp_path / "box.ply"), "--out", str(tmp_path / "box.png"), "--size",
                 "160x120"]) == 0
    assert len(asked) == 4
