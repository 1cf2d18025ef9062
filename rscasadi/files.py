"""Output directories: checked before the work, written whole or not at all, and never losing a
file that rscasadi did not write; and the cache directory."""
from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import stat
import tempfile
from pathlib import Path

from rscasadi.errors import Error


class OutputError(Error, RuntimeError):
    """The output directory cannot be written or replaced."""


class CheckError(Error, RuntimeError):
    """A result failed its own check (a designed trajectory, a fit, a study): nothing is written."""


def cache_dir() -> Path:
    """Where rscasadi keeps what it built (compiled libraries, parsed model files):
    $RSCASADI_CACHE, else ~/.cache/rscasadi."""
    return Path(os.environ.get("RSCASADI_CACHE", Path.home() / ".cache" / "rscasadi"))


def sources_digest(*paths) -> str:
    """A digest of source files' bytes: part of a cache entry's key, so that what a changed
    generator or parser would make differently is made again."""
    digest = hashlib.sha256()
    for path in paths:
        digest.update(Path(path).read_bytes())
    return digest.hexdigest()


MiB = 1 << 20
MAX_INPUT_BYTES = {"log": 256 * MiB,       # 29 columns at 1 kHz for 15 min; longer runs: several logs
                   "mesh": 64 * MiB,       # the largest meshes of public robot descriptions are ~20 MB
                   "model": 16 * MiB,      # a model file, a URDF, a problem or trajectory file
                   "result": 256 * MiB}    # a solution.json


class InputTooLarge(Error, ValueError):
    """An input file is larger than rscasadi reads for its kind: refused by its size, unread."""


def size_refusal(path, kind: str) -> str:
    """Why `path` is not read for its size (larger than MAX_INPUT_BYTES[kind]), or "": its size
    and the limit, checked before any reading.  A missing file is left for the reader to name."""
    try:
        size = Path(path).stat().st_size
    except OSError:
        return ""
    limit = MAX_INPUT_BYTES[kind]
    return f"{size / MiB:.0f} MiB, larger than the {limit // MiB} MiB rscasadi reads for a {kind}" if size > limit else ""


def check_input_size(path, kind: str) -> None:
    """Refuse `path` before reading it when it is too large for its kind (`size_refusal`), naming
    the file: a 2 GB file is refused at once, not after minutes and gigabytes of memory."""
    why = size_refusal(path, kind)
    if why:
        raise InputTooLarge(f"{path}: {why} file; refused unread"
                            + (" (split a long log into several: identify takes many)" if kind == "log" else ""))


def _existing_ancestor(path: Path) -> Path:
    while not path.exists():
        path = path.parent
    return path


def _kind(mode: int) -> str:
    """A file's kind in words, from its st_mode."""
    for test, word in ((stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISLNK, "a symbolic link"), (stat.S_ISREG, "a regular file")):
        if test(mode):
            return word
    return "a special file"


def _not_a_link(path: Path, what: str):
    """Refuse `path` if its last component is a symbolic link: an output goes where it is named,
    never where a link points (a link into a system folder would have rscasadi write there)."""
    if path.is_symlink():
        raise OutputError(f"{path} is a symbolic link (to {os.readlink(path)}); refusing to write {what} through "
                          "it: give the real path")


def check_writable(out) -> Path:
    """`out` resolved, after checking that it is a directory (or can be made one) that this
    process may write, and not a symbolic link: before the work, not after it."""
    _not_a_link(Path(out), "a directory")
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a directory; give --out a directory")
    here = _existing_ancestor(out)
    if not here.is_dir():
        raise OutputError(f"cannot write into {out}: {here} is not a directory")
    if not os.access(here, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write into {out}: {here} is not writable")
    return out


def check_output_file(path) -> Path:
    """`path` (absolute), after checking before the work that it can become a regular file:
    absent or a regular file, not a symbolic link, in an existing directory this process may
    write.  A device, FIFO, socket or directory there is refused by name, never replaced."""
    path = Path(path)
    _not_a_link(path, "a file")
    try:
        mode = path.lstat().st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise OutputError(f"{path}: {exc.strerror}") from exc
    if mode is not None and not stat.S_ISREG(mode):
        raise OutputError(f"{path} exists and is {_kind(mode)}, not a regular file; refusing to replace it "
                          "(give the name of a file to write)")
    parent = path.absolute().parent
    if not parent.is_dir():
        raise OutputError(f"{path}: the directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write {path}: {parent} is not writable")
    return path.absolute()


def _replaced(src: Path, dst: Path, prefix: str = "") -> tuple[list[str], list[str]]:
    """Entries of src that would replace an entry of dst (recursively inside directories), and
    those whose kind differs (a file where dst has a directory, or the reverse)."""
    replaced: list[str] = []
    clash: list[str] = []
    for entry in sorted(src.iterdir()):
        target, name = dst / entry.name, f"{prefix}{entry.name}"
        if entry.is_dir() and target.is_dir() and not target.is_symlink():
            r, c = _replaced(entry, target, name + "/")
            replaced, clash = replaced + r, clash + c
        elif target.exists() or target.is_symlink():
            replaced.append(name)
            mode = target.lstat().st_mode
            if stat.S_ISDIR(mode) != entry.is_dir() or not (stat.S_ISDIR(mode) or stat.S_ISREG(mode)):
                clash.append(f"{name} ({_kind(mode)})")
    return replaced, clash


def _merge(src: Path, dst: Path):
    """Move every entry of src into dst, replacing the entry of the same name; directories are
    merged, so files in dst that src does not name are kept."""
    for entry in sorted(src.iterdir()):
        target = dst / entry.name
        if entry.is_dir() and target.is_dir() and not target.is_symlink():
            _merge(entry, target)
        else:
            os.replace(entry, target)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:                        # another user's process: alive
        return True
    return True


def remove_stale(directory: Path, prefix: str):
    """Remove the temporary directories `prefix<pid>.*` in `directory` whose process has ended
    (killed before it could clean up: SIGKILL, a power cut)."""
    try:
        entries = list(Path(directory).glob(prefix + "*"))
    except OSError:
        return
    for entry in entries:
        pid = entry.name[len(prefix):].split(".", 1)[0]
        if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)) and entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)


