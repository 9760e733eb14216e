"""The ``dqpose.v1`` messages a recording treats by their type, by full name: one constant a
type, for the writer's views (:data:`dqpose.record.writer.ANSWER_VIEWS`), the viewer and the
exports, which know a recorded call's messages by the names its schemas carry."""
from __future__ import annotations

#: a fused pose (or an error entry): Fuse's, StreamFuse's and Subscribe's answers
FUSED_POSE = "dqpose.v1.FusedPose"
#: the World's configuration (Configure's request and answer), whose frames go on /tf_static
WORLD_CONFIG = "dqpose.v1.WorldConfig"
#: an Execute's request (the arm it names) and its feedback
EXECUTE_REQUEST = "dqpose.v1.ExecuteRequest"
EXECUTION_FEEDBACK = "dqpose.v1.ExecutionFeedback"
#: a watched arm's state (WatchArm's answers)
ARM_STATE = "dqpose.v1.ArmState"
#: a hand-eye calibration's request (its views and setup) and answer
CALIBRATE_REQUEST = "dqpose.v1.CalibrateRequest"
CALIBRATE_RESPONSE = "dqpose.v1.CalibrateResponse"
