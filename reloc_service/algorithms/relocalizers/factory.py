"""Build a relocalizer from a method (a string, parsed once into a
:class:`~reloc_service.core.methods.MethodSpec`): ``"ferns"``, ``"<place>+<pose>"`` (the multi
relocalizer, e.g. ``"sbi+p3p"``), ``"<place>+<pose>:<features>"`` (the same on the named
features, e.g. ``"sbi+p3p:orb"``: 500 ORB features per query, whatever ``options["p3p"]`` says
about features) or a comma-separated fallback chain of those (``"sbi+p3p:orb,bow+p3p"``).

Method strings without a ``:`` mean what they always meant (``"sbi+p3p"`` is SIFT unless
``options["p3p"]["kind"]`` says otherwise); ``options["p3p:orb"]`` configures the ORB variant
over ``options["p3p"]``. The same strings name methods in ``reloc eval -m``, the service's
``service.methods`` and the engine's saved models (``models/sbi+p3p_orb,bow+p3p,sbi+p3p``:
``storage.model_dir_name`` turns the ``:`` into ``_``; a chain's steps save into
``0_sbi_p3p_orb``, ``1_bow_p3p``, ...)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from ...core.map import KeyframeMap
from ...core.methods import MethodSpec, MethodStep, parse_method

# Importing a plugin module runs its ``@register``: the explicit list of what the core offers
# (no scanning, no entry points). Tools add their own (``tools.eval.gt``) by importing them.
from ..place import bow, sbi  # noqa: F401
from ..pose import esm, fivept, none, p3p  # noqa: F401
from ..pose.base import PoseFinder
from . import ferns, multi, tracking  # noqa: F401
from .base import RELOCALIZERS, Relocalizer
from .chain import ChainRelocalizer
from .multi import STEP_FEATURES

Options = Mapping[str, Mapping[str, Any]]

#: The method the engine and the service use when none is named: the fast path first (the
#: small blurry image, P3P on 500 ORB features); where it cannot verify, SIFT of the query
#: reduced to half size (blur and distance remove the fine scales ORB's corners need, and the
#: coarse ones cost a quarter of full-size SIFT); only where that cannot verify either, the
#: full-size SIFT steps: bag-of-words retrieval (rotation and exposure invariant) with P3P,
#: then the small blurry image (which still ranks heavily blurred queries) with P3P. Maps
#: built for it carry ORB and SIFT landmarks. One set of defaults for every data set: see the
#: README's results table.
DEFAULT_METHOD = "sbi+p3p:orb,sbi+p3p:sift-half,bow+p3p,sbi+p3p"


def create_relocalizer(spec: str | MethodSpec, kmap: KeyframeMap, *,
                       options: Options | None = None) -> Relocalizer:
    """A relocalizer for ``spec`` (a method string, parsed here, or a parsed
    :class:`MethodSpec`) over ``kmap``; ``options`` maps plugin names (``"sbi"``, ``"p3p"``,
    ``"ferns"``, ``"multi"``, ``"verify"``, ...) to their option dicts. A method of several
    steps (comma-separated) makes a fallback chain of them."""
    steps = parse_method(spec).steps
    if len(steps) > 1:
        return ChainRelocalizer(kmap, [_create_step(step, kmap, options or {}) for step in steps])
    return _create_step(steps[0], kmap, options or {})


def create_tracker(kmap: KeyframeMap, *, options: Options | None = None) -> Relocalizer:
    """The tracking step (:mod:`.tracking`, ``options["track"]``, ``options["verify"]``)
    over ``kmap``: what the engine asks first when a query's prior carries a covariance."""
    return _create_step(MethodStep(relocalizer=tracking.TRACK), kmap, options or {})


def _create_step(step: MethodStep, kmap: KeyframeMap, options: Options) -> Relocalizer:
    """The relocalizer of one step: the multi relocalizer for ``<place>+<pose>``, else the
    relocalizer the step names."""
    kind = "multi" if step.relocalizer is None else step.relocalizer
    return RELOCALIZERS.lookup(kind).from_options(step, kmap, options)


def list_methods() -> list[dict[str, Any]]:
    """Every selectable method with a one-line description and whether it is evaluation-only."""
    from ..place.base import PLACE_FINDERS
    from ..pose.base import POSE_FINDERS

    methods = []
    for place_name, place_cls in sorted(PLACE_FINDERS.items()):
        for pose_name, pose_cls in sorted(POSE_FINDERS.items()):
            for features, kind in _feature_variants(pose_cls):
                step = MethodStep(place=place_name, pose=pose_name, features=features)
                methods.append({"method": str(step),
                                "evaluation_only": bool(place_cls.evaluation_only),
                                "description": f"multi relocalizer: {place_name} place finder, "
                                               f"{pose_name} pose finder{kind}"})
    methods.append({"method": DEFAULT_METHOD, "evaluation_only": False,
                    "description": "the default (engine and service): a fallback chain, "
                                   "each step only where the ones before cannot verify"})
    for name, cls in sorted(RELOCALIZERS.items()):
        if name in ("multi", "chain"):
            continue
        doc = (cls.__doc__ or "").strip().splitlines()
        methods.append({"method": name, "evaluation_only": False,
                        "description": doc[0] if doc else name})
    return methods


def _feature_variants(pose_cls: type[PoseFinder]) -> list[tuple[str | None, str]]:
    """(feature kind of the method step, description suffix) of a pose finder: None for the
    plain name, plus one per feature kind when its configuration has a ``kind``."""
    fields = {f.name for f in dataclasses.fields(pose_cls.Conf)}
    variants: list[tuple[str | None, str]] = [(None, "")]
    if "kind" in fields:
        variants += [(kind, f" on {conf['max_features']} {conf['kind'].upper()} features"
                      + (f" of the image reduced to {conf['query_scale']:g} of its size"
                         if "query_scale" in conf else ""))
                     for kind, conf in sorted(STEP_FEATURES.items())
                     if set(conf) - {"first_pool_keyframes"} <= fields]
    return variants
