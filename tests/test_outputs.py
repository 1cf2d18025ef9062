"""Output directories and files: a user's own files survive a re-run, an existing directory keeps
its permissions, a failed or interrupted run leaves nothing, a read-only directory is refused
before the work, and no JSON the project writes holds NaN or Infinity."""
import json
import os
import stat
import shutil
import subprocess

import numpy as np
import pytest

from rscasadi.cli import main
from rscasadi.files import OutputError, fresh_directory, write_json

from conftest import REFERENCE, ROOT


def _write(out, names):
    with fresh_directory(out) as tmp:
        (tmp / "manifest.json").write_text("{}")
        for name in names:
            (tmp / name).parent.mkdir(parents=True, exist_ok=True)
            (tmp / name).write_text(f"new {name}")


def test_rerun_keeps_the_users_files_and_replaces_its_own(tmp_path):
    out = tmp_path / "out"
    _write(out, ["a.txt", "sub/b.txt"])
    (out / "notes.txt").write_text("mine")
    (out / "sub" / "mine.txt").write_text("mine too")
    (out / "a.txt").write_text("old")
    _write(out, ["a.txt", "sub/b.txt"])
    assert (out / "notes.txt").read_text() == "mine" and (out / "sub" / "mine.txt").read_text() == "mine too"
    assert (out / "a.txt").read_text() == "new a.txt"
    assert sorted(p.name for p in out.iterdir()) == [".rscasadi", "a.txt", "manifest.json", "notes.txt", "sub"]   # no temporary left


