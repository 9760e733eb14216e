"""The rpc layer's conversions under their former single address, for importers not yet moved
(``dqpose.rpc.arms``, tests and benchmarks that name ``convert.plan_msg`` and the like). Each
name lives in its own module: :mod:`~dqpose.rpc.geometry` (Pose, StampedPose, covariances,
Interpolation), :mod:`~dqpose.rpc.wire` (hand-built wire bytes and the C fast paths),
:mod:`~dqpose.rpc.checks` (counts, field-named errors) and one ``<service>_convert`` module per
service; import from there.
"""
from dqpose.errors import FieldError
from dqpose.rpc.blending_convert import METHOD_ENUMS, METHOD_NAMES
from dqpose.rpc.checks import field_named
from dqpose.rpc.fusion_convert import (
                                       DEFAULT_MAX_EXTRAPOLATION,
                                       DEFAULT_PROBABILITY,
                                       DEFAULT_WINDOW,
                                       STATUS_ENUMS,
                                       STATUS_NAMES,
                                       Measurements,
                                       Options,
                                       fused_from_msg,
                                       fused_to_msg,
                                       measurement_msgs,
                                       measurements_to_arrays,
                                       options_from_msg,
                                       options_msg,
                                       wire_measurement_error,
)
from dqpose.rpc.geometry import (
                                       COVARIANCE_SIZE,
                                       INTERPOLATION_ENUMS,
                                       INTERPOLATION_NAMES,
                                       arrays_to_stamped,
                                       dq_to_pose,
                                       dqs_to_poses,
                                       flat_to_dqs,
                                       pose_arrays,
                                       pose_msgs,
                                       poses_to_arrays,
                                       poses_to_dqs,
                                       poses_to_flat,
                                       stamped_msgs,
                                       stamped_to_arrays,
)
from dqpose.rpc.handeye_convert import (
                                       CALIBRATE_FIELDS,
                                       CALIBRATE_REQUEST,
                                       SETUP_ENUMS,
                                       SETUP_NAMES,
                                       CalibrateArgs,
                                       calibrate_error,
                                       calibrate_from_msg,
                                       calibrate_msg,
                                       calibration_from_msg,
                                       calibration_to_msg,
)
from dqpose.rpc.trajectories_convert import (
                                       PlanArgs,
                                       limits_from_msg,
                                       limits_msg,
                                       plan_from_msg,
                                       plan_info_msg,
                                       plan_msg,
                                       sample_msgs,
                                       samples_from_msgs,
)
from dqpose.rpc.wire import (
                                       WireMeasurements,
                                       blend_batch_items_wire,
                                       blend_batch_wire,
                                       blend_request_wire,
                                       blend_responses_from_wire,
                                       blend_wire,
                                       decode_blend_request,
                                       fuse_stream_from_wire,
                                       interpolate_request_wire,
                                       measurements_wire,
                                       poses_wire,
                                       stamped_poses_wire,
)

__all__ = [
    "FieldError", "METHOD_ENUMS", "METHOD_NAMES", "field_named", "DEFAULT_MAX_EXTRAPOLATION",
    "DEFAULT_PROBABILITY", "DEFAULT_WINDOW", "STATUS_ENUMS", "STATUS_NAMES", "Measurements",
    "Options", "fused_from_msg", "fused_to_msg", "measurement_msgs", "measurements_to_arrays",
    "options_from_msg", "options_msg", "wire_measurement_error", "COVARIANCE_SIZE",
    "INTERPOLATION_ENUMS", "INTERPOLATION_NAMES", "arrays_to_stamped", "dq_to_pose",
    "dqs_to_poses", "flat_to_dqs", "pose_arrays", "pose_msgs", "poses_to_arrays", "poses_to_dqs",
    "poses_to_flat", "stamped_msgs", "stamped_to_arrays", "CALIBRATE_FIELDS", "CALIBRATE_REQUEST",
    "SETUP_ENUMS", "SETUP_NAMES", "CalibrateArgs", "calibrate_error", "calibrate_from_msg",
    "calibrate_msg", "calibration_from_msg", "calibration_to_msg", "PlanArgs", "limits_from_msg",
    "limits_msg", "plan_from_msg", "plan_info_msg", "plan_msg", "sample_msgs",
    "samples_from_msgs", "WireMeasurements", "blend_batch_items_wire", "blend_batch_wire",
    "blend_request_wire", "blend_responses_from_wire", "blend_wire", "decode_blend_request",
    "fuse_stream_from_wire", "interpolate_request_wire", "measurements_wire", "poses_wire",
    "stamped_poses_wire",
]
