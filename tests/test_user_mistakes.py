"""A user's mistake gets one clear line and a non-zero exit, never a traceback or a hang: generated
broken model files, URDFs and problem files thrown at the loaders, and the commands run on wrong
paths as a new user would."""
import copy
import os
import re
import tomllib

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import rscasadi
from rscasadi import ModelFileError
from rscasadi.cli import main
from rscasadi.ocp import load_problem
from rscasadi.ocp.sweep import load_sweep

from conftest import REFERENCE, ROOT, to_toml

PANDA = ROOT / "problems" / "panda_sea.toml"
PROBLEM = ROOT / "problems" / "ocp_min_time.toml"
# CI explores the same examples on every run (derandomize); RSCASADI_FUZZ=N explores N fresh ones locally.
SETTINGS = settings(max_examples=int(os.environ.get("RSCASADI_FUZZ", 60)), deadline=5000,
                    derandomize=bool(os.environ.get("CI")) and "RSCASADI_FUZZ" not in os.environ,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])

values = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
                   st.text(max_size=8), st.lists(st.floats(-10, 10), max_size=7),
                   st.dictionaries(st.text(max_size=5), st.floats(-1, 1), max_size=3))


def _paths(doc, prefix=()):
    """Every (container, key) of a decoded TOML document."""
    items = doc.items() if isinstance(doc, dict) else enumerate(doc)
    for key, value in items:
        yield doc, key
        if isinstance(value, (dict, list)):
            yield from _paths(value, prefix + (key,))


@st.composite
def mutated(draw, doc):
    doc = copy.deepcopy(doc)
    for _ in range(draw(st.integers(1, 3))):
        places = list(_paths(doc))
        if not places:
            break
        container, key = draw(st.sampled_from(places))
        if draw(st.booleans()) and isinstance(container, dict):
            del container[key]
        else:
            container[key] = draw(values)
    return doc


def _toml_value(v):
    return v is not None and not (isinstance(v, dict) and any(x is None for x in v.values()))


def _write_doc(path, doc) -> bool:
    """Write a document as TOML; False when it holds something TOML cannot say (None)."""
    try:
        path.write_text(to_toml(doc))
    except (TypeError, ValueError, AttributeError):
        return False
    return True


def _must_be_named_error(load, path):
    try:
        load(path)
    except ModelFileError as exc:
        assert str(path.name) in str(exc) or "urdf" in str(exc).lower(), str(exc)


with open(REFERENCE, "rb") as fh:
    REFERENCE_DOC = tomllib.load(fh)
with open(PANDA, "rb") as fh:
    PANDA_DOC = tomllib.load(fh)
PANDA_DOC["urdf"] = str(ROOT / "problems" / "urdf" / "panda.urdf")
with open(PROBLEM, "rb") as fh:
    PROBLEM_DOC = tomllib.load(fh)
PROBLEM_DOC["model"] = str(REFERENCE)
with open(ROOT / "problems" / "ocp_min_time_codesign.toml", "rb") as fh:
    CODESIGN_DOC = tomllib.load(fh)
CODESIGN_DOC["model"] = str(REFERENCE)
with open(ROOT / "problems" / "sweep_spring_stiffness.toml", "rb") as fh:
    SWEEP_DOC = tomllib.load(fh)
SWEEP_DOC["problem"] = str(PROBLEM)
URDF_TEXT = (ROOT / "problems" / "urdf" / "panda.urdf").read_text()


KINDS = {"model file": (REFERENCE_DOC, rscasadi.load), "URDF-form model file": (PANDA_DOC, rscasadi.load),
         "problem file": (PROBLEM_DOC, load_problem), "co-design problem file": (CODESIGN_DOC, load_problem),
         "sweep file": (SWEEP_DOC, load_sweep)}


@pytest.mark.parametrize("kind", list(KINDS))
@SETTINGS
@given(data=st.data())
def test_broken_files_are_refused_by_name(tmp_path, kind, data):
    doc, load = KINDS[kind]
    path = tmp_path / "broken.toml"
    if _write_doc(path, data.draw(mutated(doc))):
        _must_be_named_error(load, path)


ATTRIBUTE = re.compile(r'(\w+)="([^"]*)"')


@st.composite
def broken_urdf(draw):
    text = URDF_TEXT
    how = draw(st.sampled_from(["attribute", "cut", "element", "garbage"]))
    if how == "attribute":
        spots = list(ATTRIBUTE.finditer(text))
        m = spots[draw(st.integers(0, len(spots) - 1))]
        new = draw(st.one_of(st.text(max_size=6), st.sampled_from(["nan", "inf", "-1", "0 0 0", "1e400", "", "a b c"])))
        text = text[:m.start(2)] + new.replace('"', "").replace("<", "").replace("&", "") + text[m.end(2):]
    elif how == "cut":
        text = text[:draw(st.integers(0, len(text) - 1))]
    elif how == "element":
        tags = list(re.finditer(r"<(inertial|joint|link|origin|axis|mass|inertia|limit)\b[^>]*/>", text))
        m = tags[draw(st.integers(0, len(tags) - 1))]
        text = text[:m.start()] + text[m.end():]
    else:
        text = draw(st.text(max_size=40))
    return text


@SETTINGS
@given(text=broken_urdf())
def test_broken_urdfs_are_refused_by_name(tmp_path, text):
    (tmp_path / "panda.urdf").write_text(text)
    doc = copy.deepcopy(PANDA_DOC)
    doc["urdf"] = "panda.urdf"
    path = tmp_path / "panda.toml"
    path.write_text(to_toml(doc))
    try:
        rscasadi.load(path)
    except ModelFileError as exc:
        assert "panda" in str(exc), str(exc)


