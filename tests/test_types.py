"""The package's annotations hold: mypy at the strictness stated in pyproject.toml ([tool.mypy])."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_package_passes_the_type_checker(tmp_path):
    run = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(tmp_path / "cache")], cwd=ROOT,
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]


def test_the_type_checker_would_notice(tmp_path):
    """The same configuration refuses a module that passes a str where an int is declared."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f(n: int) -> int:\n    return n\n\n\nf('three')\n")
    run = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(tmp_path / "cache"),
                          "--config-file", str(ROOT / "pyproject.toml"), str(bad)], cwd=ROOT,
                         capture_output=True, text=True)
    assert run.returncode == 1 and "arg-type" in run.stdout, run.stdout
