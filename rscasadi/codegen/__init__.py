"""Generated C: the arm's Functions as C99, compiled, cached, described by a manifest."""
from rscasadi.codegen.generate import (CodegenError, functions, generate, load_compiled, rhs, rk4,  # noqa: F401
                                       step_functions)
