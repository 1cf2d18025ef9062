"""Generated C: the arm's Functions as C99, compiled, cached, described by a manifest."""
from .generate import (CodegenError, cache_dir, functions, generate, load_compiled, rhs, rk4,  # noqa: F401
                       step_functions, _compiler)
