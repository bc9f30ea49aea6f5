"""kpd.io.images: the one PNG encoder, read back by Open3D and Pillow, and the completeness check."""

import numpy as np
import pytest
from PIL import Image

from kpd.errors import InputError, WriteError
from kpd.io.images import encode_png, read_png, verify_png, write_png


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_encode_png_round_trips_through_pillow(channels, tmp_path):
    image = np.random.default_rng(channels).integers(0, 256, size=(7, 5, channels), dtype=np.uint8)
    path = tmp_path / "a.png"
    path.write_bytes(encode_png(image))
    back = np.asarray(Image.open(path))
    np.testing.assert_array_equal(back.reshape(image.shape), image)
    verify_png(path)


def test_write_png_read_png_and_refusals(tmp_path):
    image = np.random.default_rng(0).integers(0, 256, size=(9, 11, 3), dtype=np.uint8)
    np.testing.assert_array_equal(read_png(write_png(tmp_path / "b.png", image)), image)
    with pytest.raises(InputError, match="uint8"):
        write_png(tmp_path / "c.png", image.astype(float))
    with pytest.raises(InputError, match="uint8"):
        encode_png(np.zeros((2, 2, 5), np.uint8))
    with pytest.raises(InputError, match="no such image"):
        read_png(tmp_path / "missing.png")
    cut = tmp_path / "cut.png"
    cut.write_bytes(encode_png(image)[:-8])
    with pytest.raises(WriteError, match="no end chunk"):
        verify_png(cut)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.png", "cut.png"]
