"""Shared pieces of every profile model: strict sections and validated field types."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated, Any

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict

from ..geometry import rigid_problem


class Section(BaseModel):
    """A profile section: unknown keys are refused, so a typo is an error, not a silent default."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


def _check_rigid(value: list[list[float]]) -> list[list[float]]:
    problem = rigid_problem(value)
    if problem:
        raise ValueError(f"not a rigid transform: {problem}")
    return value


#: A 4x4 rigid transform written as four rows of four numbers (translation in mm).
RigidTransform = Annotated[list[list[float]], AfterValidator(_check_rigid)]

IDENTITY = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


#: What a profile's `problems()` yields: (location of the field, message) for each check across fields.
Findings = Iterator[tuple[tuple[str | int, ...], str]]


def matrix(value: Any) -> np.ndarray:
    """A profile's list-of-lists transform or matrix as a float64 array."""
    return np.asarray(value, dtype=np.float64)
