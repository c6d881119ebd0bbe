"""Build a relocalizer from a method string: ``"ferns"``, ``"<place>+<pose>"`` (the multi
relocalizer, e.g. ``"sbi+p3p"``) or a comma-separated fallback chain (``"bow+p3p,sbi+esm"``)."""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

from ..errors import ConfigError
from ..map import KeyframeMap
from .base import RELOCALIZERS, Relocalizer

#: Modules whose import registers plugins (explicit list: no scanning, no entry points).
PLUGIN_MODULES = (
    "reloc_service.place.sbi", "reloc_service.place.gt", "reloc_service.place.bow",
    "reloc_service.pose.none", "reloc_service.pose.esm", "reloc_service.pose.p3p",
    "reloc_service.pose.fivept",
    "reloc_service.relocalizers.multi", "reloc_service.relocalizers.chain",
    "reloc_service.relocalizers.ferns",
)

Options = Mapping[str, Mapping[str, Any]]

#: The method the engine and the service use when none is named: bag-of-words retrieval
#: (rotation and exposure invariant) with P3P, and when it cannot verify, the small blurry
#: image (which still ranks heavily blurred queries) with P3P. One set of defaults for every
#: data set: see the README's results table.
DEFAULT_METHOD = "bow+p3p,sbi+p3p"


def load_plugins() -> None:
    """Import every plugin module so its ``@register`` runs; missing ones are skipped."""
    for name in PLUGIN_MODULES:
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise


def create_relocalizer(spec: str, kmap: KeyframeMap, *, options: Options | None = None,
                       evaluation: bool = False) -> Relocalizer:
    """A relocalizer for ``spec`` over ``kmap``; ``options`` maps plugin names (``"sbi"``,
    ``"p3p"``, ``"ferns"``, ``"multi"``, ``"verify"``, ...) to their option dicts."""
    load_plugins()
    spec = spec.strip()
    if not spec:
        raise ConfigError("empty method; expected e.g. 'sbi+p3p', 'ferns' or 'bow+p3p,sbi+esm'")
    kind = "chain" if "," in spec else "multi" if "+" in spec else spec
    return RELOCALIZERS.lookup(kind).from_options(spec, kmap, options or {}, evaluation=evaluation)


def list_methods() -> list[dict[str, Any]]:
    """Every selectable method with a one-line description and whether it is evaluation-only."""
    load_plugins()
    from ..place.base import PLACE_FINDERS
    from ..pose.base import POSE_FINDERS

    methods = []
    for place_name, place_cls in sorted(PLACE_FINDERS.items()):
        for pose_name in sorted(POSE_FINDERS):
            methods.append({"method": f"{place_name}+{pose_name}",
                            "evaluation_only": bool(place_cls.evaluation_only),
                            "description": f"multi relocalizer: {place_name} place finder, "
                                           f"{pose_name} pose finder"})
    for name, cls in sorted(RELOCALIZERS.items()):
        if name in ("multi", "chain"):
            continue
        doc = (cls.__doc__ or "").strip().splitlines()
        methods.append({"method": name, "evaluation_only": False,
                        "description": doc[0] if doc else name})
    return methods
