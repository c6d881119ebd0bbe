"""The default method's answers on a map whose triangulated landmarks seen by fewer than N
keyframes are left out of pose estimation (docs/covariance_tails.md, section 4).

    python scripts/confirmed_landmarks.py SET [--min-keyframes N] [reloc eval options...]
    RELOC="python scripts/confirmed_landmarks.py" scripts/eval_sets.sh OUT [SETS]

A landmark triangulated from two keyframes is never checked: a wrong correspondence that
satisfies the epipolar constraint (a look-alike along a short epipolar segment, as a camera
panning in place makes them) gives a point as precise-looking as a right one, and only a
third view can contradict it. This builds the map as ``reloc eval`` does, takes every
triangulated landmark (a depth sigma above zero: not lifted from a depth map) observed by
fewer than ``--min-keyframes`` keyframes off the keyframes' features (the pools the pose
finders match read them there), then trains and scores the queries as ``reloc eval`` does,
so its table compares with ``reloc eval SET -m default`` directly.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np


def _observers(state: Any) -> tuple[np.ndarray, np.ndarray]:
    """(L,) landmark ids referenced by any keyframe and (L,) how many keyframes reference
    each (once per keyframe, whatever its observations' feature kinds)."""
    per_keyframe = [np.unique(np.concatenate([f.landmark_ids[f.landmark_ids >= 0]
                                              for f in kf.features.values()] or [[]]))
                    for kf in state.keyframes.values()]
    if not per_keyframe:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.unique(np.concatenate(per_keyframe).astype(np.int64), return_counts=True)


def unconfirmed(state: Any, min_keyframes: int) -> np.ndarray:
    """Ids of the triangulated landmarks of ``state`` seen by fewer than ``min_keyframes``
    keyframes (landmarks lifted from a depth map, sigma 0, are measured, not matched)."""
    ids, counts = _observers(state)
    few = ids[counts < min_keyframes]
    return few[state.landmark_sigmas(few, 0.0) > 0.0]


def strip(engine: Any, landmark_ids: np.ndarray) -> None:
    """Take ``landmark_ids`` off every keyframe's features and publish the map so."""
    import dataclasses
    from types import MappingProxyType

    state = engine.map.snapshot()
    keyframes = {}
    for kf_id, kf in state.keyframes.items():
        for kind, feats in list(kf.features.items()):
            drop = np.isin(feats.landmark_ids, landmark_ids)
            if drop.any():
                ids, points = feats.landmark_ids.copy(), feats.points_world.copy()
                ids[drop], points[drop] = -1, np.nan
                kf = kf.with_features(kind, dataclasses.replace(feats, landmark_ids=ids,
                                                                points_world=points))
        keyframes[kf_id] = kf
    engine.map.replace_state(dataclasses.replace(
        state, keyframes=MappingProxyType(keyframes), version=state.version + 1))
    with engine._rw.write():
        engine._publish([])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--min-keyframes", type=int, default=3)
    args, rest = parser.parse_known_args()

    from reloc_service.cli.main import main as reloc_main
    from reloc_service.tools.eval import inprocess

    train = inprocess.InProcessBackend.train

    def stripped_then_train(self: Any, *a: Any, **k: Any) -> Any:
        state = self.engine.map.snapshot()
        few = unconfirmed(state, args.min_keyframes)
        print(f"left out: {len(few)} of {len(state.landmarks)} landmarks (triangulated, seen "
              f"by fewer than {args.min_keyframes} keyframes)", file=sys.stderr)
        strip(self.engine, few)
        return train(self, *a, **k)

    inprocess.InProcessBackend.train = stripped_then_train  # type: ignore[method-assign]
    method = [] if {"-m", "--method"} & set(rest) else ["-m", "default"]
    sys.exit(reloc_main(["eval", args.dataset, *method, *rest]))


if __name__ == "__main__":
    main()