def test_existing_empty_directory_keeps_its_permissions(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    out.chmod(0o750)
    _write(out, ["a.txt"])
    assert stat.S_IMODE(out.stat().st_mode) == 0o750 and (out / "a.txt").exists()


def test_failure_leaves_the_directory_as_it_was(tmp_path):
    out = tmp_path / "out"
    _write(out, ["a.txt"])
    before = {p.name: p.read_text() for p in out.iterdir()}
    for exc in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with fresh_directory(out) as tmp:
                (tmp / "a.txt").write_text("half")
                raise exc
        assert {p.name: p.read_text() for p in out.iterdir()} == before
    with pytest.raises(RuntimeError):
        with fresh_directory(tmp_path / "new") as tmp:
            (tmp / "x").write_text("half")
            raise RuntimeError
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_foreign_file_in_the_way_is_refused_untouched(tmp_path):
    """A directory of the user's, even one holding a manifest.json of its own (what rscasadi's
    outputs hold too), is not taken for rscasadi's: only the .rscasadi marker counts."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("the user's")
    (out / "manifest.json").write_text('{"mine": true}')
    with pytest.raises(OutputError, match="not written by rscasadi.*manifest.json"):
        _write(out, ["a.txt"])
    assert sorted(p.name for p in out.iterdir()) == ["a.txt", "manifest.json"]
    assert (out / "a.txt").read_text() == "the user's" and (out / "manifest.json").read_text() == '{"mine": true}'


def test_sigterm_and_kill_leave_no_temporary_behind(tmp_path):
    """SIGTERM during a write: the command exits 143 and removes its temporary directory; one
    killed (SIGKILL) leaves its temporary directory, which the next run into the same place
    removes."""
    import signal
    import sys
    import time
    out = tmp_path / "out"
    script = tmp_path / "slow.py"
    script.write_text(f"""
import sys, time
from rscasadi import interrupt
from rscasadi.files import fresh_directory
interrupt.install()
try:
    with fresh_directory({str(out)!r}) as tmp:
        (tmp / "a.txt").write_text("half")
        print("writing", flush=True)
        time.sleep(60)
except KeyboardInterrupt:
    sys.exit(143 if interrupt.terminated() else 130)
""")
    for sig, code in ((signal.SIGTERM, 143), (signal.SIGKILL, -9)):
        p = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
        assert p.stdout.readline().strip() == "writing"
        p.send_signal(sig)
        assert p.wait(timeout=30) == code
        left = [q.name for q in tmp_path.iterdir() if q.name.startswith(".out")]
        assert bool(left) == (sig == signal.SIGKILL), left
    _write(out, ["b.txt"])                          # the next run cleans what the killed one left
    assert sorted(q.name for q in tmp_path.iterdir() if q.name != "slow.py") == ["out"]
    assert sorted(q.name for q in out.iterdir()) == [".rscasadi", "b.txt", "manifest.json"]


def test_a_corrupt_cache_entry_is_rebuilt_not_used(tmp_path, monkeypatch):
    """A cached library changed after its build (garbage written over it, or truncated) is found
    out by its SHA-256 record, rebuilt with a warning, and the rebuilt one loads; a stale build
    folder of a killed compile is removed."""
    import sys
    from rscasadi.native.build import BUILD_PREFIX, cached_library
    monkeypatch.setenv("RSCASADI_CACHE", str(tmp_path / "cache"))
    sources = {"f.c": "double rsf_twice(double x) { return 2.0 * x; }\n"}
    lib = cached_library(sources, ["-O1"], name="t", log=lambda m: None)
    (lib.parent / f"{BUILD_PREFIX}999999999.x").mkdir()                 # a killed compile's (no such pid)
    load = ("import ctypes, sys; f = ctypes.CDLL(sys.argv[1]).rsf_twice; f.restype = ctypes.c_double; "
            "f.argtypes = [ctypes.c_double]; print(f(21.0))")
    for damaged in (b"garbage" * 100, lib.read_bytes()[:1000]):       # overwritten, truncated
        (lib.parent / "damaged").write_bytes(damaged)
        (lib.parent / "damaged").replace(lib)
        said = []
        again = cached_library(sources, ["-O1"], name="t", log=said.append)
        assert again == lib and any("does not match the record" in m for m in said), said
        run = subprocess.run([sys.executable, "-c", load, str(again)], capture_output=True, text=True)
        assert run.stdout.strip() == "42.0", run.stderr
    quiet = []
    cached_library(sources, ["-O1"], name="t", log=quiet.append, what="t", log_hit=True)
    assert quiet == [f"cache hit: {lib} (t)"]
    assert not list(lib.parent.glob(f"{BUILD_PREFIX}*"))


def test_a_source_shared_by_libraries_is_compiled_once(tmp_path, monkeypatch):
    """The one build step keeps each source's object: a second library with the same source and
    the headers it includes (a controller's kernel in its own library and in the controller's)
    compiles only its other sources; a header it includes changed (directly or through another),
    other flags or a damaged object compile it again, a header it does not include does not; and
    every library computes what its sources say."""
    import sys
    from rscasadi.native.build import cached_library, compiler
    monkeypatch.setenv("RSCASADI_CACHE", str(tmp_path / "cache"))
    calls = tmp_path / "calls.txt"
    wrapper = tmp_path / "cc.sh"
    wrapper.write_text(f'#!/bin/sh\nfor a in "$@"; do case "$a" in *.c) echo "$a" >> {calls};; esac; done\n'
                       f'exec {" ".join(compiler())} "$@"\n')
    wrapper.chmod(0o755)
    kernel = {"k.c": '#include "k.h"\ndouble rsk_k(double x) { return K * x; }\n', "k.h": "#define K 3.0\n"}
    def build(extra, flags=("-O1",), headers=None):
        calls.write_text("")
        sources = {**kernel, **(headers or {}), **extra}
        lib = cached_library(sources, list(flags), name="t", log=lambda m: None, cc=[str(wrapper)])
        return lib, sorted(calls.read_text().split())
    load = ("import ctypes, sys; l = ctypes.CDLL(sys.argv[1]); f, g = l.rsk_k, getattr(l, sys.argv[2]); "
            "f.restype = g.restype = ctypes.c_double; f.argtypes = g.argtypes = [ctypes.c_double]; print(f(2.0), g(2.0))")
    def values(lib, name):
        run = subprocess.run([sys.executable, "-c", load, str(lib), name], capture_output=True, text=True)
        return run.stdout.split()
    a = {"a.c": "double rsk_a(double x) { return x + 1.0; }\n"}
    b = {"b.c": "double rsk_b(double x) { return x - 1.0; }\n"}
    lib, compiled = build(a)
    assert compiled == ["a.c", "k.c"] and values(lib, "rsk_a") == ["6.0", "3.0"]
    lib, compiled = build(b)
    assert compiled == ["b.c"] and values(lib, "rsk_b") == ["6.0", "1.0"]
    lib, compiled = build(b, headers={"k.h": "#define K 5.0\n"})
    assert compiled == ["k.c"] and values(lib, "rsk_b") == ["10.0", "1.0"]
    lib, compiled = build(b, headers={"other.h": "#define K 7.0\n"})     # a header k.c does not include
    assert compiled == [] and values(lib, "rsk_b") == ["6.0", "1.0"]
    nested = {"k.h": '#include "deep.h"\n#define K DEEP\n', "deep.h": "#define DEEP 4.0\n"}
    lib, compiled = build(b, headers=nested)                              # through a header it includes
    assert compiled == ["k.c"] and values(lib, "rsk_b") == ["8.0", "1.0"]
    lib, compiled = build(b, headers={**nested, "deep.h": "#define DEEP 9.0\n"})
    assert compiled == ["k.c"] and values(lib, "rsk_b") == ["18.0", "1.0"]
    lib, compiled = build(b, flags=("-O2",))
    assert compiled == ["b.c", "k.c"]
    for obj in (tmp_path / "cache" / "obj").glob("k_*.o"):
        obj.write_bytes(b"garbage")
    lib, compiled = build({"c.c": "double rsk_c(double x) { return x * x; }\n"})
    assert compiled == ["c.c", "k.c"] and values(lib, "rsk_c") == ["6.0", "4.0"]


def test_json_is_valid_without_nan_or_infinity(tmp_path):
    write_json(tmp_path / "x.json", {"a": float("nan"), "b": [1.0, float("inf")], "c": np.float64(-np.inf),
                                     "d": np.array([1.0, np.nan])})
    text = (tmp_path / "x.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"a": None, "b": [1.0, None], "c": None, "d": [1.0, None]}


@pytest.fixture
def read_only(tmp_path):
    """A directory this process cannot write: mode 555, or immutable where we are root (root
    writes through any mode)."""
    ro = tmp_path / "readonly"
    ro.mkdir()
    if os.geteuid() != 0:
        ro.chmod(0o555)
        yield ro
        ro.chmod(0o755)
        return
    if not shutil.which("chattr") or subprocess.run(["chattr", "+i", str(ro)], capture_output=True).returncode:
        pytest.skip("root, and this file system has no immutable flag: nothing is read-only to root")
    yield ro
    subprocess.run(["chattr", "-i", str(ro)], check=True)


def test_read_only_output_is_refused_before_the_work(read_only, tmp_path, capsys):
    log = tmp_path / "log.csv"
    log.write_text("t,theta_1\n")
    for argv, not_started in (
            (["ocp", str(REFERENCE.parent / "ocp_min_effort.toml"), "--out", str(read_only)], "solving"),
            (["identify", str(REFERENCE), str(log), "--out", str(read_only)], "identifying"),
            (["excite", str(REFERENCE), "--out", str(read_only)], "excitation:"),
            (["mpc", str(REFERENCE.parent / "mpc_arm3.toml"), "--out", str(read_only)], "compiling"),
            (["reproduce", "--out", str(read_only)], "wrote")):
        assert main(argv) == 2, argv
        res = capsys.readouterr()
        assert "not writable" in res.err and str(read_only) in res.err, res.err
        assert not_started not in res.out and "Traceback" not in res.err, res.out
    assert list(read_only.iterdir()) == []


def _special_files(tmp_path):
    """A FIFO, a socket, a directory and (as root) a character device made in tmp_path, never the
    machine's own: what an output must refuse rather than replace."""
    import socket
    made = {"FIFO": tmp_path / "fifo.gif"}
    os.mkfifo(made["FIFO"])
    made["socket"] = tmp_path / "sock.gif"
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(made["socket"]))
    made["directory"] = tmp_path / "dir.gif"
    made["directory"].mkdir()
    if os.geteuid() == 0:
        made["character device"] = tmp_path / "null.gif"
        os.mknod(made["character device"], stat.S_IFCHR | 0o666, os.makedev(1, 3))
    return made, sock


