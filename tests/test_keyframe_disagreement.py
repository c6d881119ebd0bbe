"""The keyframe pose uncertainty a map measures of itself
(:mod:`reloc_service.algorithms.pose.keyframe_disagreement`): about zero for exact poses,
the error put into them where they are off, and the engine's default pose covariance."""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

import numpy as np
import pytest

from reloc_service.algorithms.pose.keyframe_disagreement import (
    CHI2_3_MEDIAN,
    keyframe_pose_sigma,
)
from reloc_service.core.errors import ConfigError
from reloc_service.core.geometry import se3_exp
from reloc_service.core.map import MapState
from reloc_service.core.mapping import MappingConf
from reloc_service.engine import Engine, EngineConf


def perturbed(state: MapState, position_m: float, rotation_rad: float, seed: int) -> MapState:
    """``state`` with each keyframe's pose put off by a twist of random directions whose
    position and rotation parts have the lengths of an isotropic error of ``position_m`` and
    ``rotation_rad`` per axis at the median (``sqrt(CHI2_3_MEDIAN)`` sigmas), its
    landmarks left where the exact poses placed them."""
    rng = np.random.default_rng(seed)
    scale = np.sqrt(CHI2_3_MEDIAN)
    keyframes = {}
    for kf_id, keyframe in state.keyframes.items():
        rho, omega = rng.normal(size=3), rng.normal(size=3)
        twist = np.concatenate([rho / np.linalg.norm(rho) * position_m * scale,
                                omega / np.linalg.norm(omega) * rotation_rad * scale])
        keyframes[kf_id] = dataclasses.replace(
            keyframe, world_from_cam=keyframe.world_from_cam @ se3_exp(twist))
    return dataclasses.replace(state, keyframes=MappingProxyType(keyframes))


def test_exact_keyframes_measure_about_zero(synthetic_map):
    measured = keyframe_pose_sigma(synthetic_map)
    assert measured is not None and measured.keyframes == 6
    assert measured.position_m < 0.003
    assert measured.rotation_deg < 0.05


def test_keyframes_put_off_measure_the_error_put_into_them(synthetic_map):
    measured = keyframe_pose_sigma(perturbed(synthetic_map, 0.02, np.radians(0.5), seed=1))
    assert measured is not None
    assert 0.5 * 0.02 < measured.position_m < 2.0 * 0.02
    assert 0.5 * 0.5 < measured.rotation_deg < 2.0 * 0.5
    low, high = measured.position_interval_m
    assert low <= measured.position_m <= high


def test_the_keyframe_sigmas_are_auto_or_two_numbers():
    assert not MappingConf().keyframe_sigma_auto   # a VIO's stated noise by default
    assert MappingConf().default_pose_covariance()[0, 0] == pytest.approx(0.02 ** 2)
    auto = MappingConf(keyframe_position_sigma_m="auto", keyframe_rotation_sigma_deg="auto")
    assert auto.keyframe_sigma_auto and auto.default_pose_covariance() is None
    stated = MappingConf(keyframe_position_sigma_m=0.01, keyframe_rotation_sigma_deg=0.3)
    assert not stated.keyframe_sigma_auto
    assert stated.default_pose_covariance()[0, 0] == pytest.approx(1e-4)
    with pytest.raises(ConfigError, match="both 'auto' or both numbers"):
        MappingConf(keyframe_position_sigma_m="auto")
    with pytest.raises(ConfigError, match="'auto' or a finite number"):
        MappingConf(keyframe_position_sigma_m="fixed", keyframe_rotation_sigma_deg="fixed")


AUTO_SIGMAS = {"keyframe_position_sigma_m": "auto", "keyframe_rotation_sigma_deg": "auto"}


def _engine(scene, mapping: dict, pose_covariance=None) -> Engine:
    engine = Engine(EngineConf(methods=("sbi+p3p",), mapping=MappingConf(**mapping)))
    for i, (image, pose) in enumerate(zip(scene.keyframe_images, scene.keyframe_poses,
                                          strict=True)):
        engine.add_keyframe(i, image, scene.camera, pose, pose_covariance=pose_covariance)
    return engine


def test_the_engine_states_what_the_map_measured_and_a_stated_default_or_put_overrides_it(
        synthetic_scene, tmp_path):
    auto = _engine(synthetic_scene, AUTO_SIGMAS)
    assert auto.status()["keyframe_pose_sigma"] is None   # measured when trained
    auto.train()
    measured = auto.keyframe_pose_sigma
    assert measured is not None
    assert auto.status()["keyframe_pose_sigma"]["position_m"] == measured.position_m
    assert np.array_equal(auto.map.snapshot().pose_covariances([0])[0], measured.covariance())
    auto.save(tmp_path / "map")
    loaded = Engine.load(tmp_path / "map", auto.conf)
    assert loaded.keyframe_pose_sigma == measured

    stated = _engine(synthetic_scene, {"keyframe_position_sigma_m": 0.01,
                                       "keyframe_rotation_sigma_deg": 0.3})
    stated.train()
    assert stated.keyframe_pose_sigma is None
    assert stated.map.snapshot().pose_covariances([0])[0][0, 0] == pytest.approx(1e-4)

    put = _engine(synthetic_scene, AUTO_SIGMAS, pose_covariance=np.eye(6) * 1e-6)
    put.train()
    assert put.keyframe_pose_sigma is None   # every keyframe states its own
    assert put.map.snapshot().pose_covariances([0])[0][0, 0] == pytest.approx(1e-6)
