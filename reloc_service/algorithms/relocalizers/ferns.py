"""Ferns relocalizer (thesis 3.2, 5.1.2, 5.2.2): map landmarks are the classes of a random-ferns
classifier trained on warped views of their observations; query keypoints are classified into
2D-3D correspondences and the pose comes from P3P LO-RANSAC, then the shared verification;
the verified poses are weighed against each other and the alternatives a repetition of the map
offers as a multi step weighs its own (:mod:`.ferns_weighing`).

Training is exact and incremental (:mod:`reloc_service.algorithms.ferns.models`): every trained
observation ``(keyframe, keypoint, landmark)`` is recorded, its samples are a function of the
keyframe image and ``(seed, keyframe id, warp)`` only, so a keyframe (or a landmark) leaving the
map subtracts exactly what it added.

Scale (thesis 5.2.2: 1730 classes already strain one model): at most ``max_classes`` classes
per model, either the most observed landmarks in one model (``partition = "select"``) or one
model per region of the map (``"regions"``: k-means of keyframe positions). Classifying a query
against every model would multiply its cost by the number of regions, so a place prior picks
the regions first (``region_prior = "sbi"``): PTAM's small blurry images (the fast place finder,
one matrix-vector product over every keyframe) rank the keyframes, the landmarks trained from
the ``place_keyframes`` best-ranked ones vote for the regions whose models learned them (one
vote per keyframe, split in proportion, so a keyframe rich in landmarks does not outvote the
others), and the query is classified only against the ``max_regions`` regions with most votes
(a landmark is learned by one region, not always its keyframe's). The regions are tried in
the prior's order: the best region's correspondences alone, then pooled with the second's, ...
each attempt one RANSAC and the shared verification: most queries are verified by their best
region and never pay the others' classification. A region picked wrongly gives
correspondences that do not agree on a pose, hence no verified pose; then, with
``region_fallback``, the query is classified against every other region too (the cost of the
old exhaustive search, paid only by the queries the prior failed). A query's leaves and each
region's classes are computed once, whatever the number of attempts.

Threads. No lock: training, updates and load run behind the engine (under its write lock, or
on a fresh relocalizer built off-line and swapped in), never during a query; save runs beside
queries and, like them, only reads. Queries may run concurrently; they read the published
models (:class:`~reloc_service.algorithms.ferns.models.Published`, replaced whole after each update) and
write only the landmark lookup table of :meth:`FernsRelocalizer._landmark_points`: one tuple,
read and replaced whole, and every concurrent query pins the same map version, so racing
queries at most build the same table twice.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.errors import ConfigError, NotTrainedError
from ...core.features import SIFT_DETECTED, detect_sift
from ...core.frame import Frame, Keyframe
from ...core.map import KeyframeMap, MapState
from ...core.methods import MethodStep
from ...core.numeric import top_k
from ...core.plugins import make_conf
from ..ferns.classifier import FernClassifier
from ..ferns.fern_tests import FernTests
from ..ferns.keypoints import detect_keypoints, strongest_distinct
from ..ferns.models import FernModels, Published
from ..ferns.scorer import FernScorer
from ..ferns.training import prepare_image
from ..place.sbi import SmallBlurryImageFinder
from ..pose.base import PoseEstimate
from ..pose.map_consistency import prepare_map
from ..pose.pnp_conf import PnPConf
from .base import (
    Prior,
    Relocalizer,
    RelocResult,
    VerifyConf,
    refuses_the_query,
    register,
    result_from_estimate,
)
from .ferns_conf import FernsConf
from .ferns_files import MODEL_FILE, read_ferns, write_ferns
from .ferns_pose import classified_pose
from .ferns_regions import allowed_classes, near_keyframes, region_attempts
from .ferns_weighing import FernsWeighing, supported_p3p

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(eq=False)
class _QueryWork:
    """What one query computed (for one published model set) that a second attempt on
    more regions reuses: its (N, M) leaves and, per region, its keypoints' top classes and
    posteriors (with the same class mask: the prior is the query's)."""

    leaves: npt.NDArray[np.uint16] | None = None
    classified: dict[int, tuple[IntArray, npt.NDArray[np.float32]]] = dataclasses.field(
        default_factory=dict)


@register("ferns")
class FernsRelocalizer(Relocalizer):
    """Global relocalizer: random ferns recognise map landmarks, P3P finds the pose (thesis 3.2)."""

    Conf = FernsConf

    def __init__(self, kmap: KeyframeMap, conf: FernsConf | None = None, *,
                 verify_conf: VerifyConf | None = None, pnp_conf: PnPConf | None = None) -> None:
        super().__init__(kmap)
        self.conf = conf or FernsConf()
        self.verify_conf = verify_conf or VerifyConf()
        self.pnp_conf = pnp_conf or PnPConf()
        # Weighs the verified poses against a repetition's alternatives (:meth:`_solve`).
        self._weighing_pose = supported_p3p(self.conf.kind, self.pnp_conf)
        self._tests = FernTests(self.conf.fern_conf())
        self._points_cache: tuple[int, IntArray, Array] = (-1, np.zeros(0, np.int64),
                                                           np.zeros((0, 3)))
        # The place prior's own index of the keyframes (cheap: 40x30 floats per keyframe),
        # kept in step with the map by add_keyframe / remove_keyframe / train / load.
        self._places = SmallBlurryImageFinder(kmap, SmallBlurryImageFinder.Conf())
        self._models = FernModels(self.conf.models_conf(), self._tests)
        self._ever_trained = False

    @classmethod
    def from_options(cls, step: MethodStep, kmap: KeyframeMap,
                     options: Mapping[str, Mapping[str, Any]]) -> FernsRelocalizer:
        """``options["ferns"]`` -> :class:`FernsConf`, ``options["verify"]`` ->
        :class:`VerifyConf`; the RANSAC settings of ``options["p3p"]`` (those of
        :class:`PnPConf`) are shared with the P3P pose finder."""
        if step.relocalizer != "ferns":
            raise ConfigError(f"ferns relocalizer: expected method 'ferns', got {str(step)!r}")
        pnp_fields = {f.name for f in dataclasses.fields(PnPConf)}
        pnp_opts = {k: v for k, v in dict(options.get("p3p") or {}).items() if k in pnp_fields}
        return cls(kmap, make_conf(FernsConf, options.get("ferns"), owner="ferns"),
                   verify_conf=make_conf(VerifyConf, options.get("verify"), owner="verify"),
                   pnp_conf=make_conf(PnPConf, pnp_opts, owner="p3p"))

    # -- interface ---------------------------------------------------------------------------
    @property
    def method(self) -> str:
        return "ferns"

    @property
    def required_features(self) -> frozenset[str]:
        return frozenset({self.conf.kind})

    @property
    def reads_keyframe_images(self) -> bool:
        return True   # its training samples are warps of the keyframe images

    @property
    def trained(self) -> bool:
        return self.conf.online or self._ever_trained

    def add_keyframe(self, keyframe: Keyframe) -> None:
        """Train the observations the map gained (those of ``keyframe`` and any new ones on
        older keyframes) when ``online``; otherwise wait for :meth:`train`."""
        self._places.add_keyframe(keyframe)
        if self.conf.online:
            self.update()

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        """Subtract the samples of observations no longer in the map (when ``online``)."""
        self._places.remove_keyframe(keyframe)
        if self.conf.online:
            self.update()

    def train(self, *, progress: bool = False) -> None:
        """Rebuild every model from the current map: partition, then train all observations."""
        models = FernModels(self.conf.models_conf(), self._tests)
        self._places.train()
        models.train(self.map.snapshot(), show_progress=progress)
        self._models = models
        self._ever_trained = True
        if self.conf.competitors > 0:  # the map pool the repetition search reads, too
            self._weighing_pose.prepare_map(self.map.snapshot())
        elif self.pnp_conf.intrinsics_false_refusal > 0:
            prepare_map(self.map.snapshot(), self.conf.kind, self.pnp_conf)

    def update(self, *, show_progress: bool = False) -> None:
        """Bring the models in line with the current map (adds and removes exactly)."""
        self._models.update(self.map.snapshot(), show_progress=show_progress)

    @property
    def tests(self) -> FernTests:
        """The fern tests shared by every model."""
        return self._tests

    @property
    def scorers(self) -> tuple[FernScorer, ...]:
        """The published models (one per region), as queries see them."""
        return self._models.published.scorers

    @property
    def regions(self) -> tuple[frozenset[int], ...]:
        """The keyframe ids of each model's region (one region in "select" mode)."""
        return self._models.published.region_keyframes

    @property
    def classifiers(self) -> tuple[FernClassifier, ...]:
        """The trainable models, one per region (do not modify them directly)."""
        return self._models.classifiers

    @property
    def num_classes(self) -> int:
        """Landmarks trained, over all models."""
        return sum(s.num_classes for s in self._models.published.scorers)

    def model_nbytes(self) -> int:
        """Bytes held by the classifiers (sparse counts, classes, tests)."""
        return self._models.nbytes()

    def trained_observations(self) -> set[tuple[int, int, int]]:
        """Every trained ``(landmark id, keyframe id, keypoint index)``."""
        return self._models.trained_observations()

    # -- query -------------------------------------------------------------------------------
    def relocalize(self, query: Frame, *, prior: Prior | None = None, hypotheses: int = 1
                   ) -> RelocResult:
        """Pick the regions (place prior), classify the query's keypoints against their
        models, P3P LO-RANSAC on the correspondences, verify. Regions the prior ranked are
        tried in its order, each attempt pooling one more region's correspondences (the best
        region alone, then with the second, ...), until a pose is verified; with
        ``region_fallback``, a query verified in none of them is classified against every
        region. Each region classifies a query once (:class:`_QueryWork`)."""
        if prior is not None and prior.radius_m is None:
            prior = None  # a covariance alone restricts no region (tracking reads it)
        pub, work = self._models.published, _QueryWork()
        start = time.perf_counter()
        regions = self.choose_regions(query, prior=prior)
        place_seconds = time.perf_counter() - start
        spent: dict[str, float] = {}
        for attempt in self._attempts(regions, len(pub.scorers)):
            result = self._relocalize_in(query, attempt, pub, work, prior, hypotheses)
            for key, seconds in result.timings.items():  # the query paid every attempt
                spent[key] = spent.get(key, 0.0) + seconds
            if result.ok or refuses_the_query(result):
                break  # (the query's camera would meet every other region too)
        result.timings.update(spent)
        result.timings["place"] = place_seconds
        return result

    def _attempts(self, regions: tuple[int, ...], num_regions: int) -> list[tuple[int, ...]]:
        """The region sets :meth:`relocalize` tries in turn (:func:`.ferns_regions.region_attempts`)."""
        return region_attempts(regions, num_regions, self.conf.region_fallback)

    def choose_regions(self, query: Frame, *, prior: Prior | None = None) -> tuple[int, ...]:
        """Indices of the regions to classify ``query`` against, most voted first: every
        region when there are at most ``max_regions`` (or ``region_prior = "none"``), else the
        ``max_regions`` regions most voted for by the ``place_keyframes`` keyframes whose
        small blurry images are nearest the query's (only keyframes within the prior's radius
        count; module docstring); ties go to the lower region."""
        pub = self._models.published
        every = tuple(range(len(pub.scorers)))
        if self.conf.region_prior == "none" or len(every) <= self.conf.max_regions:
            return every
        near = None if prior is None else set(near_keyframes(self.map.snapshot(), prior))
        if near is not None and not near:
            return every  # relocalize_in says "no keyframe within the prior's radius"
        ranked = self._places.find_places(query, self.conf.place_keyframes, allowed=near)
        votes = np.zeros(len(every))
        for cand in ranked:
            votes += pub.landmark_regions.get(cand.keyframe_id, 0.0)
        if not votes.any():
            return every
        order = top_k(votes, self.conf.max_regions, keep=votes > 0)
        return tuple(int(r) for r in order)

    def relocalize_in(self, query: Frame, regions: Iterable[int], *, prior: Prior | None = None,
                      hypotheses: int = 1) -> RelocResult:
        """:meth:`relocalize` against the models of ``regions`` only (indices into
        :attr:`regions`)."""
        return self._relocalize_in(query, regions, self._models.published, _QueryWork(), prior,
                                   max(1, hypotheses))

    def _relocalize_in(self, query: Frame, regions: Iterable[int], pub: Published,
                       work: _QueryWork, prior: Prior | None, hypotheses: int) -> RelocResult:
        """:meth:`relocalize_in` on the published models ``pub``, reusing (and adding to) what
        ``work`` holds of this query: its leaves and the classes each region gave it."""
        if not self.trained:
            raise NotTrainedError("ferns relocalizer: call train() first (online training is off)")
        state = self.map.snapshot()
        timings: dict[str, float] = {}
        fail: dict[str, Any] = dict(method=self.method, map_version=state.version, timings=timings)
        picked = sorted({int(r) for r in regions})
        if any(not 0 <= r < len(pub.scorers) for r in picked):
            raise ValueError(f"ferns: regions must be in [0, {len(pub.scorers)}), got {picked}")
        if sum(pub.scorers[r].num_classes for r in picked) == 0:
            return RelocResult.failure(reason="no trained landmarks", **fail)
        allowed = allowed_classes(state, [pub.scorers[r] for r in picked], prior,
                                  self.conf.kind)
        if allowed is None:
            return RelocResult.failure(reason="no keyframe within the prior's radius", **fail)
        start = time.perf_counter()
        px = self._detect(query)
        timings["features"] = time.perf_counter() - start
        start = time.perf_counter()
        kp, lm, _ = self._classify(query, px, pub, picked, allowed, work)
        points, live = self._landmark_points(state, lm)
        kp, lm, points = kp[live], lm[live], points[live]
        timings["classify"] = time.perf_counter() - start
        return self._solve(query, px, kp, lm, points, state, max(1, hypotheses), timings)

    def _detect(self, query: Frame) -> Array:
        """(N, 2) query keypoints (distinct pixels), cached on the frame."""
        key = f"ferns:keypoints:{self.conf.detector}:{self.conf.max_query_keypoints}"
        if key in query.cache:
            return query.cache[key]
        if self.conf.detector == "sift" and self.conf.competitors > 0:
            # Detected with their descriptors, left on the frame: the weighing's SIFT
            # features are these (:func:`...core.features.capped`), not extracted again.
            detection = query.cache.get(SIFT_DETECTED)
            if detection is None:
                detection = query.cache[SIFT_DETECTED] = detect_sift(query.image)
            query.cache[key] = strongest_distinct(detection.keypoints,
                                                  self.conf.max_query_keypoints)
        else:
            query.cache[key] = detect_keypoints(query.image, self.conf.detector,
                                                self.conf.max_query_keypoints)
        return query.cache[key]

    def _classify(self, query: Frame, px: Array, pub: Published, regions: list[int],
                  allowed: list[npt.NDArray[np.bool_] | None], work: _QueryWork
                  ) -> tuple[IntArray, IntArray, npt.NDArray[np.float32]]:
        """Correspondences (keypoint index, landmark id, posterior), each keypoint's
        ``top_k`` classes over the models of ``regions`` with posterior >= ``min_posterior``.
        The leaves (they depend on the image only) and each region's classes are computed
        once per query: a fallback to every region classifies only the regions not yet
        tried."""
        empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
        if len(px) == 0:
            return empty
        labels, posts = [], []
        for r, mask in zip(regions, allowed, strict=True):
            scorer = pub.scorers[r]
            if scorer.num_classes == 0 or (mask is not None and not mask.any()):
                continue
            if r not in work.classified:
                work.classified[r] = scorer.classify(self._leaves(query, px, work),
                                                     top_k=self.conf.top_k, allowed=mask)
            labels.append(work.classified[r][0])
            posts.append(work.classified[r][1])
        if not labels:
            return empty
        lab, post = np.hstack(labels), np.hstack(posts)
        k = min(self.conf.top_k, lab.shape[1])
        order = top_k(post, k)
        lab, post = np.take_along_axis(lab, order, 1), np.take_along_axis(post, order, 1)
        kp = np.repeat(np.arange(len(px)), k)
        keep = post.ravel() >= max(self.conf.min_posterior, 1e-12)
        return kp[keep], lab.ravel()[keep], post.ravel()[keep]

    def _leaves(self, query: Frame, px: Array, work: _QueryWork) -> npt.NDArray[np.uint16]:
        """(N, M) leaves of the query keypoints ``px`` (once per query)."""
        if work.leaves is None:
            image = prepare_image(query.image, self.conf.smoothing_sigma)
            work.leaves = self._tests.leaves_at(image, px)
        return work.leaves

    def _landmark_points(self, state: MapState, landmark_ids: IntArray
                         ) -> tuple[Array, npt.NDArray[np.bool_]]:
        """(N, 3) world points of ``landmark_ids`` in ``state`` and the (N,) mask of those
        still in the map (a lookup table rebuilt once per map version)."""
        # One read and one store of a whole tuple: a racing query sees an old or a new table,
        # never half of one (module docstring).
        version, ids, points = self._points_cache
        if version != state.version:
            ids = state.landmarks.id_array()
            points = state.landmark_points(ids)
            self._points_cache = (state.version, ids, points)
        if len(ids) == 0:
            return np.zeros((len(landmark_ids), 3)), np.zeros(len(landmark_ids), bool)
        pos = np.clip(np.searchsorted(ids, landmark_ids), 0, len(ids) - 1)
        return points[pos], ids[pos] == landmark_ids

    def _solve(self, query: Frame, px: Array, kp: IntArray, lm: IntArray, points: Array,
               state: MapState, hypotheses: int, timings: dict[str, float]) -> RelocResult:
        """The answer, with up to ``hypotheses - 1`` other verified results: RANSAC, then
        again on the correspondences each verified pose leaves (``hypotheses`` in all, at
        least ``1 + competitors``); with ``competitors``, the verified poses and the
        alternatives a repetition of the map offers are weighed as a multi step weighs its
        own (:mod:`.ferns_weighing`), else the first verified pose answers."""
        results: list[RelocResult] = []
        estimates: list[PoseEstimate | None] = []
        remaining = np.arange(len(kp))
        for _ in range(max(hypotheses, 1 + self.conf.competitors)):
            start = time.perf_counter()
            est = classified_pose(query, px, kp[remaining], lm[remaining], points[remaining],
                                  state, self.pnp_conf, self.conf.kind)
            timings["solve"] = timings.get("solve", 0.0) + time.perf_counter() - start
            start = time.perf_counter()
            result = result_from_estimate(est[0] if est else None, self.verify_conf,
                                          method=self.method, map_version=state.version,
                                          timings=timings)
            timings["verify"] = timings.get("verify", 0.0) + time.perf_counter() - start
            results.append(result)
            if est is None or not result.ok:
                break
            estimates.append(est[0])
            # The next solve keeps these keypoints' other classes: a repeated landmark's twin
            # is the second class of the keypoints the first pose explained.
            remaining = np.delete(remaining, est[1])
        if self.conf.competitors == 0 or not estimates:
            best = results[0]
            best.hypotheses = [r for r in results[1:hypotheses] if r.ok]
            return best
        estimates += [None] * (len(results) - len(estimates))
        start = time.perf_counter()
        weighing = FernsWeighing(self.map, self._weighing_pose, self.verify_conf)
        best = weighing.answer(query, state, results, estimates, timings, hypotheses)
        timings["unique"] = time.perf_counter() - start
        return best

    # -- persistence -------------------------------------------------------------------------
    def defer_unchecked_intrinsics(self) -> None:
        self.verify_conf = dataclasses.replace(self.verify_conf,
                                               trust_unchecked_intrinsics=False)

    def save(self, directory: Path, *, centres: str = "float16") -> None:
        """Write the models' files (:mod:`.ferns_files`: counts, records, options, regions)."""
        arrays, models = self._models.to_files()
        write_ferns(directory, arrays, {"conf": dataclasses.asdict(self.conf),
                                        "ever_trained": self._ever_trained, **models})

    def load(self, directory: Path) -> bool:
        """Restore what :meth:`save` wrote; False (nothing changed) if there is none, if it was
        made with other options, or if its keyframes are not those of the map."""
        stored = read_ferns(directory, dataclasses.asdict(self.conf))
        if stored is None:
            return False
        arrays, meta = stored
        models = FernModels.from_files(self.conf.models_conf(), self._tests, self.map.snapshot(),
                                       arrays, meta, where=str(Path(directory) / MODEL_FILE))
        if models is None:
            return False
        self._places.train()
        self._models = models
        self._ever_trained = bool(meta.get("ever_trained", True))
        return True