def _kinds(paths):
    return {name: stat.S_IFMT(os.lstat(p).st_mode) for name, p in paths.items()}


@pytest.mark.parametrize("command", ["view", "view --gif", "simulate"])
def test_an_output_file_never_replaces_a_device_fifo_socket_or_directory(command, tmp_path, capsys):
    """view --out, view --gif and simulate --out pointed at a device node, a FIFO, a socket or a
    directory: exit 2 naming the path and its kind, before the work, and the node is still there
    and of its kind."""
    made, sock = _special_files(tmp_path)
    before = _kinds(made)
    traj = ROOT / "problems" / "trajectory_arm3.toml"
    try:
        for kind, target in made.items():
            argv = {"view": ["view", str(REFERENCE), "--out", str(target)],
                    "view --gif": ["view", str(REFERENCE), "--out", str(tmp_path / "v.html"), "--gif", str(target)],
                    "simulate": ["simulate", str(REFERENCE), str(traj), "--out", str(target)]}[command]
            assert main(argv) == 2, kind
            err = capsys.readouterr().err
            assert str(target) in err and ("not a regular file" in err or "is not a directory" in err), err
            assert not (tmp_path / "v.html").exists()
    finally:
        sock.close()
    assert _kinds(made) == before


def test_an_output_through_a_symlink_is_refused(tmp_path, capsys):
    """An --out (file or directory) that is a symbolic link, here into a folder standing for a
    system one: refused by name, and nothing is written where it points."""
    system = tmp_path / "system"
    system.mkdir()
    (system / "passwd").write_text("root:x:0:0\n")
    link_file, link_dir = tmp_path / "view.html", tmp_path / "out"
    os.symlink(system / "passwd", link_file)
    os.symlink(system, link_dir)
    assert main(["view", str(REFERENCE), "--out", str(link_file)]) == 2
    assert "symbolic link" in capsys.readouterr().err
    assert main(["export", "mujoco", str(REFERENCE), "--out", str(link_dir)]) == 2
    assert "symbolic link" in capsys.readouterr().err
    assert sorted(p.name for p in system.iterdir()) == ["passwd"]
    assert (system / "passwd").read_text() == "root:x:0:0\n"