TMP_PREFIX = ".rscasadi-tmp."
MARKER = ".rscasadi"           # in every output directory: rscasadi wrote it (no other file counts)
MARKER_TEXT = "This directory was written by rscasadi: the next run into it replaces the files it wrote.\n"


@contextlib.contextmanager
def fresh_directory(out):
    """Yield a temporary directory to write the outputs into.  On success each entry written there
    replaces the entry of the same name in `out` (which is created if need be, and keeps its
    permissions if it exists); nothing else in `out` is touched, and `out` gets the MARKER file.
    On any failure or interrupt the temporary directory is removed and `out` is as it was.  A
    directory without the MARKER (one rscasadi did not write, whatever files it holds) is refused
    if an output would replace one of its files.  Temporary directories of killed runs are
    removed first."""
    out = check_writable(out)
    try:
        if out.exists():
            remove_stale(out, TMP_PREFIX)
            tmp = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{os.getpid()}.", dir=out))
        else:
            out.parent.mkdir(parents=True, exist_ok=True)
            remove_stale(out.parent, f".{out.name}{TMP_PREFIX}")
            tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}{TMP_PREFIX}{os.getpid()}.", dir=out.parent))
    except OSError as exc:
        raise OutputError(f"cannot write into {out}: {exc.strerror}") from exc
    try:
        yield tmp
        (tmp / MARKER).write_text(MARKER_TEXT)
        if not out.exists():
            umask = os.umask(0)
            os.umask(umask)
            tmp.chmod(0o777 & ~umask)
            tmp.rename(out)
            return
        replaced, clash = _replaced(tmp, out)
        if clash:
            raise OutputError(f"{out}: {', '.join(clash)} is of another kind than what rscasadi writes there "
                              f"(a regular file or a directory); refusing to replace it")
        replaced = [name for name in replaced if name != MARKER]
        if replaced and not (out / MARKER).is_file():
            raise OutputError(f"{out} was not written by rscasadi (no {MARKER} file in it) and holds "
                              f"{', '.join(replaced)}; refusing to replace them (choose another --out, or "
                              "move them away)")
        _merge(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def showing_final_paths(log, tmp, out):
    """A log that prints `out` (a path, or words such as "(a temporary build)") where a message
    names the temporary directory `tmp`."""
    tmp, out = str(tmp), str(Path(out).resolve()) if isinstance(out, Path) else str(out)
    return lambda msg: log(str(msg).replace(tmp, out))


def finite_json(obj):
    """obj with every NaN or infinity replaced by None (JSON's null: "no number"), numpy scalars
    and arrays as Python numbers and lists; the reason for a null is stated beside it by the writer."""
    import math

    import numpy as np
    if isinstance(obj, dict):
        return {str(k): finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_json(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


@contextlib.contextmanager
def replacing(path):
    """The project's one atomic write: a temporary name beside `path` to write to, which replaces
    `path` whole when the block ends normally and is removed otherwise.  `path` must be absent or
    a regular file (check_output_file), checked before and again just before the replacement: a
    device, FIFO, socket, directory or symbolic link is never replaced."""
    path = check_output_file(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")       # the suffix kept: writers read it
    if tmp.is_symlink() or (tmp.exists() and not tmp.is_file()):
        raise OutputError(f"{tmp} (rscasadi's temporary name for {path.name}) exists and is not a regular file")
    try:
        yield tmp
        check_output_file(path)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text(path, text: str):
    """`text` into `path`, written whole or not at all."""
    with replacing(path) as tmp:
        tmp.write_text(text)


def write_json(path, obj, indent: int = 1):
    """Valid JSON (no NaN or Infinity: null), written whole or not at all."""
    import json
    write_text(path, json.dumps(finite_json(obj), indent=indent, allow_nan=False) + "\n")


def safe_name(text) -> str:
    """A name from a user's file kept to letters, digits and _ . - (the rest as _): safe inside a
    C comment, an XML attribute and a file name."""
    import re
    return re.sub(r"[^A-Za-z0-9._-]", "_", str(text))


def run_stamp() -> str:
    """The run's date, machine and commit (of the checkout holding this package), for the first
    line under a results file's title."""
    import datetime
    import os
    import platform
    import subprocess
    root = Path(__file__).resolve().parents[1]
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        run = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "rscasadi"], cwd=root, capture_output=True,
                               text=True).stdout.strip()
        commit = run.stdout.strip()
    except OSError:
        commit, dirty = "", ""
    where = f"commit {commit}{' with local changes' if dirty else ''}" if commit else "not a git checkout"
    return f"Run of {datetime.date.today().isoformat()} on {cpu}, {os.cpu_count()} cores, {platform.system()}; {where}."
