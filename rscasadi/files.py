"""Output directories that appear whole or not at all."""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path


class OutputError(RuntimeError):
    """The output directory cannot be written or replaced."""


@contextlib.contextmanager
def fresh_directory(out, marker: str):
    """Yield a temporary directory beside `out`; on success it replaces `out` whole, on any
    failure it is removed and `out` is untouched.  An existing `out` is replaced only if it
    holds `marker` (a file this project wrote there) or is empty."""
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a directory; give --out a directory")
    if out.exists() and any(out.iterdir()) and not (out / marker).exists():
        raise OutputError(f"{out} exists and was not written by rscasadi (no {marker}); refusing to replace it")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
        tmp.chmod(0o755)
    except OSError as exc:
        raise OutputError(f"cannot write into {out.parent}: {exc.strerror}") from exc
    try:
        yield tmp
        old = None
        if out.exists():
            old = out.with_name(f".{out.name}.old.{os.getpid()}")
            out.rename(old)
        tmp.rename(out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
