"""Place finders: rank the map's keyframes by how likely the query was taken near them."""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Any, ClassVar

from ...core.features import FeatureConf
from ...core.frame import Frame, Keyframe
from ...core.map import KeyframeMap
from ...core.plugins import Registry, make_conf

PLACE_FINDERS: Registry[PlaceFinder] = Registry("place finder")
register = PLACE_FINDERS.register


@dataclass(frozen=True)
class PlaceCandidate:
    """A keyframe proposed for a query; ``score`` is higher for more similar (any scale)."""

    keyframe_id: int
    score: float


class PlaceFinder(abc.ABC):
    """Ranks map keyframes by appearance similarity to a query frame (thesis 4, figure 4.2).

    Not thread-safe: used behind the engine, which keeps ``add_keyframe``, ``remove_keyframe``
    and ``train`` apart from queries; ``find_places`` may run in several queries at once, so
    it must not change the finder's state (see :mod:`reloc_service.engine`)."""

    name: ClassVar[str]
    #: Needs ground truth: registered only by the evaluation tools (``tools.eval.gt``), and
    #: refused by the service's configuration even where those tools are loaded.
    evaluation_only: ClassVar[bool] = False
    #: Feature kinds keyframes must carry (an instance may set its own from its conf).
    required_features: frozenset[str] = frozenset()
    #: Whether it reads keyframe pixels (beyond features and small blurry images saved
    #: with the map): a map served with it keeps its keyframe images on disk.
    reads_keyframe_images: ClassVar[bool] = False

    @dataclass(frozen=True)
    class Conf:
        pass

    def __init__(self, kmap: KeyframeMap, conf: Any) -> None:
        self.map = kmap
        self.conf = conf

    @abc.abstractmethod
    def add_keyframe(self, keyframe: Keyframe) -> None:
        """Index ``keyframe`` (already in the map)."""

    @abc.abstractmethod
    def remove_keyframe(self, keyframe: Keyframe) -> None:
        """Forget ``keyframe`` (already removed from the map)."""

    def train(self) -> None:  # noqa: B027 (optional hook)
        """Rebuild whatever model needs the whole map (default: nothing to do)."""

    @property
    def trained(self) -> bool:
        return True

    def feature_confs(self) -> dict[str, FeatureConf]:
        """The query features :meth:`find_places` extracts, by kind, with the settings it
        extracts them with (so they can be extracted ahead, elsewhere, to the same
        result); default: none."""
        return {}

    @abc.abstractmethod
    def find_places(self, query: Frame, k: int, *, allowed: set[int] | None = None
                    ) -> list[PlaceCandidate]:
        """Up to ``k`` candidates, best first; ``[]`` on an empty map. ``allowed`` restricts
        the candidates to those keyframe ids (a prior pose with a radius)."""

    def state(self, *, centres: str = "float16") -> dict[str, Any] | None:
        """Trained model to persist with the map (msgpack-able), or None; ``centres``: how
        float cluster centres are stored ("float16" or "uint8")."""
        return None

    def load_state(self, state: dict[str, Any]) -> None:  # noqa: B027 (optional hook)
        """Restore what :meth:`state` returned."""


def create_place_finder(options: dict[str, Any], kmap: KeyframeMap) -> PlaceFinder:
    """``create_place_finder({"name": "sbi", **options}, kmap)``."""
    opts = dict(options)
    name = opts.pop("name", None)
    cls = PLACE_FINDERS.lookup(str(name))
    return cls(kmap, make_conf(cls.Conf, opts, owner=f"place finder {name}"))
