"""Every rule of docs/user-guide/model.md section 4 refuses a bad file with the file, the joint and the field."""
import tomllib

import numpy as np
import pytest

import rscasadi
from rscasadi import ModelFileError

from conftest import REFERENCE, to_toml


@pytest.fixture
def doc():
    with open(REFERENCE, "rb") as fh:
        return tomllib.load(fh)


def set_path(d, path, value):
    keys = path.split(".")
    for k in keys[:-1]:
        d = d[int(k)] if isinstance(d, list) else d[k]
    if value is DELETE:
        del d[keys[-1]]
    else:
        d[keys[-1]] = value


class _Delete:
    def __repr__(self):                 # a stable test id (pytest-xdist workers must agree)
        return "DELETE"


DELETE = _Delete()
CASES = [
    # (path in the document, new value, joint named in the message, field named, words)
    ("name", DELETE, None, "name", "missing"),
    ("name", "", None, "name", "non-empty"),
    ("joints", [], None, "joints", "at least one"),
    ("gravity", [0.0, -9.81], None, "gravity", "3 numbers"),
    ("colour", "red", None, "colour", "unknown key"),
    ("joints.0.name", DELETE, "joint 1", "name", "missing"),
    ("joints.2.name", "shoulder_yaw", "joint 3", "name", "duplicate"),
    ("joints.1.origin_xyz", DELETE, "joint 2", "origin_xyz", "missing"),
    ("joints.1.origin_rpy", [0.0, 0.0], "joint 2", "origin_rpy", "3 numbers"),
    ("joints.1.origin_xyz", [0.0, "a", 0.0], "joint 2", "origin_xyz[1]", "number"),
    ("joints.1.gear_ratio", DELETE, "joint 2", "gear_ratio", "missing"),
    ("joints.1.gear_ratio", 0.0, "joint 2", "gear_ratio", "> 0"),
    ("joints.1.gear_ratio", -50.0, "joint 2", "gear_ratio", "> 0"),
    ("joints.1.gear_ratio", True, "joint 2", "gear_ratio", "number"),
    ("joints.1.gear_ratio", float("nan"), "joint 2", "gear_ratio", "finite"),
    ("joints.2.sea", DELETE, "joint 3", "sea", "missing"),
    ("joints.2.sea.k1", DELETE, "joint 3", "sea.k1", "missing"),
    ("joints.2.sea.k1", 0.0, "joint 3", "sea.k1", "> 0"),
    ("joints.2.sea.k3", -1.0, "joint 3", "sea.k3", ">= 0"),
    ("joints.2.sea.d", -0.1, "joint 3", "sea.d", ">= 0"),
    ("joints.2.sea.k2", 1.0, "joint 3", "sea.k2", "unknown key"),
    ("joints.0.gear_loss.b", -1.0, "joint 1", "gear_loss.b", ">= 0"),
    ("joints.0.gear_loss.c", -1.0, "joint 1", "gear_loss.c", ">= 0"),
    ("joints.0.gear_loss.eps", 0.0, "joint 1", "gear_loss.eps", "> 0"),
    ("joints.0.gear_loss.friction", 1.0, "joint 1", "gear_loss.friction", "unknown key"),
    ("joints.0.limits.tau", 0.0, "joint 1", "limits.tau", "> 0"),
    ("joints.0.limits.dphi", -4.0, "joint 1", "limits.dphi", "> 0"),
    ("joints.0.limits.psi", 0.0, "joint 1", "limits.psi", "> 0"),
    ("joints.0.limits.theta", [1.0, -1.0], "joint 1", "limits.theta", "below"),
    ("joints.0.limits.theta", [1.0], "joint 1", "limits.theta", "2 numbers"),
    ("joints.0.limits.torque", 1.0, "joint 1", "limits.torque", "unknown key"),
    ("joints.0.stiffness", 1.0, "joint 1", "stiffness", "unknown key"),
    ("joints.1.link", DELETE, "joint 2", "link", "missing"),
    ("joints.1.link.mass", DELETE, "joint 2", "link.mass", "missing"),
    ("joints.1.link.mass", 0.0, "joint 2", "link.mass", "> 0"),
    ("joints.1.slow_rotor.mass", -0.3, "joint 2", "slow_rotor.mass", "> 0"),
    ("joints.1.fast_rotor.com", [0.0, 0.0], "joint 2", "fast_rotor.com", "3 numbers"),
    ("joints.1.fast_rotor.inertia", [1e-5, 1e-5, 1e-5], "joint 2", "fast_rotor.inertia", "6 numbers"),
    ("joints.1.link.inertia", [0.002, 0.022, -0.022, 0, 0, 0], "joint 2", "link.inertia", "positive definite"),
    ("joints.1.link.inertia", [0.01, 0.01, 0.01, 0.02, 0, 0], "joint 2", "link.inertia", "positive definite"),
    ("joints.1.link.inertia", [0.002, 0.002, 0.022, 0, 0, 0], "joint 2", "link.inertia", "triangle"),
    ("joints.1.slow_rotor.density", 1.0, "joint 2", "slow_rotor.density", "unknown key"),
]


