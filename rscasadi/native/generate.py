"""The one pipeline of a generated controller (the MPC, the impedance controller, the observer;
`package`, its last step, also writes the arm's library, rscasadi.codegen.generate):
CasADi Functions generated to C, the controller's template files filled in, the input guard,
compiled once per source by the one build step, written whole with a manifest that the ctypes
loader (native.loader) reads.

Every symbol, macro and file carries the controller's name, `kind` (mpc, impedance, observer)
or `P_kind` with a prefix P, so any number of generated controllers link into one program:

    P_mpc_init, P_mpc_t, P_MPC_NU        in P_mpc.h, P_mpc.c, libP_mpc.so
    mpc_init, mpc_t, MPC_NU              in rscasadi_mpc.h, rscasadi_mpc.c, librscasadi_mpc.so

The templates write `${sym}_init`, `${SYM}_NU`, `#include "${header}"`; CasADi's Functions are
named `${sym}_<what>` by the caller (`function_name`), so nothing is renamed after generation.
"""
from __future__ import annotations

import re
import shutil
import tempfile
from pathlib import Path
from string import Template

import casadi as ca

from rscasadi.errors import InvalidArgument
from rscasadi.files import fresh_directory, write_json
from rscasadi.native.build import cached_library, compiler
from rscasadi.native.controller import guard_source


C_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,62}\Z")      # a C symbol's prefix (63 significant)
LABELS = {"mpc": "MPC", "impedance": "impedance controller", "observer": "observer"}   # in the progress lines


def symbols(kind: str, prefix: str = "") -> dict:
    """The names of a `kind` controller with `prefix` (see the module's docstring): sym, SYM,
    header, source, library."""
    if prefix and not C_IDENTIFIER.match(prefix):
        raise InvalidArgument(f"prefix {prefix!r}: the C symbols' prefix must be a C identifier")
    sym = f"{prefix}_{kind}" if prefix else kind
    stem = sym if prefix else f"rscasadi_{kind}"
    return {"sym": sym, "SYM": sym.upper(), "header": f"{stem}.h", "source": f"{stem}.c", "library": f"lib{stem}.so"}


def function_name(kind: str, prefix: str, what: str) -> str:
    """The C name of one of the controller's CasADi Functions: `<sym>_<what>`."""
    return f"{symbols(kind, prefix)['sym']}_{what}"


# CasADi's dense product z += x y walks x along its rows in the innermost loop (a strided sum the
# compiler cannot vectorise); the same sums with the rows innermost add the same terms to each z in
# the same order (bitwise equal) and vectorise.  On the Panda's Riccati MPC (N = 10) the product
# was a fifth of a step.
_MTIMES_DENSE = ("      for (j=0; j<nrow_x; ++j) {\n        for (k=0; k<ncol_x; ++k) {\n"
                 "          z[j + i*nrow_x] += x[j + k*nrow_x] * y[k + i*ncol_x];\n        }\n      }\n")
_MTIMES_DENSE_ROWS_INNERMOST = ("      for (k=0; k<ncol_x; ++k) {\n        for (j=0; j<nrow_x; ++j) {\n"
                                "          z[j + i*nrow_x] += x[j + k*nrow_x] * y[k + i*ncol_x];\n        }\n      }\n")


def casadi_sources(functions: list[ca.Function], name: str | None = None) -> dict[str, str]:
    """CasADi's C of `functions`, one file with its header, `name`.c (default: the first's name),
    its dense product's loops in the order that vectorises (`_MTIMES_DENSE`)."""
    name = functions[0].name() if name is None else name
    gen = ca.CodeGenerator(f"{name}.c", {"with_header": True})
    for f in functions:
        gen.add(f)
    with tempfile.TemporaryDirectory() as d:
        gen.generate(d + "/")
        sources = {file: (Path(d) / file).read_text() for file in (f"{name}.c", f"{name}.h")}
    sources[f"{name}.c"] = sources[f"{name}.c"].replace(_MTIMES_DENSE, _MTIMES_DENSE_ROWS_INNERMOST, 1)
    return sources


def _largest(macros: list[str]) -> str:
    """A C expression of the largest of `macros` (nested conditionals)."""
    out = macros[0]
    for m in macros[1:]:
        out = f"({m} > {out} ? {m} : {out})"
    return out


def write_controller(kind: str, prefix: str, functions: list[ca.Function], templates: Path, header: dict, body: dict,
                     out, flags: list, manifest: dict, log=print, extra_sources: dict | None = None,
                     cc: list | None = None, casadi_file: str | None = None, link: list | None = None) -> dict:
    """Generate `functions`, fill templates/rscasadi_<kind>.h and .c with `header` and `body`
    (plus sym, SYM, header, casadi_header, the work sizes sz_w, sz_iw and sz_w_check, sz_iw_check:
    C expressions of the largest of CasADi's own figures), add the guard and
    `extra_sources`, compile with `flags` once per source (linked with `link`), and write everything with the manifest
    (its header, library, symbol, sources and compiler filled in) into `out`, whole or not at all."""
    names = symbols(kind, prefix)
    casadi_file = functions[0].name() if casadi_file is None else casadi_file
    sources = casadi_sources(functions, casadi_file)
    common = {"sym": names["sym"], "SYM": names["SYM"], "header": names["header"], "casadi_header": f"{casadi_file}.h"}
    sizes = {"sz_w": max(f.sz_w() for f in functions) + 1, "sz_iw": max(f.sz_iw() for f in functions) + 1,
             "sz_w_check": _largest([f"{f.name()}_SZ_W" for f in functions]),
             "sz_iw_check": _largest([f"{f.name()}_SZ_IW" for f in functions])}
    sources[names["header"]] = Template((templates / f"rscasadi_{kind}.h").read_text()).substitute(
        {**common, **sizes, **header})
    sources[names["source"]] = Template((templates / f"rscasadi_{kind}.c").read_text()).substitute(
        {**common, **sizes, **body})
    sources.update(guard_source())
    sources.update(extra_sources or {})
    manifest = {**manifest, "header": names["header"], "symbol": names["sym"],
                "sources": sorted(k for k in sources if k.endswith(".c")),
                "api": {f"{names['sym']}_{k}": v for k, v in manifest["api"].items()}}
    manifest = package(out, sources, flags, names["library"], manifest, log, cc, name=kind,
                       what=f"the {LABELS.get(kind, kind)} ({' '.join(flags)})", link=link)
    log(f"wrote {Path(out) / names['library']}, {names['header']} and manifest.json")
    return manifest


def package(out, sources: dict, flags: list, library: str, manifest: dict, log=print, cc: list | None = None,
            name: str = "lib", what: str | None = None, built: dict | None = None, link: list | None = None) -> dict:
    """The last step of every generated library (controllers and the arm's): `sources` (file name
    -> text, headers included) written into `out` with the shared `library` the one build step
    makes of `built` (default: all of them; cached by their hash, so a header no source includes
    should stay out) and manifest.json, `manifest` completed with the library, the compiler and
    the source hash; whole or not at all."""
    cc = compiler() if cc is None else cc
    with fresh_directory(Path(out)) as tmp:
        for file, text in sources.items():
            (tmp / file).write_text(text)
        lib = cached_library(sources if built is None else built, flags, link or (), name=name, what=what, log=log,
                             cc=cc, log_hit=True)
        shutil.copy2(lib, tmp / library)
        manifest = {**manifest, "library": library, "compiler": cc + flags, "source_hash": lib.stem.rsplit("_", 1)[1]}
        write_json(tmp / "manifest.json", manifest, indent=2)
    return manifest
