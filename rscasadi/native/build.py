"""C to shared libraries, compiled once per source, compiler and flags: the one build step.

`cached_library(sources, flags)` compiles C sources (file name -> text) into one shared library
in the cache directory and returns its path.  The library's name carries a hash of everything
that shapes it (the sources, the compiler, the flags, the link arguments, CasADi's version), so
it is rebuilt exactly when one of them changes and found again otherwise, across processes and
runs.  Each source's object is kept as well (obj/, keyed by the source, the headers it includes,
the compiler and the flags), so a source that several libraries share compiles once.  A lock
per library keeps two processes (sweep workers, test workers) from compiling the
same one twice; the library is written under a temporary name and renamed, so no reader ever
sees half of one.  Beside it a record of its SHA-256 and size, written at build time, is checked
before every use: a library changed since (truncated by a full disk, overwritten, corrupted) is
rebuilt with a warning, never loaded or shipped.  Build folders of runs that were killed are
removed by the next run.

`casadi_c(functions, name)` is the C of CasADi Functions under a fixed file name: CasADi
prefixes its internal symbols with the file's name, so a name that varied (a pid, a temporary
file) would vary the source and defeat the cache.
"""
from __future__ import annotations

import fcntl
import hashlib
import os
import platform
import re
import shlex
import shutil
import subprocess
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import casadi as ca

from rscasadi.errors import Error
from rscasadi.files import cache_dir, remove_stale

OPT_LEVELS = ("-O0", "-O1", "-O2", "-O3", "-Os")


LARGE_C = 1_000_000    # bytes of generated C above which an OCP's functions compile at -O0 by default


def nlp_opt(size: int | None = None) -> str:
    """The optimisation level of an OCP's compiled functions: $RSCASADI_NLP_OPT if set; else
    -O1 for up to LARGE_C bytes of C and -O0 above, where gcc's -O1 passes grow faster than the
    code (Baxter's 15-joint condensing kernel, 5 MB: 119 s at -O1, 13 s at -O0, its solves 1.4x
    slower; 2026-11-29, 2-core Intel Xeon VM).  `size` None: the setting as it enters a cache
    key ("auto" when the size decides)."""
    chosen = os.environ.get("RSCASADI_NLP_OPT")
    if chosen:
        return chosen
    if size is None:
        return "auto"
    return "-O1" if size <= LARGE_C else "-O0"


def nlp_level(opt: str, size: int) -> str:
    """`opt` itself, or for "auto" nlp_opt's level for `size` bytes of C."""
    return nlp_opt(size) if opt == "auto" else opt


class BuildError(Error, RuntimeError):
    """A C compiler is missing, or a source does not compile or link."""


def compiler() -> list:
    """The C compiler: $CC (may carry flags), else `cc`."""
    cc = shlex.split(os.environ.get("CC", "cc")) or ["cc"]
    if shutil.which(cc[0]) is None:
        raise BuildError(f"C compiler {cc[0]!r} not found (set $CC to a C compiler)")
    return cc


def native_flags() -> list:
    """This processor's instructions, fused multiply-adds, and on x86 full-width vectors (gcc
    tunes Zen 1 to 128-bit ones): the step-Jacobian kernel 20-25 % faster at n = 12."""
    wide = ["-mprefer-vector-width=256"] if platform.machine().lower() in ("x86_64", "amd64") else []
    return ["-march=native", "-ffp-contract=fast"] + wide


BLASFEO_KERNELS = Path(__file__).with_name("templates") / "blasfeo_kernels.c"


def blasfeo_kernels() -> dict:
    """BLASFEO's 4x4 product and 4-row matrix-vector kernels in vector C
    (templates/blasfeo_kernels.c, in front of the CasADi wheel's GENERIC BLASFEO), as a source
    for the one build step (file name -> text)."""
    return {BLASFEO_KERNELS.name: BLASFEO_KERNELS.read_text()}


