"""The engine shared by ``reloc eval`` and the service (:mod:`.engine`: the keyframe map, its
builder and the live relocalizers behind one lock discipline) and what it is made with
(:mod:`.conf`)."""

from .conf import EngineConf
from .engine import Engine, MappingConf, TriangulationConf

__all__ = ["Engine", "EngineConf", "MappingConf", "TriangulationConf"]
