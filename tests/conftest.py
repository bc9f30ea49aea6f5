"""Shared fixtures. Real-data tests read ../shared/data (or $KPD_DATA); they skip when it is absent, except under CI."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

REPO = Path(__file__).resolve().parents[1]

# Hypothesis's own timing checks (an example's deadline, input generation "too slow") fail a test for the speed of
# a shared machine, not for what kpd does: the house rule keeps time out of the tests' assertions.
settings.register_profile("kpd", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("kpd")


def _data_root() -> Path:
    return Path(os.environ.get("KPD_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session", autouse=True)
def _torch_compiler_cache(tmp_path_factory):
    """torch's exporter (``dynamo=True``) makes its compiler's cache folder, ``/tmp/torchinductor_<user>`` unless
    told otherwise: the tests keep it in their own temporary folder (their processes' children too)."""
    if "TORCHINDUCTOR_CACHE_DIR" in os.environ:
        yield
        return
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(tmp_path_factory.mktemp("torchinductor"))
    yield
    os.environ.pop("TORCHINDUCTOR_CACHE_DIR", None)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The real data folder; absence skips the test locally and fails it under CI=true."""
    root = _data_root()
    if not (root / "modelnet10").is_dir():
        message = f"real data not found at {root} (set KPD_DATA)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
    return root


@pytest.fixture(scope="session")
def sneaker(data_dir):
    """The real sneaker scan (a mesh)."""
    from kpd.io import read_mesh

    mesh = read_mesh(data_dir / "scans" / "sneaker.ply")
    return mesh


@pytest.fixture(scope="session")
def chair(data_dir):
    """ModelNet10 chair_0890 (test split)."""
    from kpd.io import read_mesh

    return read_mesh(data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply")


@pytest.fixture(scope="session")
def chair_file(data_dir) -> Path:
    """The path of ModelNet10 chair_0890 (test split)."""
    return data_dir / "modelnet10" / "chair" / "test" / "chair_0890.ply"


@pytest.fixture(scope="module")
def chair_model():
    """The shipped chair model."""
    from kpd.runtime import Model

    return Model.load("chair")


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> Path:
    """A torch-free toy bundle (``helpers.make_toy_bundle``)."""
    from helpers import make_toy_bundle

    return make_toy_bundle(tmp_path_factory.mktemp("bundles") / "toy.kpd")


@pytest.fixture(scope="module")
def banana(data_dir):
    """The YCB banana scan: a textured OBJ."""
    from kpd.io import read_mesh

    return read_mesh(data_dir / "scans/ycb/banana/textured_simple_reoriented.obj")


# --- annotated datasets (tests/test_annotations_*.py) ---


@pytest.fixture(scope="session")
def kpn_root(data_dir) -> Path:
    return data_dir / "keypointnet"


@pytest.fixture(scope="session")
def part_root(data_dir) -> Path:
    return data_dir / "shapenetpart_sample"


@pytest.fixture(scope="session")
def chairs(kpn_root):
    from kpd import annotations as ann

    return ann.KeypointNet(kpn_root, "chair")


@pytest.fixture(scope="session")
def chair_shapes(chairs, part_root):
    from kpd import annotations as ann

    shapes, skipped = ann.keypointnet_shapes(chairs, "all", geometry_dirs=[part_root])
    return {s.model_id: s for s in shapes}, skipped


@pytest.fixture(scope="session")
def part_shapes(part_root):
    from kpd import annotations as ann

    parts = ann.ShapeNetPart(part_root)
    return {name: ann.shapenetpart_shapes(parts, name)[0] for name in sorted(parts.categories)}
