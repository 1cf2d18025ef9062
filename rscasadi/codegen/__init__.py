"""Generated C: the arm's Functions as C99, compiled, cached, described by a manifest."""
from rscasadi.codegen.generate import (CodegenError, CompiledFeedforward, functions, generate, load_compiled,  # noqa: F401
                                       rhs, rk4,
                                       step_functions)
