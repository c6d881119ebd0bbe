"""A plane seen face on cannot check the query's intrinsics (the focal and the distance trade
off exactly): its last resort, trusting the calibration, holds only where the query claims the
map's own camera; a query claiming another camera is refused with that reason."""

from __future__ import annotations

import dataclasses

import pytest

from reloc_service.algorithms.relocalizers.factory import create_relocalizer
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.frame import Frame
from reloc_service.core.geometry import pose_error
from reloc_service.tools.synth.planar import PlanarScene, keyframe_grid, planar_scene, query_pose

CAMERA = PinholeCamera(width=320, height=240, fx=250.0, fy=250.0, cx=159.5, cy=119.5)


@pytest.fixture(scope="module")
def plane() -> PlanarScene:
    return planar_scene(keyframe_grid(3, 2), camera=CAMERA, max_features=1000)


def test_the_maps_own_camera_is_trusted_on_a_plane_seen_face_on(plane):
    gt = query_pose(1)
    result = create_relocalizer("sbi+p3p", plane.map).relocalize(Frame(plane.render(gt), CAMERA))
    assert result.ok
    assert pose_error(result.world_from_cam, gt)[0] < 0.01


@pytest.mark.parametrize("scale", [1.15, 1.3])
def test_another_camera_is_refused_on_a_plane_seen_face_on(plane, scale):
    """The same image claiming a focal ``scale`` times the map's: on one plane the pose
    absorbs it (the camera moved along its axis), so nothing in the data would refuse it and
    the answer would be off by the focal's share of the distance."""
    claimed = dataclasses.replace(CAMERA, fx=CAMERA.fx * scale, fy=CAMERA.fy * scale)
    result = create_relocalizer("sbi+p3p", plane.map).relocalize(
        Frame(plane.render(query_pose(1)), claimed))
    assert not result.ok
    assert "intrinsics unchecked" in result.reason  # each candidate group says it
    assert "not the map's calibration" in result.reason
