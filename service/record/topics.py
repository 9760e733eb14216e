"""The topics of a recording and the fields of its JSON channels (docs/recording.md)."""
from __future__ import annotations

#: the call log: one JSON object a call's beginning (with what it records) and end
CALLS_TOPIC = "/dqpose/calls"
#: where messages are missing (the recorder fell behind, or the files could not be written:
#: ``error`` says why)
DROPPED_TOPIC = "/dqpose/record/dropped"
TF_TOPIC = "/tf"
#: a World's frames fixed in their parents (statics, sources), one message a Configure (tf2's
#: latched ``/tf_static``: repeated at the start of each later file of the run)
TF_STATIC_TOPIC = "/tf_static"
ELLIPSOIDS_TOPIC = "/fused/ellipsoids"
#: views are drawn for this many bodies a file at most (each has its channels)
MAX_VIEW_BODIES = 1000


def requests_topic(rpc: str) -> str:
    return f"/dqpose/{rpc}/requests"


def answers_topic(rpc: str) -> str:
    return f"/dqpose/{rpc}/answers"


def pose_topic(body: str) -> str:
    return f"/fused/{body}"


def stats_topic(body: str) -> str:
    return f"/fused/{body}/stats"


def plan_topic(name: str) -> str:
    return f"/plans/{name}"


def arm_topic(arm: str, what: str) -> str:
    """An arm's channels: ``commanded`` and ``actual`` poses, ``feedback`` and ``state``
    scalars, ``limits``."""
    return f"/arms/{arm}/{what}"


CALL_FIELDS = {"call": "integer", "rpc": "string", "event": "string",
               "request_type": "string", "answer_type": "string", "code": "string",
               "details": "string", "continued": "boolean", "world": "string",
               "internal": "boolean"}
DROPPED_FIELDS = {"first_dropped": "integer", "count": "integer", "resumed": "integer",
                  "error": "string"}
STATS_FIELDS = {"body": "string", "time": "number", "chi2": "number", "dof": "integer",
                "sigma_position": "number", "sigma_rotation": "number"}
FEEDBACK_FIELDS = {"time": "number", "state": "string", "message": "string",
                   "error_position": "number", "error_rotation": "number"}
ARM_STATE_FIELDS = {"arm": "string", "state": "string", "busy": "boolean", "faults": "string",
                    "linear_speed": "number", "angular_speed": "number"}
