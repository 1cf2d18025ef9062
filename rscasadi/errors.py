"""The base of every error rscasadi defines: `except rscasadi.Error` catches what the library
refuses or fails at (a model file, a log, an output folder, a build, a controller's arrays, a
result's own check), and each error also keeps the builtin base it had (ValueError,
RuntimeError), so existing handlers still catch it."""


class Error(Exception):
    """An error rscasadi raises on purpose; its message names the file, field, option or code."""


class InvalidArgument(Error, ValueError):
    """A value passed to a function that it refuses; the message names the argument and what it must be."""


class WrongType(Error, TypeError):
    """An argument of a type the function does not take, or a field an object does not have."""


class NotFound(Error, KeyError):
    """A name (a frame, a joint) the model does not have; the message lists those it has."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class Failed(Error, RuntimeError):
    """A computation or a resource that did not do what was asked: a solver, a library, a
    controller's return code; the message says which and why."""
