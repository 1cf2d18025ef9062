"""The base of every error rscasadi defines: `except rscasadi.Error` catches what the library
refuses or fails at (a model file, a log, an output folder, a build, a controller's arrays, a
result's own check), and each error also keeps the builtin base it had (ValueError,
RuntimeError), so existing handlers still catch it."""


class Error(Exception):
    """An error rscasadi raises on purpose; its message names the file, field, option or code."""
