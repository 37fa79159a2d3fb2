"""The one config mechanism (avatar_motor/config.py) and the dataset's per-cache weights."""
import json

import numpy as np
import pytest
import torch

from avatar_motor import config
from avatar_motor.data.cache import MotionCache
from avatar_motor.data.dataset import SegmentConfig, SegmentDataset
from avatar_motor.train.adapt import AdaptConfig
from avatar_motor.train.trainer import TrainConfig


def test_file_then_sets_over_the_defaults(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"steps": 10, "segment": {"mirror": False}, "model": {"width": 64}}))
    cfg = config.load(TrainConfig, f, ["steps=20", "segment.weights={\"a\": 0.2}", "name=my model", "model.depth=2"])
    assert (cfg.steps, cfg.segment.mirror, cfg.segment.weights, cfg.name) == (20, False, {"a": 0.2}, "my model")
    assert (cfg.model.width, cfg.model.depth) == (64, 2) and cfg.batch == TrainConfig().batch
    with pytest.raises(ValueError, match=r"training config.segment: unknown fields \['mirrorr'\]"):
        TrainConfig.from_dict({"segment": {"mirrorr": True}})
    with pytest.raises(ValueError, match="NAME=VALUE"):
        config.load(AdaptConfig, None, ["steps"])
    with pytest.raises(ValueError, match="steps is not a nested config"):
        config.load(AdaptConfig, None, ["steps=3", "steps.x=1"])
    f.write_text("{")
    with pytest.raises(ValueError, match="not valid JSON"):
        config.load(TrainConfig, f)


def _cache(name: str, clips: int, frames: int) -> MotionCache:
    n = clips * frames
    q = np.zeros((n, 22, 4), np.float32)
    q[..., 0] = 1
    meta = {"name": name, "clips": [{"key": f"{name}_{k}.bvh", "labels": {}} for k in range(clips)]}
    return MotionCache(np.zeros((n, 3), np.float32), q, np.arange(clips) * frames, np.full(clips, frames), meta)


def test_a_cache_gets_its_share_of_the_windows():
    big, small = _cache("big", 40, 100), _cache("small", 2, 30)
    ds = SegmentDataset([big, small], SegmentConfig(split="all", weights={"small": 0.25}))
    g = torch.Generator().manual_seed(0)
    clips = torch.cat([ds.sample_indexed(512, g)[2] for _ in range(8)])
    share = np.mean(["small" in ds.clip_names[int(c)] for c in clips])
    assert abs(share - 0.25) < 0.03  # uniform would give 28 of 3,388 windows, 0.8 %
    assert SegmentDataset([big, small], SegmentConfig(split="all")).window_cdf is None
    # a clip of a cache by its file name: taken out of its cache's share
    ds = SegmentDataset([big, small], SegmentConfig(split="all", weights={"small": 0.2, "small/small_1": 0.1}))
    clips = torch.cat([ds.sample_indexed(512, g)[2] for _ in range(8)])
    names = [ds.clip_names[int(c)] for c in clips]
    assert abs(np.mean([n == "small_1.bvh" for n in names]) - 0.1) < 0.03
    assert abs(np.mean([n == "small_0.bvh" for n in names]) - 0.2) < 0.03
    with pytest.raises(ValueError, match="no window of this split"):
        SegmentDataset([big, small], SegmentConfig(split="all", weights={"small/kick": 0.1}))
    with pytest.raises(ValueError, match=r"names \['tiny'\], which the training data lacks"):
        SegmentDataset([big, small], SegmentConfig(split="all", weights={"tiny": 0.1}))
    with pytest.raises(ValueError, match="must sum to 1"):
        SegmentDataset([big, small], SegmentConfig(split="all", weights={"small": 0.5, "big": 0.2}))
    with pytest.raises(ValueError, match=r"shares in \(0, 1\]"):
        SegmentDataset([big, small], SegmentConfig(split="all", weights={"small": 0.0}))


def test_runtime_options_reach_nested_configs():
    """--runtime NAME=VALUE sets a runtime field, a dotted name a field of a nested config
    (physics.kinematic), with the field's type; a wrong name or type is refused naming the fields."""
    import argparse
    from avatar_motor.cli import _runtime_config

    def parse(*items):
        return _runtime_config(argparse.Namespace(runtime=list(items), steps=None, backend=None))

    cfg = parse("physics.kinematic=2", "physics.candidates=4", "smooth_sigma=0", "lock_yaw=false")
    assert cfg.physics.kinematic == 2.0 and cfg.physics.candidates == 4 and isinstance(cfg.physics.candidates, int)
    assert cfg.smooth_sigma == 0.0 and cfg.lock_yaw is False
    assert parse().physics.kinematic != 2.0  # each call starts from the defaults
    with pytest.raises(ValueError, match="physics fields .*kinematic"):
        parse("physics.kinematik=2")
    with pytest.raises(ValueError, match="runtime's fields .*physics"):
        parse("physics=2")
    with pytest.raises(ValueError, match="takes a int"):
        parse("physics.candidates=many")
    with pytest.raises(ValueError, match="runtime's fields"):
        parse("nothing.kinematic=2")
