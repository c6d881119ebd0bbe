"""Options of the ferns relocalizer (``options["ferns"]``): the classifier's shape, its
training warps, its scale (classes per model, regions) and its query (detector, classes per
keypoint), validated when made."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from ...core.errors import ConfigError
from ...core.features import FEATURE_KINDS
from ..ferns.fern_tests import FernConf
from ..ferns.models import ModelsConf
from ..ferns.training import WarpConf

QUERY_DETECTORS = ("sift", "fast")
PARTITIONS = ("select", "regions")
REGION_PRIORS = ("sbi", "none")


@dataclass(frozen=True)
class FernsConf:
    """Options of the ferns relocalizer (``options["ferns"]``).

    Classifier: ``num_ferns`` x ``num_tests`` tests in a ``patch_size`` patch (thesis: 100 x 12).
    Training: ``num_warps`` samples per observation (thesis: 100), warps as in
    :class:`~reloc_service.algorithms.ferns.training.WarpConf`; ``online`` trains each new keyframe as it
    arrives (else only :meth:`train` does); ``workers`` threads warp keyframes in parallel.
    Scale: ``max_classes`` per model, ``partition`` "select" or "regions" (:mod:`.ferns`'s docstring);
    with regions, ``region_prior`` "sbi" classifies a query against the ``max_regions`` regions
    whose keyframes its small blurry image resembles most (tried best first, one more each
    time until a pose is verified; then every region with ``region_fallback``), "none"
    against every region.
    Query: ``detector`` "sift" (DoG, like the landmarks' keypoints) or "fast", at most
    ``max_query_keypoints``; each keypoint gives its ``top_k`` classes with posterior at least
    ``min_posterior``. ``kind`` is the feature kind whose landmarks are learned.

    ``max_rotation_rad`` is +-0.6 rad (34 deg) by default, enough for the roll of a forward
    camera; a downward-looking camera that yaws needs pi. Full rotations cost recognition and
    memory: on the 2000-landmark benchmark the top-1 rate of a 15-degree rotated photo falls
    from 98% to 51% and the model grows from 85 to 116 MB. The "fast" detector finds corners
    a few pixels off the landmarks' DoG keypoints: many inliers but a reprojection RMS above
    the verification's 2.5 px on the test scene, so "sift" is the default.
    """

    num_ferns: int = 100
    num_tests: int = 12
    patch_size: int = 32
    regularization: float = 1.0
    num_warps: int = 100
    max_rotation_rad: float = 0.6
    min_scale: float = 0.6
    max_scale: float = 1.5
    affine: bool = True
    max_noise_sigma: float = 5.0
    max_blur_sigma: float = 1.0
    smoothing_sigma: float = 1.0
    online: bool = True
    workers: int = 2
    max_classes: int = 2000
    partition: str = "regions"
    region_prior: str = "sbi"
    max_regions: int = 2
    place_keyframes: int = 5
    region_fallback: bool = True
    kind: str = "sift"
    detector: str = "sift"
    max_query_keypoints: int = 1000
    top_k: int = 2
    min_posterior: float = 0.01
    seed: int = 0
    #: Solve again on the correspondences a verified pose leaves, up to this many times, and
    #: answer only the pose that explains the query significantly better than every other
    #: verified one and every alternative a repetition of the map offers, as a multi step
    #: weighs its own (:mod:`.ferns_weighing`, :mod:`.uniqueness`; a keypoint's second class
    #: is often a repeated landmark's twin). 0: the first verified pose answers.
    competitors: int = 2

    def __post_init__(self) -> None:
        self.fern_conf()
        self.warp_conf()
        if self.detector not in QUERY_DETECTORS:
            raise ConfigError(f"ferns: detector {self.detector!r} unknown; expected one of "
                              f"{QUERY_DETECTORS}")
        if self.kind not in FEATURE_KINDS:
            raise ConfigError(f"ferns: kind {self.kind!r} unknown; expected one of {FEATURE_KINDS}")
        if self.partition not in PARTITIONS:
            raise ConfigError(f"ferns: partition {self.partition!r} unknown; expected one of "
                              f"{PARTITIONS}")
        if self.region_prior not in REGION_PRIORS:
            raise ConfigError(f"ferns: region_prior {self.region_prior!r} unknown; expected one "
                              f"of {REGION_PRIORS}")
        if min(self.workers, self.max_classes, self.max_query_keypoints, self.top_k,
               self.max_regions, self.place_keyframes) < 1:
            raise ConfigError("ferns: workers, max_classes, max_query_keypoints, top_k, "
                              "max_regions and place_keyframes must be >= 1")
        if self.competitors < 0:
            raise ConfigError(f"ferns: competitors must be >= 0, got {self.competitors}")
        if not 0 <= self.min_posterior < 1:
            raise ConfigError(f"ferns: min_posterior must be in [0, 1), got {self.min_posterior}")

    def fern_conf(self) -> FernConf:
        """The classifier's shape: the :class:`FernConf` options of the same names."""
        return FernConf(**_shared_fields(self, FernConf))

    def models_conf(self) -> ModelsConf:
        """What :class:`~reloc_service.algorithms.ferns.models.FernModels` needs of these options."""
        return ModelsConf(kind=self.kind, partition=self.partition, max_classes=self.max_classes,
                          num_warps=self.num_warps, workers=self.workers, fern=self.fern_conf(),
                          warp=self.warp_conf(), seed=self.seed)

    def warp_conf(self) -> WarpConf:
        """The training warps: the :class:`WarpConf` options of the same names (these
        options repeat them flat, with a relocalizer's defaults), the real view always among
        the samples."""
        return WarpConf(include_identity=True, **_shared_fields(self, WarpConf))


def _shared_fields(conf: Any, target: Any) -> dict[str, Any]:
    """The values of the dataclass ``conf``'s fields that the dataclass ``target`` has too, by
    name: what ``target(**...)`` takes from ``conf``."""
    names = {f.name for f in dataclasses.fields(target)}
    return {f.name: getattr(conf, f.name) for f in dataclasses.fields(conf) if f.name in names}
