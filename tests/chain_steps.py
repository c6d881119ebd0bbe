"""Chain steps the intrinsics tests put in front of or behind each other (not a test module):
one that answers every query with a given estimate, one that refuses every query's
intrinsics with a given test, each leaving on the query what the multi relocalizer leaves."""

from __future__ import annotations

from reloc_service.algorithms.pose.intrinsics import IntrinsicsCheck
from reloc_service.algorithms.relocalizers.base import Relocalizer, RelocResult, RelocStatus
from reloc_service.algorithms.relocalizers.chain_hooks import ANSWERED
from reloc_service.algorithms.relocalizers.confirmation import REFUSED
from reloc_service.algorithms.relocalizers.multi import MultiRelocalizer
from reloc_service.core.features import FeatureConf
from reloc_service.core.map import KeyframeMap


class AnsweringStep(Relocalizer):
    """A step matching ``kind`` features that answers every query with ``estimate``'s pose
    and leaves the estimate for the chain, with the multi relocalizer's options ``conf``
    (None: a step without them, which the chain neither confirms nor compares)."""

    name = "answering"

    def __init__(self, kmap: KeyframeMap, estimate, kind: str = "sift",
                 conf: MultiRelocalizer.Conf | None = None) -> None:
        super().__init__(kmap)
        self.estimate, self.kind = estimate, kind
        self.conf = conf

    @property
    def method(self) -> str:
        return f"answering:{self.kind}"

    @property
    def required_features(self) -> frozenset[str]:
        return frozenset({self.kind})

    def feature_confs(self) -> dict[str, FeatureConf]:
        return {self.kind: FeatureConf(kind=self.kind)}

    def add_keyframe(self, keyframe) -> None:
        pass

    def remove_keyframe(self, keyframe) -> None:
        pass

    def relocalize(self, query, *, prior=None, hypotheses=1) -> RelocResult:
        query.cache[ANSWERED] = self.estimate
        return RelocResult(status=RelocStatus.OK, method=self.method,
                           world_from_cam=self.estimate.world_from_cam,
                           covariance=self.estimate.covariance, confidence=0.5)


class RefusingOrb(Relocalizer):
    """An ORB step refusing every query's intrinsics with ``check``, left on the query as
    the multi relocalizer leaves it."""

    name = "refusing"
    method = "refusing:orb"
    required_features = frozenset({"orb"})

    def __init__(self, kmap: KeyframeMap, check: IntrinsicsCheck) -> None:
        super().__init__(kmap)
        self.check = check

    def add_keyframe(self, keyframe) -> None:
        pass

    def remove_keyframe(self, keyframe) -> None:
        pass

    def relocalize(self, query, *, prior=None, hypotheses=1) -> RelocResult:
        query.cache[REFUSED] = self.check
        return RelocResult.failure(self.method, self.check.reason)
