"""Relocalizers: the multi (place finder + pose finder), ferns and fallback-chain families."""

from .base import Prior, Relocalizer, RelocResult, RelocStatus, VerifyConf, verify
from .factory import create_relocalizer, list_methods

__all__ = ["Prior", "RelocResult", "RelocStatus", "Relocalizer", "VerifyConf",
           "create_relocalizer", "list_methods", "verify"]