@pytest.mark.parametrize("path,value,joint,field,words", CASES, ids=[f"{c[0]}={c[1]!r}"[:60] for c in CASES])
def test_rule_is_enforced(tmp_path, doc, path, value, joint, field, words):
    set_path(doc, path, value)
    f = tmp_path / "bad.toml"
    f.write_text(to_toml(doc))
    with pytest.raises(ModelFileError) as err:
        rscasadi.load(f)
    msg = str(err.value)
    assert str(f) in msg
    assert f"field '{field}'" in msg
    assert words in msg
    if joint:
        assert msg.split(": ")[1].startswith(joint)
        name = None if path.endswith(".name") else doc["joints"][int(path.split(".")[1])]["name"]
        if name:
            assert repr(name) in msg
    else:
        assert "joint" not in msg.split("field")[0].replace(str(f), "")


def test_defaults_and_reference_values(arm3):
    m = arm3.model
    assert m.n == 3 and m.name == "fs-sea-3dof"
    assert [jt.name for jt in m.joints] == ["shoulder_yaw", "shoulder_pitch", "elbow_pitch"]
    np.testing.assert_array_equal(m.gravity, [0, 0, -9.81])
    assert [jt.k3 for jt in m.joints] == [0.0] * 3 and [jt.c for jt in m.joints] == [0.0] * 3
    assert [jt.eps for jt in m.joints] == [0.01] * 3
    assert m.joints[2].limits == {"tau": 0.4, "dphi": 4.0, "psi": 0.15, "theta": (-3.1, 3.1)}
    assert m.joints[0].rotor_inertia == pytest.approx(5.0e-4 + 100 ** 2 * 3.5e-5)


def test_optional_tables_may_be_absent(tmp_path, doc):
    for jt in doc["joints"]:
        for key in ("gear_loss", "limits"):
            jt.pop(key, None)
        jt["sea"] = {"k1": 100.0}
    doc.pop("gravity")
    f = tmp_path / "minimal.toml"
    f.write_text(to_toml(doc))
    m = rscasadi.load(f).model
    assert m.joints[0].limits == {} and m.joints[0].b == 0.0 and m.joints[0].d == 0.0
    np.testing.assert_array_equal(m.gravity, [0, 0, -9.81])


def test_unreadable_and_malformed_files(tmp_path):
    with pytest.raises(ModelFileError, match="cannot read model file"):
        rscasadi.load(tmp_path / "absent.toml")
    bad = tmp_path / "broken.toml"
    bad.write_text("name = \n")
    with pytest.raises(ModelFileError, match=r"broken\.toml: not valid TOML"):
        rscasadi.load(bad)


def test_joint_that_is_not_a_table(tmp_path):
    f = tmp_path / "x.toml"
    f.write_text('name = "x"\njoints = [1]\n')
    with pytest.raises(ModelFileError, match=r"joint 1, field '': expected a table"):
        rscasadi.load(f)
