"""Pipeline stages: built-ins, the registry that also finds plugins, and the Pipeline."""

from __future__ import annotations

from .base import NotFittedError, Stage
from .contract import check_stage
from .pipeline import Pipeline
from .registry import create, describe, get

__all__ = ["Stage", "NotFittedError", "check_stage", "Pipeline", "create", "describe", "get"]
