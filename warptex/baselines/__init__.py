"""Classic solid texture synthesis methods that warptex is compared against."""

from warptex.baselines import kopf

__all__ = ["kopf"]
