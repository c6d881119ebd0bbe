"""What a pose predicts and the query confirms: the landmarks of the local map around a pose
hypothesis, projected into the query and found there by guided matching (:mod:`.guided`).

A pose is judged by the whole image, not only by the consensus that produced it: two
hypotheses for one query (a true pose and one explained by a repeated picture, a periodic
wall, an identical cabinet elsewhere) are compared by the query keypoints each explains
(:func:`~reloc_service.algorithms.relocalizers.uniqueness.compare`); keypoints both explain cancel, the
ones only one explains decide.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core import features as feature_lib
from ...core.cameras import Camera
from ...core.frame import Features, Frame
from ...core.map import MapState
from .base import Support
from .guided import GuidedConf, project_into, search_by_projection
from .landmark_pool import LandmarkPool

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def explained_keypoints(features: Features, camera: Camera, world_from_cam: Array,
                        state: MapState, kind: str, *, radius_px: float,
                        conf: GuidedConf | None = None) -> Support:
    """The query ``features`` (of ``kind``) that the local map around ``world_from_cam``
    explains: the ``kind`` landmarks of the ``conf.local_keyframes`` keyframes nearest to the
    pose (that look the same way, within ``conf.max_view_angle_deg``) projected into the
    query and matched within ``radius_px`` of their projection (:func:`search_by_projection`,
    whose descriptor tests keep chance pairings rare)."""
    conf = conf or GuidedConf()
    near = state.nearest_keyframes(world_from_cam, conf.local_keyframes, conf.max_view_angle_deg)
    if not near or len(features) == 0:
        return Support.empty()
    pool = LandmarkPool.gather([state.keyframes[k] for k in near], kind)
    if len(pool.landmark_ids) == 0:
        return Support.empty()
    _, visible = project_into(camera, world_from_cam, pool.points_world)
    q_idx, rows = search_by_projection(features, camera, world_from_cam, pool.descriptors,
                                       pool.points_world, radius_px, conf)
    order = np.argsort(q_idx, kind="stable")
    return Support(q_idx[order].astype(np.int64), pool.landmark_ids[rows[order]].astype(np.int64),
                   int(np.count_nonzero(visible)))


def query_support(query: Frame, world_from_cam: Array, state: MapState,
                  feature_conf: feature_lib.FeatureConf, *, radius_px: float,
                  conf: GuidedConf | None = None) -> Support:
    """:func:`explained_keypoints` of the query's features of ``feature_conf.kind``
    (extracted with ``feature_conf`` unless the query has them already)."""
    kind = feature_conf.kind
    feats = query.features_of(kind, lambda: feature_lib.extract(query.image, feature_conf))
    return explained_keypoints(feats, query.camera, world_from_cam, state, kind,
                               radius_px=radius_px, conf=conf)