def _one_line_error(capsys, argv):
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code not in (0, None), argv
    assert err.startswith("rscasadi: error:") and "Traceback" not in err, err
    return err


def test_commands_on_wrong_paths_say_one_line(tmp_path, capsys):
    a_file = tmp_path / "a_file.txt"
    a_file.write_text("not a directory\n")
    assert "not a directory" in _one_line_error(capsys, ["codegen", str(REFERENCE), "--out", str(a_file)])
    assert "not a directory" in _one_line_error(capsys, ["paper", "--out", str(a_file), "--no-sweep", "--ocp", ""])
    assert "a_file.txt" in _one_line_error(capsys, ["info", str(a_file)])
    assert "missing.toml" in _one_line_error(capsys, ["info", str(tmp_path / "missing.toml")])
    assert "missing.toml" in _one_line_error(capsys, ["ocp", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "o")])
    _one_line_error(capsys, ["info", str(tmp_path)])                          # a directory as a model file
    (tmp_path / "binary.toml").write_bytes(b"\x00\xff\xfe garbage")
    assert "binary.toml" in _one_line_error(capsys, ["info", str(tmp_path / "binary.toml")])


# ----------------------------------------------------------------------------- command-line options
# Every numeric or enumerated option of every command: a value that passes the parser is one the
# command can use (finite and in range); any other is refused by the parser in one line naming the
# option, exit 2, before any work.
from rscasadi.cli import build_parser  # noqa: E402

OPTIONS = {   # command, required arguments, option -> predicate of an accepted value
    ("excite", ("m.toml", "--out", "o")): {"--period": lambda v: 0 < v < float("inf"),
                                           "--harmonics": lambda v: isinstance(v, int) and v >= 3,
                                           "--margin": lambda v: 0 < v <= 1,
                                           "--max-condition": lambda v: 0 < v < float("inf")},
    ("identify", ("m.toml", "log.csv", "--out", "o")): {"--cutoff": lambda v: 0 < v < float("inf")},
    ("paper", ()): {"--duration": lambda v: 0 < v < float("inf")},
    ("mpc", ("p.toml",)): {"--study": lambda v: 0 <= v < float("inf"), "--opt": lambda v: v.startswith("-O")},
    ("sweep", ("s.toml",)): {"--workers": lambda v: isinstance(v, int) and v >= 1},
    ("codegen", ("m.toml", "--out", "o")): {"--opt": lambda v: v.startswith("-O") and ";" not in v},
    ("ocp", ("p.toml",)): {"--solver": lambda v: v in ("ipopt", "fatrop")},
}
CASES = [(cmd, req, opt, ok) for (cmd, req), opts in OPTIONS.items() for opt, ok in opts.items()]
option_values = st.one_of(st.integers(-10, 10).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                          st.sampled_from(["0", "-0", "nan", "inf", "-inf", "1e400", "", "abc", "-O3", "-O9", "-O2;ls", "--",
                                           "ipopt", "fatrop", "2.5", "3", " 4"]),
                          st.text(max_size=6))


@pytest.mark.parametrize("cmd, required, option, accepted", CASES, ids=[f"{c[0]} {c[2]}" for c in CASES])
@SETTINGS
@given(value=option_values)
def test_command_line_options_are_checked_up_front(capsys, cmd, required, option, accepted, value):
    try:
        args = build_parser().parse_args([cmd, *required, f"{option}={value}"])
    except SystemExit as exc:
        err = capsys.readouterr().err.strip()
        assert exc.code == 2 and len(err.splitlines()) == 1, err
        assert err.startswith(f"rscasadi {cmd}: error:") and option in err and "Traceback" not in err, err
        return
    assert accepted(getattr(args, option.lstrip("-").replace("-", "_"))), (option, value)


@pytest.mark.parametrize("argv, words", [
    (["excite", "m.toml", "--out", "o", "--period", "0"], "--period: must be > 0"),
    (["excite", "m.toml", "--out", "o", "--period", "-1"], "--period: must be > 0"),
    (["excite", "m.toml", "--out", "o", "--harmonics", "0"], "--harmonics: must be >= 3"),
    (["paper", "--duration", "-1"], "--duration: must be > 0"),
    (["mpc", "p.toml", "--study", "-5"], "--study: must be >= 0"),
    (["sweep", "s.toml", "--workers", "0"], "--workers: must be > 0"),
])
def test_the_options_a_new_user_got_wrong(capsys, argv, words):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and words in err and len(err.splitlines()) == 1, err


@pytest.mark.parametrize("command,name,line,field", [
    ("ocp", "ocp_min_time.toml", "[transcription]\n", "transcription.intervals"),
    ("mpc", "mpc_arm3.toml", "\n", "horizon"),
    ("mpc", "mpc_arm3.toml", "\n", "qp_iterations"),
])
def test_sizes_beyond_the_machine_are_refused_up_front(command, name, line, field, tmp_path, capsys):
    """intervals = 100000000 took 23 GB before the kernel killed it; now refused at once with
    the limit named, nothing written."""
    import shutil
    for f in ("arm3.toml", "trajectory_arm3.toml"):
        shutil.copy(ROOT / "problems" / f, tmp_path / f)
    text = (ROOT / "problems" / name).read_text()
    key = field.split(".")[-1]
    text = re.sub(rf"^{key} = .*$", "", text, flags=re.M)
    text = text.replace(line, f"{line}{key} = 100000000\n", 1) if line.strip() else f"{key} = 100000000\n" + text
    problem = tmp_path / name
    problem.write_text(text)
    assert main([command, str(problem), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"field '{field}'" in err and "at most" in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()
