"""Method strings (``"sbi+p3p:orb,bow+p3p"``): :class:`MethodSpec`, their one parser.

A method string is a fallback chain of steps separated by commas; a step is either a place
finder and a pose finder, ``<place>+<pose>``, with an optional feature kind for the pose
finder, ``<place>+<pose>:<features>`` (``"sbi+p3p"``, ``"sbi+p3p:orb"``), or one relocalizer
named alone (``"ferns"``). Spaces around the separators are dropped: ``str(spec)`` is the
canonical string, the name the service gives the method in its results.

The parser lives in the wire protocol because method strings travel on the wire (the
``method`` of a relocalize request, the served ``methods`` of a status reply, the ``method``
that answered) and both ends import the protocol: the service parses every method it builds
or serves here, and a client may compose or read methods with the same type. Only the syntax
is checked here; which place finders, pose finders, feature kinds and relocalizers exist is
the service's to say. Errors are ``ValueError``s saying what was expected; the service turns
them into its ``ConfigError`` (``reloc_service.core.methods.parse_method``).
"""

from __future__ import annotations

from dataclasses import dataclass

#: What a whole method string looks like, for error messages.
_EXAMPLES = "e.g. 'sbi+p3p', 'ferns' or 'bow+p3p,sbi+esm'"


def split_chain(text: str) -> tuple[str, ...]:
    """The steps of a method string, each stripped (``"bow+p3p, sbi+esm"`` ->
    ``("bow+p3p", "sbi+esm")``); ValueError when the method or one of its steps is empty."""
    text = text.strip()
    if not text:
        raise ValueError(f"empty method; expected {_EXAMPLES}")
    steps = tuple(step.strip() for step in text.split(","))
    if not all(steps):
        raise ValueError(f"chain: empty step in {text!r}; expected e.g. 'bow+p3p,sbi+esm'")
    return steps


@dataclass(frozen=True)
class MethodStep:
    """One step of a method: ``place`` and ``pose`` (with ``features``, a feature kind for the
    pose finder, or None), or ``relocalizer`` alone. Names are kept as written (the registries
    judge them); a step built directly must print as a string that parses back to it."""

    place: str | None = None
    pose: str | None = None
    features: str | None = None
    relocalizer: str | None = None

    def __post_init__(self) -> None:
        if self.relocalizer is None:
            shaped = self.place is not None and self.pose is not None
        else:
            shaped = self.place is None and self.pose is None and self.features is None
        names = [n for n in (self.place, self.pose, self.features, self.relocalizer)
                 if n is not None]
        if not shaped or not all(map(_is_name, names)) or ":" in (self.pose or ""):
            raise ValueError(f"method step: expected a place and a pose finder (features "
                             f"optional) or a relocalizer alone, each a name without ',' or "
                             f"'+' (the pose finder's without ':'), got {self!r}")

    @classmethod
    def parse(cls, text: str) -> MethodStep:
        """The step ``text`` (``"sbi+p3p:orb"``, ``"ferns"``) names; ValueError naming the
        expected forms when it has a ``+`` but not one non-empty name either side, or a
        ``:`` after the pose finder but not a name either side."""
        text = text.strip()
        if "+" not in text:
            if not text:
                raise ValueError("empty method step; expected e.g. 'sbi+p3p' or 'ferns'")
            return cls(relocalizer=text)
        parts = [p.strip() for p in text.split("+")]
        if len(parts) != 2 or not all(parts):
            raise ValueError(f"multi relocalizer: expected '<place>+<pose>' or "
                             f"'<place>+<pose>:<features>' (e.g. 'sbi+p3p', 'sbi+p3p:orb'), "
                             f"got {text!r}")
        place, pose_label = parts
        pose, sep, features = (s.strip() for s in pose_label.partition(":"))
        if sep and not (pose and features):
            raise ValueError(f"multi relocalizer: expected '<pose>:<features>' with a feature "
                             f"kind (e.g. 'p3p:orb'), got {pose_label!r}")
        return cls(place=place, pose=pose, features=features if sep else None)

    @property
    def pose_label(self) -> str | None:
        """The pose part as written in the method: ``"p3p"`` or ``"p3p:orb"`` (None for a
        relocalizer named alone)."""
        if self.pose is None:
            return None
        return self.pose if self.features is None else f"{self.pose}:{self.features}"

    def __str__(self) -> str:
        if self.relocalizer is not None:
            return self.relocalizer
        return f"{self.place}+{self.pose_label}"


@dataclass(frozen=True)
class MethodSpec:
    """A parsed method: its steps, tried in order until one verifies (one step: no chain)."""

    steps: tuple[MethodStep, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "steps", tuple(self.steps))
        if not self.steps or not all(isinstance(s, MethodStep) for s in self.steps):
            raise ValueError(f"method: expected one or more MethodSteps, got {self.steps!r}")

    @classmethod
    def parse(cls, text: str) -> MethodSpec:
        """The method ``text`` names (see the module docstring); ValueError saying what was
        expected when it is empty, has an empty step or a step of neither form."""
        return cls(tuple(MethodStep.parse(step) for step in split_chain(text)))

    def __str__(self) -> str:
        return ",".join(str(step) for step in self.steps)


def _is_name(name: str) -> bool:
    """Whether ``name`` prints into a method string that parses back to it."""
    return bool(name) and name == name.strip() and "," not in name and "+" not in name
