"""The one place where ROS messages become numpy arrays and back.

Every node converts through these functions. They use the fast idioms: a message's byte payload
is filled from ``ndarray.tobytes()`` (or an ``array.array`` for typed sequences) and read with
``np.frombuffer`` (no copy), never through Python lists. The readers apply the single-message
contracts (:mod:`leapnbv_common.contracts`) and raise :class:`ConversionError`.

One module per concern, every name importable from here:

- ``base``: ConversionError, the typed sequence fields (float32[], uint32[]);
- ``stamps``: builtin_interfaces/Time <-> nanoseconds (stamp_to_ns, ns_to_stamp, set_stamp),
  headers, the ``inputs`` list of a stage output;
- ``images``: sensor_msgs/Image and CameraInfo;
- ``serialized``: CDR-serialized messages read in place (SerializedImage, header stamps);
- ``geometry``: points, point clouds, the obstacle map, poses, paths (the quaternion math is
  :mod:`leapnbv_common.rotations`);
- ``person``: PersonDetections, HumanMesh, SceneGroundTruth, ScenePeople;
- ``planning``: GroundPlane, TargetGeometry, ViewCandidates.
"""
from __future__ import annotations

from leapnbv_common.conversions.base import ConversionError, float32_sequence, uint32_sequence
from leapnbv_common.conversions.geometry import (
    obstacle_map_to_points,
    path_msg,
    path_to_numpy,
    point_msg,
    point_to_numpy,
    pointcloud2_to_xyz,
    pose_msg,
    pose_msgs,
    pose_to_numpy,
    poses_to_numpy,
    xyz_to_pointcloud2,
)
from leapnbv_common.conversions.images import (
    COLOUR_ENCODINGS,
    DEPTH_ENCODINGS,
    IMAGE_ENCODINGS,
    camera_info_to_k,
    check_image,
    depth_to_metres,
    image_size,
    image_to_numpy,
    image_to_rgb,
    make_camera_info,
    numpy_to_image,
)
from leapnbv_common.conversions.person import (
    _MESH_PARAM_SIZES,  # noqa: F401 - the HumanMesh body-parameter sizes, read by the contract tests
    HumanMeshArrays,
    SceneGroundTruthArrays,
    ScenePersonArrays,
    arrays_to_human_mesh,
    arrays_to_scene_ground_truth,
    arrays_to_scene_people,
    box_to_detection,
    detection_to_box,
    detections_to_boxes,
    human_mesh_to_arrays,
    scene_ground_truth_to_arrays,
    scene_people_to_arrays,
)
from leapnbv_common.conversions.planning import (
    GROUND_PLANE_SOURCES,
    GroundPlaneArrays,
    TargetGeometryArrays,
    ViewCandidatesArrays,
    arrays_to_ground_plane,
    arrays_to_target_geometry,
    arrays_to_view_candidates,
    ground_plane_to_arrays,
    target_geometry_to_arrays,
    view_candidates_to_arrays,
)
from leapnbv_common.conversions.serialized import (
    SerializedImage,
    serialized_header_stamp_ns,
    serialized_image_header,
)
from leapnbv_common.conversions.stamps import (
    NS_PER_S,
    Stamp,
    header_with_stamp,
    input_stamp_msgs,
    input_stamps,
    ns_to_stamp,
    set_stamp,
    stamp_to_ns,
)
from leapnbv_common.rotations import quaternion_to_rotation, rotations_to_quaternions

__all__ = [
    "COLOUR_ENCODINGS",
    "DEPTH_ENCODINGS",
    "GROUND_PLANE_SOURCES",
    "IMAGE_ENCODINGS",
    "NS_PER_S",
    "ConversionError",
    "GroundPlaneArrays",
    "HumanMeshArrays",
    "SceneGroundTruthArrays",
    "ScenePersonArrays",
    "SerializedImage",
    "Stamp",
    "TargetGeometryArrays",
    "ViewCandidatesArrays",
    "arrays_to_ground_plane",
    "arrays_to_human_mesh",
    "arrays_to_scene_ground_truth",
    "arrays_to_scene_people",
    "arrays_to_target_geometry",
    "arrays_to_view_candidates",
    "box_to_detection",
    "camera_info_to_k",
    "check_image",
    "depth_to_metres",
    "detection_to_box",
    "detections_to_boxes",
    "float32_sequence",
    "ground_plane_to_arrays",
    "header_with_stamp",
    "human_mesh_to_arrays",
    "image_size",
    "image_to_numpy",
    "image_to_rgb",
    "input_stamp_msgs",
    "input_stamps",
    "make_camera_info",
    "ns_to_stamp",
    "numpy_to_image",
    "obstacle_map_to_points",
    "path_msg",
    "path_to_numpy",
    "point_msg",
    "point_to_numpy",
    "pointcloud2_to_xyz",
    "pose_msg",
    "pose_msgs",
    "pose_to_numpy",
    "poses_to_numpy",
    "quaternion_to_rotation",
    "rotations_to_quaternions",
    "scene_ground_truth_to_arrays",
    "scene_people_to_arrays",
    "serialized_header_stamp_ns",
    "serialized_image_header",
    "set_stamp",
    "stamp_to_ns",
    "target_geometry_to_arrays",
    "uint32_sequence",
    "view_candidates_to_arrays",
    "xyz_to_pointcloud2",
]