@contextmanager
def locked(path: Path):
    """An exclusive lock on `path` (created if missing) between processes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        yield


def casadi_c(functions, name: str) -> str:
    """The C of CasADi `functions`, generated as one file called `name` (no header)."""
    gen = ca.CodeGenerator(name, {"with_header": False})
    for f in functions:
        gen.add(f)
    with tempfile.TemporaryDirectory() as d:
        gen.generate(d + os.sep)
        return (Path(d) / name).read_text()


def casadi_units(functions, stem: str, units: int = 4) -> dict:
    """The C of CasADi `functions` as up to `units` files (stem0.c, stem1.c, ...) of about equal
    size by instructions, the largest first into the lightest, for `cached_library` to compile in
    parallel (one 10 MB file compiles on one core).  Each file is self-contained: CasADi prefixes
    its internal symbols with the file's name."""
    groups: list[list] = [[] for _ in range(max(1, min(units, len(functions))))]
    load = [0] * len(groups)
    for f in sorted(functions, key=lambda f: -f.n_instructions()):
        i = load.index(min(load))
        groups[i].append(f)
        load[i] += f.n_instructions()
    return {f"{stem}{i}.c": casadi_c(group, f"{stem}{i}.c") for i, group in enumerate(groups) if group}


def library_key(sources: dict, cc: list, flags, link) -> str:
    """The hash naming a library: its sources, compiler, flags, link arguments, CasADi's version."""
    digest = hashlib.sha256()
    for part in [*cc, "|", *flags, "|", *link, "|", ca.__version__] + [f"{k}\n{v}" for k, v in sorted(sources.items())]:
        digest.update(part.encode())
        digest.update(b"\0")
    return digest.hexdigest()[:24]


def _record(lib: Path) -> Path:
    return lib.with_name(lib.name + ".sha256")


