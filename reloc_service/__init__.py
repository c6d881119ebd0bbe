"""reloc: fast vision-based 6-DoF relocalization for MAVs (keyframe maps, multi and ferns relocalizers)."""

__version__ = "0.1.0"
