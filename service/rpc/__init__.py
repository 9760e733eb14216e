"""The gRPC layer: the only package that imports grpc or the generated stubs (``_proto``).

``server`` (the server: config, auth, TLS, health, reflection, metrics, lifecycle), ``calls`` (what
every servicer shares: status mapping, call log, metrics), one module per service (``blending``),
``convert`` (messages <-> arrays, errors named by field path) and ``client`` (the NumPy client).
"""
