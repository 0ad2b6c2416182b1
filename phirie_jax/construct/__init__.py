"""Coupled Scene Construction, object branch: candidates → registration → checks →
selection → assets (``run_objects``)."""

from phirie_jax.construct.objects import run_objects

__all__ = ["run_objects"]
