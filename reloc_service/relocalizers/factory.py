"""Build a relocalizer from a method string: ``"ferns"``, ``"<place>+<pose>"`` (the multi
relocalizer, e.g. ``"sbi+p3p"``) or a comma-separated fallback chain (``"bow+p3p,sbi+esm"``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..errors import ConfigError
from ..map import KeyframeMap

# Importing a plugin module runs its ``@register``: the explicit list of what the core offers
# (no scanning, no entry points). Tools add their own (``tools.eval.gt``) by importing them.
from ..place import bow, sbi  # noqa: F401
from ..pose import esm, fivept, none, p3p  # noqa: F401
from . import ferns, multi  # noqa: F401
from .base import RELOCALIZERS, Relocalizer
from .chain import ChainRelocalizer

Options = Mapping[str, Mapping[str, Any]]

#: The method the engine and the service use when none is named: bag-of-words retrieval
#: (rotation and exposure invariant) with P3P, and when it cannot verify, the small blurry
#: image (which still ranks heavily blurred queries) with P3P. One set of defaults for every
#: data set: see the README's results table.
DEFAULT_METHOD = "bow+p3p,sbi+p3p"


def create_relocalizer(spec: str, kmap: KeyframeMap, *, options: Options | None = None
                       ) -> Relocalizer:
    """A relocalizer for ``spec`` over ``kmap``; ``options`` maps plugin names (``"sbi"``,
    ``"p3p"``, ``"ferns"``, ``"multi"``, ``"verify"``, ...) to their option dicts. A comma
    makes a fallback chain of the steps it separates."""
    spec = spec.strip()
    if not spec:
        raise ConfigError("empty method; expected e.g. 'sbi+p3p', 'ferns' or 'bow+p3p,sbi+esm'")
    if "," in spec:
        steps = [step.strip() for step in spec.split(",")]
        if not all(steps):
            raise ConfigError(f"chain: empty step in {spec!r}; expected e.g. 'bow+p3p,sbi+esm'")
        return ChainRelocalizer(kmap, [create_relocalizer(s, kmap, options=options) for s in steps])
    kind = "multi" if "+" in spec else spec
    return RELOCALIZERS.lookup(kind).from_options(spec, kmap, options or {})


def list_methods() -> list[dict[str, Any]]:
    """Every selectable method with a one-line description and whether it is evaluation-only."""
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
