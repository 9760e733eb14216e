# The C core (service/csrc/, module.c's method table), for type checkers: its functions take and
# return NumPy arrays; their signatures are documented where dqpose.dq and the others wrap them.
from typing import Any

def __getattr__(name: str) -> Any: ...
