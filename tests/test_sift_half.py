"""The ``:sift-half`` step: SIFT of the query reduced to half size, matched to the map's SIFT
landmarks, verified as every step."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.algorithms.relocalizers.factory import create_relocalizer, list_methods
from reloc_service.core.errors import ConfigError
from reloc_service.core.frame import Frame
from reloc_service.core.geometry import pose_error
from reloc_service.core.map import KeyframeMap
from reloc_service.core.mapping import MapBuilder, MappingConf


@pytest.fixture(scope="module")
def room_sift(synthetic_scene) -> KeyframeMap:
    """The synthetic room mapped with SIFT landmarks (as the default's SIFT steps use)."""
    kmap = KeyframeMap()
    builder = MapBuilder(kmap, MappingConf(feature_kinds=("sift",)))
    for i, (image, pose) in enumerate(zip(synthetic_scene.keyframe_images,
                                          synthetic_scene.keyframe_poses, strict=True)):
        builder.add_keyframe(i, image, synthetic_scene.camera, pose, timestamp=float(i))
    return kmap


def test_the_step_reads_its_features_from_the_half_size_image(room_sift):
    step = create_relocalizer("sbi+p3p:sift-half", room_sift)
    conf = step.pose.conf
    assert (conf.kind, conf.max_features, conf.query_scale) == ("sift", 1000, 0.5)
    assert conf.first_pool_keyframes == 1
    assert set(step.feature_confs()) == {"sift@0.5"}
    assert step.required_features == {"sift"}  # the map's SIFT landmarks
    # a pose finder that cannot reduce the query image does not take the suffix
    with pytest.raises(ConfigError, match="does not reduce the query image"):
        create_relocalizer("sbi+5pt:sift-half", room_sift)
    listed = {m["method"] for m in list_methods()}
    assert "sbi+p3p:sift-half" in listed and "sbi+5pt:sift-half" not in listed


def test_it_answers_and_leaves_full_size_sift_unextracted(synthetic_scene, room_sift):
    step = create_relocalizer("sbi+p3p:sift-half", room_sift)
    step.train()
    answered = 0
    for i in range(len(synthetic_scene.query_images)):
        query = Frame(synthetic_scene.query_images[i], synthetic_scene.camera)
        result = step.relocalize(query)
        assert set(query.features) == {"sift@0.5"}
        if result.ok:
            answered += 1
            # a reduced pixel is two of the image's: still well within the 5 cm recall
            assert pose_error(result.world_from_cam, synthetic_scene.query_poses[i])[0] < 0.05
    assert answered >= len(synthetic_scene.query_images) // 2


def test_keypoints_are_weighted_as_located_to_a_reduced_pixel(room_sift):
    step = create_relocalizer("sbi+p3p:sift-half", room_sift)
    full = create_relocalizer("sbi+p3p", room_sift)
    idx = np.arange(3)
    sift = next(iter(room_sift.snapshot().keyframes.values())).features["sift"]
    assert np.array_equal(step.pose._scales(sift, idx), np.full(3, 2.0))
    assert full.pose._scales(sift, idx) is None


def test_a_chain_leaves_the_half_size_steps_refusal_to_full_size_sift(room_sift):
    """An intrinsics refusal rests on the keypoints' localisation: full-size SIFT after the
    half-size step matches other keypoints, so the chain asks it; two full-size SIFT steps
    would meet the same correspondences."""
    chain = create_relocalizer("sbi+p3p:sift-half,bow+p3p,sbi+p3p", room_sift)
    assert chain._other_features_after(0)
    assert not chain._other_features_after(1)
