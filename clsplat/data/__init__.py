"""Driving-scene data: the data model, a synthetic generator and dataset loaders/writers."""
from .scene import (
    CAMERA_NAMES,
    SEMANTIC_CLASSES,
    Box3D,
    Camera,
    DrivingSequence,
    Frame,
    LidarPoints,
    invert_transform,
    make_transform,
    project_points,
    quat_to_rotmat,
    rotmat_to_quat,
    unproject_depth,
)
from .synthetic import SyntheticConfig, StreetScene, generate_sequence, make_rig, render_view
from .pandaset import load_pandaset, write_pandaset
from .nuscenes import load_nuscenes_sample, load_nuscenes_scene, write_nuscenes

__all__ = [
    "CAMERA_NAMES", "SEMANTIC_CLASSES", "Box3D", "Camera", "DrivingSequence", "Frame", "LidarPoints",
    "invert_transform", "make_transform", "project_points", "quat_to_rotmat", "rotmat_to_quat",
    "unproject_depth", "SyntheticConfig", "StreetScene", "generate_sequence", "make_rig", "render_view",
    "load_pandaset", "write_pandaset", "load_nuscenes_scene", "load_nuscenes_sample", "write_nuscenes",
]
