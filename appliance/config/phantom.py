"""The box phantom: its printed ArUco markers and where each sits on the box."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from .base import IDENTITY, Findings, RigidTransform, Section, matrix

#: OpenCV's predefined ArUco dictionaries and how many markers each holds.
ARUCO_DICTIONARIES = {
    "DICT_4X4_50": 50, "DICT_4X4_100": 100, "DICT_4X4_250": 250, "DICT_4X4_1000": 1000,
    "DICT_5X5_50": 50, "DICT_5X5_100": 100, "DICT_5X5_250": 250, "DICT_5X5_1000": 1000,
    "DICT_6X6_50": 50, "DICT_6X6_100": 100, "DICT_6X6_250": 250, "DICT_6X6_1000": 1000,
    "DICT_7X7_50": 50, "DICT_7X7_100": 100, "DICT_7X7_250": 250, "DICT_7X7_1000": 1000,
    "DICT_ARUCO_ORIGINAL": 1024,
}


class Box(Section):
    length_mm: float = Field(gt=0, le=3000, description="Along the box's long axis, phantom x (mm).")
    width_mm: float = Field(gt=0, le=3000, description="Along phantom y (mm).")
    height_mm: float = Field(gt=0, le=3000, description="Along phantom z (mm).")


class Marker(Section):
    id: int = Field(ge=0, description="ArUco id printed on the marker.")
    T_phantom_from_marker: RigidTransform = Field(
        IDENTITY, description="Marker centre and axes in the phantom frame (4x4, mm); marker z is its outward normal.")
    calibrated: bool = Field(False, description="True once `fluorosim calibrate phantom` has measured this marker.")

    def T(self) -> np.ndarray:
        return matrix(self.T_phantom_from_marker)


class PhantomProfile(Section):
    name: str = Field(min_length=1, description="Shown on screen.")
    aruco_dictionary: Literal[tuple(ARUCO_DICTIONARIES)] = Field(  # type: ignore[valid-type]  # the keys as a Literal
        description="OpenCV predefined dictionary the markers come from.")
    marker_size_mm: float = Field(gt=0, le=500, description="Printed side length of the black marker square (mm).")
    root_marker_id: int = Field(ge=0, description="The marker whose frame is the phantom frame.")
    box: Box
    markers: list[Marker] = Field(min_length=1, description="Every marker stuck on the box.")

    def problems(self) -> Findings:
        size = ARUCO_DICTIONARIES[self.aruco_dictionary]
        seen: dict[int, int] = {}
        for i, m in enumerate(self.markers):
            if m.id in seen:
                yield ("markers", i, "id"), f"duplicate marker id {m.id} (also markers[{seen[m.id]}])"
            seen.setdefault(m.id, i)
            if m.id >= size:
                yield ("markers", i, "id"), f"{m.id} is not in {self.aruco_dictionary}, which has ids 0..{size - 1}"
        if self.root_marker_id not in seen:
            yield ("root_marker_id",), f"marker {self.root_marker_id} is not among markers {sorted(seen)}"

    def marker(self, marker_id: int) -> Marker:
        return next(m for m in self.markers if m.id == marker_id)
