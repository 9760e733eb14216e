"""The gRPC layer: the only package that imports grpc or the generated stubs (``_proto``).

``server`` (the server: config, auth, TLS, health, reflection, metrics, lifecycle), ``calls`` (what
every servicer shares: status mapping, call log, metrics), ``checks`` (request counts, errors named
by field path), one module per service (``blending``, ``fusion``, ``trajectories`` with ``arms``,
``handeye``) with its messages <-> arrays beside it (``<service>_convert``), ``geometry`` (the
shared Pose, StampedPose, covariance and Interpolation messages), ``wire`` (wire bytes built and
read without message objects, the C fast paths) and ``client`` (the NumPy client). ``convert``
re-exports the conversions under their former address.
"""

# The server's default limits, which the client must know to split what it sends under them.
# Here because this module imports nothing: `dqpose serve --help` shows them without grpc.
DEFAULT_MAX_MESSAGE_BYTES = 4 * 1024 * 1024
DEFAULT_MAX_POSES = 10_000        # per request: poses, keyframes, sampled times, batch requests
BATCH_POSE_FACTOR = 10            # a BlendBatch may carry this many times max_poses poses in all
