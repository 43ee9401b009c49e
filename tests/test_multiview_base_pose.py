"""The multiview base-pose sampler (thesis §3.5): aimed poses, noise bounds, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from shiftkit.envs.base_pose import BasePose, BasePoseSampler


def _sampler(**kw) -> BasePoseSampler:
    # a camera 0.6 m up on the base, tilted down towards a centre 0.83 m away (the mv-* layout)
    position = np.array([0.3, -0.05, 0.6])
    target = np.array([0.0, 0.5, 0.125])
    axis = target - position
    params = dict(
        centre=(0.4, -0.2, 0.125),
        camera_position=tuple(position),
        camera_axis=tuple(axis),
        distance=float(np.linalg.norm(axis)),
        yaw_range=(-0.6, 0.2),
    )
    return BasePoseSampler(**{**params, **kw})


def test_optical_axis_passes_within_noise_bound_of_centre_and_yaw_fills_range():
    sampler = _sampler()
    rng = np.random.default_rng(0)
    poses = [sampler.sample(rng) for _ in range(1000)]
    misses = np.array([sampler.axis_miss(p) for p in poses])
    assert misses.max() <= sampler.miss_bound()
    assert misses.max() > 0.01  # the noise does move the view
    yaws = np.array([p.yaw for p in poses])
    lo, hi = sampler.yaw_range
    assert yaws.min() >= lo - sampler.yaw_noise and yaws.max() <= hi + sampler.yaw_noise
    counts, _ = np.histogram(yaws, bins=8, range=(lo, hi))
    assert counts.min() > 80  # uniform: ~125 per bin, none empty
    assert yaws.min() < lo + 0.02 and yaws.max() > hi - 0.02


def test_noiseless_poses_aim_exactly_and_put_the_centre_at_the_aim_point():
    sampler = _sampler(xy_noise=0.0, yaw_noise=0.0)
    for yaw in np.linspace(-0.6, 0.2, 9):
        pose = sampler.solve(float(yaw))
        assert sampler.axis_miss(pose) < 1e-9
        assert np.allclose(pose.to_base(np.array(sampler.centre)), sampler.aim_point())
    centre = sampler.centre_pose()
    assert centre.yaw == pytest.approx(-0.2)


def test_same_generator_seed_same_poses_and_frames_round_trip():
    sampler = _sampler()
    a = [sampler.sample(np.random.default_rng(5)) for _ in range(3)]
    assert a[0] == a[1] == a[2]
    pose = BasePose(0.3, -0.4, 0.7)
    points = np.random.default_rng(1).normal(size=(4, 3))
    assert np.allclose(pose.to_base(pose.to_world(points)), points)
    assert BasePose.from_dict(pose.as_dict()) == pose


def test_inconsistent_camera_height_is_refused():
    with pytest.raises(ValueError, match="optical axis"):
        _sampler(distance=0.5)
