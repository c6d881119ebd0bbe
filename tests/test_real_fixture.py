"""Real imagery shipped with the tests (TUM fr1_rpy, CC BY 4.0): a handheld map of keyframes a
few centimetres apart, relocalized with the default settings."""

from pathlib import Path

import numpy as np
import pytest

from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.tools.eval.evaluate import evaluate

FIXTURE = Path(__file__).parent / "data" / "tum_fr1_rpy_mini"


@pytest.fixture(scope="module")
def result():
    return evaluate(FIXTURE, ["sbi+p3p", "bow+p3p", DEFAULT_METHOD], progress=False)


def test_short_baseline_keyframes_make_landmarks(result):
    per_keyframe = np.asarray(result.map.landmarks_per_keyframe)
    assert len(per_keyframe) == 9
    assert np.median(per_keyframe) >= 100, per_keyframe


@pytest.mark.parametrize("method", ["sbi+p3p", "bow+p3p", DEFAULT_METHOD])
def test_every_query_relocalized_and_none_wrong(result, method):
    summary = result.method(method).summary
    # The benchmark's ground truth is good to 1-3 cm and 0.3-0.7 deg on this fast-rotation
    # sequence (interpolated to the image timestamps): score at 25 cm / 10 deg.
    assert summary.recall["25cm_10deg"] == 1.0, [q.reason for q in result.method(method).queries]
    assert summary.wrong_rate == 0.0


def test_queries_claiming_a_focal_30_percent_long_are_not_answered():
    from reloc_service.algorithms.pose.intrinsics import REFUSAL
    from reloc_service.tools.eval.query_camera import QueryCamera

    stale = evaluate(FIXTURE, [DEFAULT_METHOD], progress=False,
                     query_camera=QueryCamera(focal_scale=1.3))
    assert stale.dataset["query_camera"] == {"focal_scale": 1.3, "k1": None}
    queries = stale.method(DEFAULT_METHOD).queries
    assert not any(q.returned for q in queries)
    assert sum(q.reason.startswith(REFUSAL) for q in queries) >= 2, [q.reason for q in queries]
