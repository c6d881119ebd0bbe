"""Fallback chains: first verified step wins, timings summed, every reason kept."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service import features as feature_lib
from reloc_service.cameras import PinholeCamera
from reloc_service.errors import ConfigError, NotTrainedError
from reloc_service.frame import Frame, Keyframe
from reloc_service.geometry import pose_error
from reloc_service.map import KeyframeMap
from reloc_service.relocalizers.base import Prior, Relocalizer, RelocResult
from reloc_service.relocalizers.chain import ChainRelocalizer
from reloc_service.relocalizers.factory import create_relocalizer
from reloc_service.relocalizers.multi import MultiRelocalizer
from reloc_service.tools.synth.planar import PlanarScene, keyframe_grid, planar_scene, query_pose

CAMERA = PinholeCamera(width=320, height=240, fx=250.0, fy=250.0, cx=159.5, cy=119.5)


@pytest.fixture(scope="module")
def scene() -> PlanarScene:
    return planar_scene(keyframe_grid(3, 2), camera=CAMERA, max_features=1000)


def test_factory_builds_a_chain_of_steps(scene):
    chain = create_relocalizer("sbi+p3p, sbi+none", scene.map, options={"p3p": {"kind": "orb"}})
    assert isinstance(chain, ChainRelocalizer)
    assert [s.method for s in chain.steps] == ["sbi+p3p", "sbi+none"]
    assert all(isinstance(s, MultiRelocalizer) for s in chain.steps)
    assert chain.method == "sbi+p3p,sbi+none"
    assert chain.required_features == {"orb"}
    with pytest.raises(ConfigError, match="empty step"):
        create_relocalizer("sbi+p3p,,sbi+none", scene.map)
    with pytest.raises(ConfigError, match="unknown place finder 'nope'"):
        create_relocalizer("sbi+p3p,nope+none", scene.map)


def test_first_step_answers(scene):
    gt = query_pose(0)
    result = create_relocalizer("sbi+p3p,sbi+none", scene.map).relocalize(
        Frame(scene.render(gt), CAMERA))
    assert result.ok and result.method == "sbi+p3p"
    assert pose_error(result.world_from_cam, gt)[0] < 0.01
    assert "pose" not in result.timings  # the second step never ran


def test_falls_back_and_sums_timings(scene):
    kmap = KeyframeMap()
    for kf in scene.map.snapshot().keyframes.values():  # keyframes without features: p3p fails
        kmap.add_keyframe(Keyframe(image=kf.image, camera=CAMERA, id=kf.id,
                                   world_from_cam=kf.world_from_cam))
    target = kmap.snapshot().keyframe(2)
    chain = create_relocalizer("sbi+p3p,sbi+none", kmap,
                               options={"multi": {"require_agreement": False}})
    result = chain.relocalize(Frame(target.image.copy(), CAMERA))
    assert result.ok and result.method == "sbi+none"
    assert np.array_equal(result.world_from_cam, target.world_from_cam)
    assert {"features", "match", "pose"} <= result.timings.keys()  # both steps' stages
    first = chain.steps[0].relocalize(Frame(target.image.copy(), CAMERA))
    assert not first.ok
    assert result.timings["place"] >= 0.0


def test_no_step_answers_gives_every_reason(scene):
    import cv2
    import skimage.data as data

    image = cv2.resize(cv2.cvtColor(data.chelsea(), cv2.COLOR_RGB2GRAY), CAMERA.size)
    result = create_relocalizer("sbi+p3p,sbi+none", scene.map).relocalize(Frame(image, CAMERA))
    assert not result.ok and result.method == "sbi+p3p,sbi+none"
    p3p_part, none_part = result.reason.split("; sbi+none: ", 1)
    assert p3p_part.startswith("sbi+p3p: ") and "too few inliers" in p3p_part
    assert "image alignment too weak" in none_part
    assert {"features", "match", "pose"} <= result.timings.keys()


def test_features_are_extracted_once_across_steps(scene, monkeypatch):
    calls = []
    real_extract = feature_lib.extract
    monkeypatch.setattr(feature_lib, "extract",
                        lambda *a, **k: calls.append(1) or real_extract(*a, **k))
    strict = create_relocalizer("sbi+p3p", scene.map,
                                options={"verify": {"min_inliers": 100_000}})
    chain = ChainRelocalizer(scene.map, [strict, create_relocalizer("sbi+p3p", scene.map)])
    gt = query_pose(1)
    result = chain.relocalize(Frame(scene.render(gt), CAMERA),
                              prior=Prior(world_from_cam=gt, radius_m=100.0))
    assert result.ok and pose_error(result.world_from_cam, gt)[0] < 0.01
    assert len(calls) == 1  # the second step reused the query's cached features
    assert result.timings["match"] > 0


class _Untrained(Relocalizer):
    name = "untrained"

    @property
    def method(self) -> str:
        return "untrained"

    @property
    def trained(self) -> bool:
        return False

    def add_keyframe(self, keyframe: Keyframe) -> None:
        self.added = keyframe.id

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        self.removed = keyframe.id

    def relocalize(self, query, *, prior=None, hypotheses=1) -> RelocResult:
        raise NotTrainedError("call train() first")


def test_untrained_step_is_skipped_and_calls_are_forwarded(scene):
    untrained = _Untrained(scene.map)
    multi = create_relocalizer("sbi+p3p", scene.map)
    chain = ChainRelocalizer(scene.map, [untrained, multi])
    assert not chain.trained
    gt = query_pose(2)
    result = chain.relocalize(Frame(scene.render(gt), CAMERA))
    assert result.ok and result.method == "sbi+p3p"
    alone = ChainRelocalizer(scene.map, [untrained]).relocalize(Frame(scene.render(gt), CAMERA))
    assert not alone.ok and "untrained: not trained" in alone.reason
    kf = scene.map.snapshot().keyframe(0)
    chain.add_keyframe(kf)
    chain.remove_keyframe(kf)
    multi.add_keyframe(kf)  # restore the shared place finder's index
    assert untrained.added == 0 and untrained.removed == 0
    with pytest.raises(ConfigError):
        ChainRelocalizer(scene.map, [])


def test_save_and_load_each_step(scene, tmp_path):
    chain = create_relocalizer("sbi+p3p,sbi+none", scene.map)
    chain.save(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0_sbi_p3p", "1_sbi_none"]
    assert chain.load(tmp_path) is False  # sbi has no trained model to restore
