"""Replica cases."""
