"""The map frame, owned: per odometry session, ``map_from_odom`` estimated from
relocalizations and every new one tested against it (Mahalanobis distance, chi-square gate).

A relocalization of an image gives ``map_from_cam`` (its covariance from the verification); the
odometry at the image's stamp gives ``odom_from_cam`` (the odometry's own covariance). Their
composition ``map_from_cam @ inv(odom_from_cam)`` is one sample of ``map_from_odom``. Both poses
carry right perturbations in the camera frame (``pose @ exp(xi)``, twist (rho, omega)); to first
order ``map_from_odom`` is then perturbed on the right by ``Ad(odom_from_cam) (xi_map -
xi_odom)``, so a sample's covariance is ``Ad (S_map + S_odom) Ad^T`` (the two independent).

Two estimates of the same transform differ by ``r = log(inv(a) @ b)`` with covariance
``S_a + S_b``; ``r^T (S_a + S_b)^-1 r`` is chi-square with 6 degrees of freedom when both are
right, so they agree when it is below the chi-square quantile of ``confidence``.

A session is one odometry frame between resets: it starts anew when the odometry's frame id
changes, when its time goes back, when it jumps faster than the vehicle can move, or when an
anchored session's relocalization disagrees. A new session is ``unanchored`` until
``anchor_samples`` consecutive, mutually agreeing samples fix its ``map_from_odom`` (their
information-weighted mean). The first session of an empty map defines the map frame: its
``map_from_odom`` is the identity, exactly, and stays so (the map is built in that frame).
While the VIO says it is lost, the state reads ``lost`` and samples are not used (its odometry
is not to be trusted then).
"""

from __future__ import annotations

import collections
import enum
import logging
import threading
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from ...core.distributions import chi2
from ...core.geometry import invert, pose_to_tum, rotation_angle, se3_adjoint, se3_exp, se3_log

log = logging.getLogger(__name__)

Array = npt.NDArray[np.float64]


class State(enum.StrEnum):
    """Whether keyframes may be added (only ``anchored``)."""

    ANCHORED = "anchored"
    UNANCHORED = "unanchored"
    LOST = "lost"


class Verdict(enum.StrEnum):
    """What one sample did."""

    AGREES = "agrees"            # anchored, and the sample agrees with the estimate
    ANCHORED = "anchored"        # the sample completed a run: the session is anchored now
    PENDING = "pending"          # unanchored: the sample joined (or restarted) the run
    DISAGREES = "disagrees"      # anchored, and it disagrees: a new session has begun
    IGNORED = "ignored"          # lost, or a sample of an earlier session


@dataclass(frozen=True)
class Sample:
    """An estimate of ``map_from_odom`` (4, 4) with its (6, 6) covariance (right perturbation,
    twist (rho, omega) in the odometry frame)."""

    map_from_odom: Array
    covariance: Array


def sample_of(map_from_cam: Array, covariance_map: Array, odom_from_cam: Array,
              covariance_odom: Array) -> Sample:
    """One ``map_from_odom`` sample from a relocalized camera pose and the odometry's pose of
    the same camera, each with its (6, 6) covariance (right perturbation in the camera frame)."""
    adjoint = se3_adjoint(odom_from_cam)
    covariance = adjoint @ (np.asarray(covariance_map) + np.asarray(covariance_odom)) @ adjoint.T
    return Sample(map_from_cam @ invert(odom_from_cam), 0.5 * (covariance + covariance.T))


def mahalanobis2(a: Sample, b: Sample) -> float:
    """Squared Mahalanobis distance between two estimates of the same transform (their
    covariances summed; a singular sum counts only the directions it spans, and a difference
    outside them is infinitely far)."""
    r = se3_log(invert(a.map_from_odom) @ b.map_from_odom)
    s = a.covariance + b.covariance
    solution, *_ = np.linalg.lstsq(s, r, rcond=None)
    if np.linalg.norm(s @ solution - r) > 1e-9 * max(1.0, float(np.linalg.norm(r))):
        return float("inf")
    return float(r @ solution)


