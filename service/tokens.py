"""The server's bearer token checked, the one way every surface checks it (the gRPC calls'
``authorization`` metadata, the metrics port's ``Authorization`` header, the live view's
``?token=``): compared in a time that does not reveal how much of it matched."""
from __future__ import annotations

import hmac


def matches(given: str | bytes | None, token: str) -> bool:
    """Whether ``given`` is ``token`` (``None``: nothing given)."""
    if given is None:
        return False
    if isinstance(given, str):
        given = given.encode()
    return hmac.compare_digest(given, token.encode())


def bearer_matches(header: str | bytes | None, token: str) -> bool:
    """Whether an ``authorization`` value ``header`` is ``Bearer <token>``."""
    return matches(header, "Bearer " + token)
