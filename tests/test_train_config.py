"""kpd.train.config: the recipe checks every value and round-trips; the device is resolved or refused clearly."""

from __future__ import annotations

import pytest
import torch

from kpd.errors import InputError
from kpd.train.config import TrainConfig, resolve_device


def test_defaults_are_the_authors_and_round_trip():
    config = TrainConfig()
    assert (config.alpha_kpt, config.wc_lr, config.warmup, config.inf_reg, config.clamp) == (2.0, 1e-2, 200, "code",
                                                                                          True)
    config.check()
    changed = TrainConfig(keypoints=8, inf_reg="paper", alpha_inf=1e-6, paper_m=True)
    assert TrainConfig.from_dict({**changed.to_dict(), "unknown": 1}) == changed


@pytest.mark.parametrize("change, match", [
    ({"keypoints": 0}, "keypoints must be at least 1"),
    ({"batch": 0}, "batch must be at least 1"),
    ({"warmup": -1}, "warmup and val_pairs"),
    ({"inf_reg": "l2"}, "inf_reg must be"),
    ({"keypoint_source": "random"}, "keypoint_source must be"),
    ({"lr": float("nan")}, "lr must be a finite number"),
    ({"alpha_inf": -1.0}, "alpha_inf must be a finite number"),
])
def test_check_refuses_each_bad_value(change, match):
    with pytest.raises(InputError, match=match):
        TrainConfig(**change).check()


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(InputError, match="unknown device 'tpu7'"):
        resolve_device("tpu7")
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="CUDA is not available"):
            resolve_device("cuda:0")
