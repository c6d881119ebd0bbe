"""Run the ``reloc`` command line with ORB keypoints moved to the centre of the full-image
pixels they were found in: an experiment on whether OpenCV's ORB coordinates carry a
level-dependent offset.

OpenCV's ORB reports a keypoint found at pixel ``x_l`` of pyramid level ``l`` (scale ``s =
1.2^l``) at ``x_l s``, while that level's pixel, resized from the full image with its pixel
centres aligned, covers the full image around ``x_l s + (s - 1) / 2`` (up to 1.3 px at level
7, the same in x and y). A query matched at another level than the map's keyframes (a blurred
or closer query) then carries a shift common to all its keypoints, which the pose absorbs and
its residuals cannot show. This script adds ``(s - 1) / 2`` to every ORB keypoint (map and
queries alike) and otherwise runs ``reloc`` unchanged:

    python scripts/orb_level_offset.py eval SET -m default --json OUT.json --no-progress

(``reloc eval`` in-process: the map is built with the moved keypoints too).
"""

from __future__ import annotations

import sys

import numpy as np

from reloc_service.core import features

_original = features._features_from_cv


def _centred(kind: str, keypoints: list, descriptors: np.ndarray | None) -> features.Features:
    """:func:`features._features_from_cv`, ORB keypoints moved by ``(s - 1) / 2`` pixels."""
    found = _original(kind, keypoints, descriptors)
    if kind != "orb" or len(found.keypoints_px) == 0:
        return found
    scale = features.ORB_SCALE_FACTOR ** found.levels.astype(np.float64)
    return features.Features.create(kind, found.keypoints_px + ((scale - 1.0) / 2.0)[:, None],
                                    found.descriptors, levels=found.levels, sizes=found.sizes,
                                    angles=found.angles)


if __name__ == "__main__":
    features._features_from_cv = _centred
    from reloc_service.cli.main import main
    sys.exit(main())
