"""Pure learner maths and shared definitions for wfnn (no network, clock, threads or files)."""

__version__ = "0.1.0"
