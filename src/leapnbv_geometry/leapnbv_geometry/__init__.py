"""Mesh rasterizer, person mask and back-projection, RANSAC ground plane and their nodes."""

from __future__ import annotations

from .ground import GroundPlaneError, GroundPlaneResult, fit_ground_plane, ground_points_from_depth
from .raster import RasterError, RasterResult, rasterize_mesh, warm_up
from .target_geometry import (
    TargetGeometryError,
    TargetGeometryResult,
    backproject,
    compute_target_geometry,
    pixels_to_points,
    place_mesh_metric,
)

__all__ = [
    "GroundPlaneError",
    "GroundPlaneResult",
    "RasterError",
    "RasterResult",
    "TargetGeometryError",
    "TargetGeometryResult",
    "backproject",
    "compute_target_geometry",
    "fit_ground_plane",
    "ground_points_from_depth",
    "pixels_to_points",
    "place_mesh_metric",
    "rasterize_mesh",
    "warm_up",
]