def _fingerprint(lib: Path) -> str:
    digest = hashlib.sha256()
    with open(lib, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return f"{digest.hexdigest()} {lib.stat().st_size}"


def intact(lib: Path) -> bool:
    """Whether `lib` is the library its record describes (SHA-256 and size from its build)."""
    try:
        return _record(lib).read_text().strip() == _fingerprint(lib)
    except OSError:
        return False


BUILD_PREFIX = ".build."


def object_key(cc: list, flags, sources: dict, unit: str) -> str:
    """The hash naming the object of one .c source: its name and text, the headers beside it that
    it includes (#include "name", through headers too, conditional or not), the compiler, the
    flags, CasADi's version."""
    headers = [f"{k}\n{sources[k]}" for k in sorted(_included(sources, unit))]
    digest = hashlib.sha256()
    for part in [*cc, "|", *flags, "|", ca.__version__, unit, sources[unit], *headers]:
        digest.update(part.encode())
        digest.update(b"\0")
    return digest.hexdigest()[:24]


def _included(sources: dict, unit: str) -> set:
    """The names of `sources` that `unit` includes with #include "...", directly or through them."""
    found: set = set()
    todo = [unit]
    while todo:
        for name in re.findall(r'^\s*#\s*include\s*"([^"]+)"', sources[todo.pop()], re.MULTILINE):
            if name in sources and name not in found:
                found.add(name)
                todo.append(name)
    return found


def _compile(cc: list, flags, link, sources: dict, lib: Path):
    """Each .c source to an object (in parallel; the headers beside them; an object already in
    the cache's obj/ for the same source, headers, compiler and flags is reused: a controller's
    kernel is one source of several libraries), then one shared library and its record."""
    units = [name for name in sources if name.endswith(".c")]
    remove_stale(lib.parent, BUILD_PREFIX)
    objects = cache_dir() / "obj"
    objects.mkdir(parents=True, exist_ok=True)
    cached = {name: objects / f"{Path(name).stem}_{object_key(cc, flags, sources, name)}.o" for name in units}
    with tempfile.TemporaryDirectory(dir=lib.parent, prefix=f"{BUILD_PREFIX}{os.getpid()}.") as d:
        for name, text in sources.items():
            (Path(d) / name).write_text(text)
        procs = []
        for name in units:
            if intact(cached[name]):
                shutil.copyfile(cached[name], Path(d) / (name + ".o"))
            else:
                procs.append((name, subprocess.Popen([*cc, *flags, "-fPIC", "-c", name, "-o", name + ".o"], cwd=d,
                                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)))
        for name, proc in procs:
            _, err = proc.communicate()
            if proc.returncode != 0:
                raise BuildError(f"compiling {name} failed ({' '.join(cc + list(flags))}):\n{err[-2000:]}")
            _store(Path(d) / (name + ".o"), cached[name])
        part = Path(d) / lib.name
        run = subprocess.run([*cc, *flags, "-shared", *[n + ".o" for n in units], "-o", str(part), *link, "-lm"],
                             cwd=d, capture_output=True, text=True)
        if run.returncode != 0:
            raise BuildError(f"linking {lib.name} failed:\n{run.stderr[-2000:]}")
        record = Path(d) / _record(lib).name
        record.write_text(_fingerprint(part) + "\n")
        part.replace(lib)
        record.replace(_record(lib))


def _store(built: Path, target: Path) -> None:
    """A copy of the object `built` at `target` with its record, each renamed into place."""
    part = target.with_name(f"{BUILD_PREFIX}{os.getpid()}.{target.name}")
    shutil.copyfile(built, part)
    record = target.with_name(f"{BUILD_PREFIX}{os.getpid()}.{_record(target).name}")
    record.write_text(_fingerprint(part) + "\n")
    part.replace(target)
    record.replace(_record(target))


def indexed(key: str, build) -> tuple:
    """(lines, found): what `build()` returns (lines of text, the first a library's path) for a
    `key` made of everything that shapes that library, from the cache's index (found) if the
    library it names is intact, else built now and indexed.  Why: the key (a serialised
    Function, source versions) costs milliseconds where generating the C to hash it costs
    seconds."""
    index = cache_dir() / "lib" / f"index_{hashlib.sha256(key.encode()).hexdigest()[:24]}"
    try:
        lines = index.read_text().split("\n")
        if intact(Path(lines[0])):
            return lines, True
    except OSError:
        pass
    lines = [str(v) for v in build()]
    index.parent.mkdir(parents=True, exist_ok=True)
    tmp = index.with_name(f"{index.name}.{os.getpid()}.tmp")
    tmp.write_text("\n".join(lines))
    os.replace(tmp, index)                         # whole or not at all
    return lines, False


def cached_library(sources: dict, flags=(), link=(), name: str = "lib", what: str | None = None,
                   log=print, cc: list | None = None, log_hit: bool = False) -> Path:
    """The shared library of `sources` (file name -> C text; .h files are the headers the .c
    files include) compiled with `flags` and linked
    with `link`, from the cache or built now; `name` starts its file name, `what` names it in
    the log of a build (and of a cache hit, with `log_hit`)."""
    cc = compiler() if cc is None else cc
    flags, link = list(flags), list(link)
    key = library_key(sources, cc, flags, link)
    directory = cache_dir() / "lib"
    lib = directory / f"{name}_{key}.so"
    if lib.exists() and intact(lib):
        if what and log_hit:
            log(f"cache hit: {lib} ({what})")
        return lib
    with locked(directory / f"{name}_{key}.lock"):
        if lib.exists() and intact(lib):        # built by another process while this one waited
            if what and log_hit:
                log(f"cache hit: {lib} ({what})")
            return lib
        if lib.exists() and not _record(lib).exists():
            log(f"note: {lib} has no record of its build (an older rscasadi's): rebuilding it")
            lib.unlink()
        elif lib.exists():
            log(f"warning: {lib} does not match the record of its build (corrupt, truncated or changed "
                "since): rebuilding it")
            lib.unlink()
        t0 = time.perf_counter()
        if what:
            log(f"compiling {what} ({' '.join(cc + flags)}) ...")
        _compile(cc, flags, link, sources, lib)
        if what:
            log(f"compiled {what} in {time.perf_counter() - t0:.1f} s: {lib}")
    return lib
