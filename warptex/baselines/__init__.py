"""Classic solid texture synthesis methods that warptex is compared against."""