def weighted_mean(samples: list[Sample]) -> Sample:
    """The information-weighted mean on SE(3) (Gauss-Newton about the first sample) and its
    covariance, the samples taken as independent."""
    information = [np.linalg.pinv(s.covariance, hermitian=True) for s in samples]
    total = np.sum(information, axis=0)
    covariance = np.linalg.pinv(total, hermitian=True)
    mean = samples[0].map_from_odom
    for _ in range(4):
        residual = sum((w @ se3_log(invert(mean) @ s.map_from_odom)
                        for w, s in zip(information, samples, strict=True)), np.zeros(6))
        step = covariance @ residual
        mean = mean @ se3_exp(step)
        if np.linalg.norm(step) < 1e-12:
            break
    return Sample(mean, 0.5 * (covariance + covariance.T))


def describe_difference(a: Sample, b: Sample) -> str:
    """'x.xx m, y.y deg' between two estimates of ``map_from_odom``."""
    delta = invert(a.map_from_odom) @ b.map_from_odom
    return (f"{np.linalg.norm(delta[:3, 3]):.2f} m, "
            f"{np.degrees(rotation_angle(delta[:3, :3])):.1f} deg")


@dataclass(frozen=True)
class MapFrameConf:
    """How sure an agreement must be, how many samples anchor a session, and the fastest the
    vehicle moves (an odometry faster than that has jumped; 0: not checked)."""

    anchor_samples: int = 3
    confidence: float = 0.999
    max_speed_m_s: float = 20.0
    max_turn_rate_deg_s: float = 720.0

    @property
    def gate(self) -> float:
        """The chi-square quantile (6 degrees of freedom) two agreeing estimates stay below."""
        return float(chi2.ppf(self.confidence, 6))


@dataclass
class _Odometry:
    frame_id: str
    stamp: float
    odom_from_body: Array


