"""The memory budget of binding: what binding a mesh needs at its peak, what the process may still use, and the check
that refuses a mesh too large before any work.
"""

from __future__ import annotations

import os
from pathlib import Path

from kpd.errors import InputError

__all__ = ["bind_memory", "available_memory", "check_bind_memory"]

# What binding adds at its peak to a process that has read the mesh and loaded the model (the surface sample, the
# mesh's copies, the basis and the straightening's system and factorisations; CAD meshes, full of slivers, are the
# worst case), with what the commands that bind add to draw it: fitted above the peaks measured on the dense meshes
# of docs/scale.md (docs/results.md), the editor's included.
_BIND_BYTES = 150 * 2**20
_BIND_BYTES_PER_VERTEX = 200
_BIND_BYTES_PER_TRIANGLE = 100
_BIND_BYTES_PER_KEYPOINT_VERTEX = 24  # the (V, K) basis in float64 and its corrected copy


def bind_memory(vertices: int, triangles: int, keypoints: int) -> int:
    """Bytes that binding a mesh of ``vertices`` and ``triangles`` to ``keypoints`` holds at its peak (an estimate
    from measurements, docs/scale.md)."""
    return int(_BIND_BYTES + vertices * (_BIND_BYTES_PER_VERTEX + keypoints * _BIND_BYTES_PER_KEYPOINT_VERTEX)
               + triangles * _BIND_BYTES_PER_TRIANGLE)


def available_memory() -> int | None:
    """Bytes of memory this process can still use (Linux: MemAvailable, capped by a cgroup limit and by a limit on
    the process's address space, ``ulimit -v``, less what it maps already), or None when the system does not say."""
    available = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if available is None:
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return None
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit = Path(limit_file).read_text().strip()
            usage = int(Path(usage_file).read_text().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < 1 << 60:
            available = min(available, int(limit) - usage)
        break
    mapped = _address_space_left()
    return available if mapped is None else min(available, mapped)


def _address_space_left() -> int | None:
    """Bytes the process may still map under its address-space limit (``RLIMIT_AS``, as ``ulimit -v`` and some
    batch schedulers set it), or None without a limit."""
    try:
        import resource

        limit = resource.getrlimit(resource.RLIMIT_AS)[0]
        if limit == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmSize:"):
                    return limit - int(line.split()[1]) * 1024
    except (ImportError, OSError, ValueError):
        pass
    return None


def check_bind_memory(vertices: int, triangles: int, keypoints: int) -> None:
    """Raise :class:`~kpd.errors.InputError` naming the mesh's size and the memory it needs when binding it would
    not fit in the memory that is available (rather than being killed by the system midway)."""
    need = bind_memory(vertices, triangles, keypoints)
    have = available_memory()
    if have is not None and need > have:
        left = _address_space_left()
        limited = left is not None and left < need  # the process's own limit refuses it, whatever the machine has
        where = ("of address space is left under this process's limit (simplify the mesh, or raise the limit: "
                 "ulimit -v)" if limited else "of memory is available (simplify the mesh, or free memory)")
        raise InputError(f"a mesh of {vertices:,} vertices and {triangles:,} triangles needs about "
                         f"{_size(need)} to bind; {_size(max(have, 0))} {where}")


def _size(count: int) -> str:
    return f"{count / 2**30:.1f} GiB" if count >= 2**30 else f"{count / 2**20:.0f} MiB"
