# CasADi for the type checker: every name is Any. Its own stubs type SX, MX and DM as separate
# classes, so code written once for all three (the library's symbolic algorithms) cannot pass.
from typing import Any

def __getattr__(name: str) -> Any: ...