@dataclass
class MapFrame:
    """``map_from_odom`` of the current odometry session and its state (see module
    docstring). Thread-safe: the bridge's worker feeds odometry, relocalize workers samples."""

    conf: MapFrameConf = field(default_factory=MapFrameConf)
    #: The map was empty: the first session defines the map frame (identity).
    defines_map: bool = False

    def __post_init__(self) -> None:
        self._lock = threading.Lock()
        self.session = 0
        #: Counts the odometry's resets only: a sample is of the current odometry when its
        #: epoch is this one (a session begun by a disagreement keeps the odometry it had).
        self.epoch = 0
        self.defining = False
        self.estimate: Sample | None = None
        self.lost = False
        self.odom_frame_id = ""
        self.counts: collections.Counter[str] = collections.Counter()
        self.last_event = "no odometry yet"
        self._run: list[Sample] = []
        self._window: collections.deque[Sample] = collections.deque(
            maxlen=self.conf.anchor_samples)
        self._last: _Odometry | None = None

    # -- reading -------------------------------------------------------------------------------
    @property
    def state(self) -> State:
        if self.lost:
            return State.LOST
        return State.UNANCHORED if self.estimate is None else State.ANCHORED

    def current(self) -> tuple[int, Sample | None]:
        """(odometry epoch, estimate or None) read together."""
        with self._lock:
            return self.epoch, self.estimate

    def status(self) -> dict[str, str]:
        """State, ``map_from_odom`` (``tx ty tz qx qy qz qw``) and counts, as strings."""
        with self._lock:
            estimate = self.estimate
            out = {"state": self.state.value, "session": str(self.session),
                   "odom_frame_id": self.odom_frame_id,
                   "defines_map_frame": str(self.defining).lower(),
                   "anchor_run": f"{len(self._run)}/{self.conf.anchor_samples}",
                   "last_event": self.last_event}
            out["map_from_odom"] = ("" if estimate is None else
                                    " ".join(f"{v:.4f}" for v in pose_to_tum(estimate.map_from_odom)))
            out.update({k: str(v) for k, v in sorted(self.counts.items())})
        return out

    # -- odometry --------------------------------------------------------------------------------
    def on_odometry(self, frame_id: str, stamp: float, odom_from_body: Array) -> bool:
        """Follow the odometry; True when this message begins a new session (a reset)."""
        with self._lock:
            last, self._last = self._last, _Odometry(frame_id, stamp, odom_from_body)
            if last is None:
                self.odom_frame_id = frame_id
                if self.defines_map and self.session == 0:
                    self._define_map_frame()
                return False
            reason = self._reset_reason(last, frame_id, stamp, odom_from_body)
            if reason is None:
                return False
            self.odom_frame_id = frame_id
            self.epoch += 1
            self._new_session(f"odometry reset: {reason}")
            return True

    def _reset_reason(self, last: _Odometry, frame_id: str, stamp: float,
                      odom_from_body: Array) -> str | None:
        if frame_id != last.frame_id:
            return f"frame id changed from {last.frame_id!r} to {frame_id!r}"
        dt = stamp - last.stamp
        if dt < 0:
            return f"time went back by {-dt:.3f} s"
        if dt == 0:
            return None
        delta = invert(last.odom_from_body) @ odom_from_body
        metres = float(np.linalg.norm(delta[:3, 3]))
        degrees = float(np.degrees(rotation_angle(delta[:3, :3])))
        if self.conf.max_speed_m_s and metres > self.conf.max_speed_m_s * dt:
            return f"jumped {metres:.2f} m in {dt:.3f} s (faster than {self.conf.max_speed_m_s} m/s)"
        if self.conf.max_turn_rate_deg_s and degrees > self.conf.max_turn_rate_deg_s * dt:
            return (f"turned {degrees:.1f} deg in {dt:.3f} s (faster than "
                    f"{self.conf.max_turn_rate_deg_s} deg/s)")
        return None

    def set_lost(self, lost: bool) -> None:
        with self._lock:
            self.lost = lost

    # -- samples -------------------------------------------------------------------------------
    def add_sample(self, sample: Sample, epoch: int) -> Verdict:
        """Test ``sample`` (made with the odometry of ``epoch``) and update the state."""
        with self._lock:
            if epoch != self.epoch or self.lost:
                self.counts["samples_ignored"] += 1
                return Verdict.IGNORED
            self.counts["samples"] += 1
            if self.estimate is not None:
                return self._anchored_sample(sample)
            return self._unanchored_sample(sample)

    def _anchored_sample(self, sample: Sample) -> Verdict:
        assert self.estimate is not None
        d2 = mahalanobis2(self.estimate, sample)
        if d2 <= self.conf.gate:
            self.counts["samples_agreed"] += 1
            if not self.defining:   # the defining session's identity is the map frame itself
                self._window.append(sample)
                self.estimate = weighted_mean(list(self._window))
            return Verdict.AGREES
        self.counts["samples_disagreed"] += 1
        jump = describe_difference(self.estimate, sample)
        self._new_session(f"a relocalization disagrees with map_from_odom by {jump} "
                          f"(Mahalanobis^2 {d2:.1f} > {self.conf.gate:.1f}): VIO reset or drift")
        self._run = [sample]
        return Verdict.DISAGREES

    def _unanchored_sample(self, sample: Sample) -> Verdict:
        if self._run and mahalanobis2(weighted_mean(self._run), sample) > self.conf.gate:
            self.counts["anchor_runs_restarted"] += 1
            self._run = []
        self._run.append(sample)
        if len(self._run) < self.conf.anchor_samples:
            return Verdict.PENDING
        self.estimate = weighted_mean(self._run)
        self._window.clear()
        self._window.extend(self._run)
        self._run = []
        self.counts["anchored"] += 1
        self.last_event = (f"session {self.session} anchored from "
                           f"{self.conf.anchor_samples} agreeing relocalizations")
        log.warning("map frame: %s; keyframes resume", self.last_event)
        return Verdict.ANCHORED

    # -- sessions ------------------------------------------------------------------------------
    def _define_map_frame(self) -> None:
        self.defining = True
        self.estimate = Sample(np.eye(4), np.zeros((6, 6)))
        self.last_event = (f"the map frame is odometry frame {self.odom_frame_id!r} "
                           "(first session of an empty map)")
        log.info("map frame: %s", self.last_event)

    def _new_session(self, reason: str) -> None:
        self.session += 1
        self.defining = False
        self.estimate = None
        self._run = []
        self._window.clear()
        self.counts["resets"] += 1
        self.last_event = f"session {self.session} began: {reason}"
        log.warning("map frame: %s; mapping stops until re-anchored", self.last_event)
