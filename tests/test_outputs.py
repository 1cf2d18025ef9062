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

from conftest import REFERENCE


def _write(out, names, marker="done.json"):
    with fresh_directory(out, marker) as tmp:
        (tmp / marker).write_text("{}")
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
    assert sorted(p.name for p in out.iterdir()) == ["a.txt", "done.json", "notes.txt", "sub"]   # no temporary left


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
            with fresh_directory(out, "done.json") as tmp:
                (tmp / "a.txt").write_text("half")
                raise exc
        assert {p.name: p.read_text() for p in out.iterdir()} == before
    with pytest.raises(RuntimeError):
        with fresh_directory(tmp_path / "new", "done.json") as tmp:
            (tmp / "x").write_text("half")
            raise RuntimeError
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_foreign_file_in_the_way_is_refused_untouched(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("the user's")
    with pytest.raises(OutputError, match="not written by rscasadi.*a.txt"):
        _write(out, ["a.txt"])
    assert [p.name for p in out.iterdir()] == ["a.txt"] and (out / "a.txt").read_text() == "the user's"


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