def test_a_device_inside_an_output_directory_is_not_replaced(tmp_path):
    """A directory rscasadi wrote, in which a file it writes has become a FIFO: the next run
    refuses to replace it, and the directory is as it was."""
    out = tmp_path / "out"
    _write(out, ["a.txt"])
    (out / "a.txt").unlink()
    os.mkfifo(out / "a.txt")
    with pytest.raises(OutputError, match="a.txt .a FIFO."):
        _write(out, ["a.txt"])
    assert stat.S_ISFIFO(os.lstat(out / "a.txt").st_mode)


def test_huge_inputs_are_refused_by_size_at_once(tmp_path, capsys):
    """A 2 GiB log and a 2 GiB mesh (sparse files: no disk used): the log is refused in one line,
    by its size, without being read; the mesh is skipped with its size named, and view still
    draws the arm."""
    import time
    log = tmp_path / "huge.csv"
    with open(log, "wb") as fh:
        fh.write(b"t,theta_1,theta_2,theta_3,phi_1,phi_2,phi_3,tau_1,tau_2,tau_3\n")
        fh.truncate(2 << 30)
    t0 = time.perf_counter()
    assert main(["identify", str(REFERENCE), str(log), "--out", str(tmp_path / "ident")]) == 2
    err = capsys.readouterr().err
    assert time.perf_counter() - t0 < 30                     # a generous bound: reading it took minutes
    assert err.count("\n") == 1 and "2048 MiB" in err and str(log) in err and "refused unread" in err, err
    assert not (tmp_path / "ident").exists()
    pkg = tmp_path / "robot"
    (pkg / "urdf").mkdir(parents=True)
    (pkg / "package.xml").write_text("<package><name>robot</name></package>\n")
    (pkg / "meshes").mkdir()
    with open(pkg / "meshes" / "huge.stl", "wb") as fh:
        fh.truncate(2 << 30)
    text = (ROOT / "problems" / "urdf" / "panda.urdf").read_text().replace(
        "package://example-robot-data/robots/panda_description/meshes/visual/link3.dae", "package://robot/meshes/huge.stl")
    (pkg / "urdf" / "panda.urdf").write_text(text)
    model = (ROOT / "problems" / "panda_sea.toml").read_text().replace('urdf = "urdf/panda.urdf"', 'urdf = "robot/urdf/panda.urdf"')
    (tmp_path / "panda.toml").write_text(model)
    assert main(["view", str(tmp_path / "panda.toml"), "--out", str(tmp_path / "view.html")]) in (0, None)
    out = capsys.readouterr().out
    assert "skipped mesh 'package://robot/meshes/huge.stl': 2048 MiB, larger than" in out, out
    assert (tmp_path / "view.html").stat().st_size > 0
