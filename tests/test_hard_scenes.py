"""The degraded presets (motion blur, exposure change, an occluder that carries a copy of a
poster hanging elsewhere) relocalized with the service's default method and default settings:
at least 80 % recalled within 5 cm / 5 deg and at most 1 % wrong poses. Slow: renders ~150
frames."""

import pytest

from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.tools.eval.evaluate import evaluate


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["room-hard", "desk-hard"])
def test_degraded_queries_mostly_relocalized_and_none_wrong(preset, tmp_path_factory):
    from reloc_service.tools.synth import render_dataset

    root = render_dataset(preset, tmp_path_factory.mktemp(preset), seed=0, workers=2,
                          progress=False)
    summary = evaluate(root, [DEFAULT_METHOD], progress=False).method(DEFAULT_METHOD).summary
    assert summary.recall["5cm_5deg"] >= 0.80, summary
    assert summary.wrong_rate <= 0.01, summary
