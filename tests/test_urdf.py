"""URDF-based model files: real arms against Pinocchio parsing the same URDF, the reference arm
in both forms, and every refusal naming the file and the element."""
import copy
import json
import tomllib

import numpy as np
import pytest

import rscasadi
from rscasadi import ModelFileError
from rscasadi.reference.pinocchio_route import PinocchioRoute

from conftest import REFERENCE, ROOT, dm, random_state, to_toml

REAL_ARMS = [ROOT / "problems" / "panda_sea.toml", ROOT / "problems" / "ur5_sea.toml"]


@pytest.fixture(scope="module", params=REAL_ARMS, ids=["panda", "ur5"])
def real_arm(request):
    return rscasadi.load(request.param)


def test_real_arms_equal_pinocchio_on_the_same_urdf(real_arm):
    """Pinocchio parses the URDF, merges the fixed links and locks the fingers by its own code."""
    route, n, rng = PinocchioRoute.from_urdf(real_arm.model), real_arm.n, np.random.default_rng(5)
    fd, M_f = real_arm.forward_dynamics(), real_arm.mass_matrix()
    for _ in range(4):
        x, tau = random_state(rng, n, 2.0), rng.normal(size=n)
        M_pin, c_pin = route.mass_bias(*x)
        assert np.max(np.abs(np.array(M_f(x[0], x[1])) - M_pin)) < 1e-9 * np.max(np.abs(M_pin))
        ours = np.concatenate([dm(v) for v in fd(*x, tau)])
        theirs = np.concatenate(route.forward_dynamics(*x, tau))
        assert np.max(np.abs(ours - theirs)) < 1e-9 * np.max(np.abs(theirs))


def test_panda_chain_merges_hand_and_fingers():
    arm = rscasadi.load(REAL_ARMS[0])
    assert arm.n == 7 and [jt.name for jt in arm.model.joints] == [f"panda_joint{i}" for i in range(1, 8)]
    assert set(arm.model.extra["links"][-1]) >= {"panda_link7", "panda_hand", "panda_leftfinger"}
    # link 7 (0.735522) + hand (0.73) + two fingers (0.015 each) of the URDF
    assert arm.model.joints[-1].link.mass == pytest.approx(0.735522 + 0.73 + 0.03, abs=1e-12)
    assert arm.model.joints[3].limits["theta"] == (-3.0718, -0.0698)     # from the URDF's <limit>


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _inertial(body, R):
    """<inertial> of a body whose frame is turned by R relative to the URDF link frame."""
    com, I = (R @ body.com).tolist(), (R @ body.inertia @ R.T).tolist()
    return (f'<inertial><origin xyz="{com[0]!r} {com[1]!r} {com[2]!r}" rpy="0 0 0"/><mass value="{body.mass!r}"/>'
            f'<inertia ixx="{I[0][0]!r}" iyy="{I[1][1]!r}" izz="{I[2][2]!r}" ixy="{I[0][1]!r}" ixz="{I[0][2]!r}" '
            f'iyz="{I[1][2]!r}"/></inertial>')


def reference_urdf(model) -> str:
    """The reference arm as a URDF, written by hand from problems/arm3.toml's numbers, with joints 2 and 3
    turning about -y of an unrotated joint frame (instead of z of a frame turned by Rx(pi/2)),
    so the link frames of the URDF differ from ours by Rx(pi/2); plus a massless tool link on a
    fixed joint and a locked prismatic joint, which must change nothing."""
    j1, j2, j3 = model.joints
    Ra = _rx(np.pi / 2)                          # our L_j = L_urdf Ra for joints 2 and 3
    return f"""<?xml version="1.0"?>
<robot name="arm3">
  <link name="base"/>
  <joint name="shoulder_yaw" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.10" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>
  <link name="l1">{_inertial(j1.link, np.eye(3))}</link>
  <joint name="shoulder_pitch" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0 0.25" rpy="0 0 0"/><axis xyz="0 -1 0"/><limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>
  <link name="l2">{_inertial(j2.link, Ra)}</link>
  <joint name="elbow_pitch" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="0.35 0 0" rpy="0 0 0"/><axis xyz="0 -1 0"/><limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>
  <link name="l3">{_inertial(j3.link, Ra)}</link>
  <joint name="tool_fixed" type="fixed"><parent link="l3"/><child link="tool"/><origin xyz="0.3 0 0" rpy="0 0 0"/></joint>
  <link name="tool"/>
  <joint name="slide" type="prismatic"><parent link="tool"/><child link="pad"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="0.1" effort="1" velocity="1"/></joint>
  <link name="pad"/>
</robot>
"""


def urdf_form_doc(old: dict, urdf: str) -> dict:
    keep = ("name", "gear_ratio", "sea", "gear_loss", "limits", "slow_rotor", "fast_rotor")
    return {"name": old["name"], "urdf": urdf, "locked": {"slide": 0.05},
            "joints": [{k: jt[k] for k in keep if k in jt} for jt in old["joints"]]}


@pytest.fixture(scope="module")
def old_doc():
    with open(REFERENCE, "rb") as fh:
        return tomllib.load(fh)


@pytest.fixture
def urdf_dir(tmp_path, arm3, old_doc):
    (tmp_path / "arm3.urdf").write_text(reference_urdf(arm3.model))
    (tmp_path / "arm3_urdf.toml").write_text(to_toml(urdf_form_doc(old_doc, "arm3.urdf")))
    return tmp_path


def test_reference_arm_in_both_forms_is_the_same_arm(arm3, urdf_dir):
    twin = rscasadi.load(urdf_dir / "arm3_urdf.toml")
    rng = np.random.default_rng(8)
    for _ in range(3):
        x = random_state(rng, 3, 2.0)
        acc, tau = rng.normal(size=6), rng.normal(size=3)
        for name, args in (("forward_dynamics", (*x, tau)), ("inverse_dynamics", (*x, acc[:3], acc[3:])),
                           ("energy", x), ("mass_matrix", x[:2])):
            a, b = (np.concatenate([dm(v) for v in getattr(arm, name)().call(list(args))]) for arm in (arm3, twin))
            assert np.max(np.abs(a - b)) < 1e-12 * max(1.0, np.max(np.abs(a))), name


# ----------------------------------------------------------------------------- refusals

def _write(d, doc, urdf_text=None):
    if urdf_text is not None:
        (d / "arm3.urdf").write_text(urdf_text)
    path = d / "arm3_urdf.toml"
    path.write_text(to_toml(doc))
    return path


URDF_CASES = [
    # (how the URDF text changes, words expected in the message)
    (lambda u: u.replace('<joint name="slide" type="prismatic">', '<joint name="slide" type="floating">'), "slide"),
    (lambda u: u.replace('<axis xyz="0 -1 0"/><limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>\n'
                         '  <link name="l3">', '<axis xyz="1 0 0"/><limit lower="-3.1" upper="3.1" effort="1" '
                         'velocity="1"/></joint>\n  <link name="l3">').replace(
        'type="revolute"><parent link="l2"/>', 'type="prismatic"><parent link="l2"/>'), "elbow_pitch"),
    (lambda u: u.replace('<link name="tool"/>', ''), "tool"),
    (lambda u: u.replace('ixx="0.012"', 'ixx="-0.012"'), "l1"),
    (lambda u: u.replace('<robot name="arm3">', '<robot name="arm3"><link'), "arm3.urdf"),
    (lambda u: u.replace('<link name="l2">', '<link name="l2x"/><link name="l2_unused">'), "l2"),
]


@pytest.mark.parametrize("mutate, words", URDF_CASES)
def test_broken_urdf_is_refused_naming_the_element(urdf_dir, arm3, old_doc, mutate, words):
    text = reference_urdf(arm3.model)
    broken = mutate(text)
    assert broken != text
    path = _write(urdf_dir, urdf_form_doc(old_doc, "arm3.urdf"), broken)
    with pytest.raises(ModelFileError) as err:
        rscasadi.load(path)
    assert words in str(err.value)


def test_refusals_of_the_model_file(urdf_dir, old_doc):
    cases = [
        (lambda d: d["joints"][1].update(name="no_such_joint"), "no_such_joint"),
        (lambda d: d["joints"].pop(2), "elbow_pitch"),                     # moving, no entry, not locked
        (lambda d: d["locked"].update(ghost=0.1), "ghost"),
        (lambda d: d.update(locked=False), "'locked'"),                    # not a table (found by the fuzzer)
        (lambda d: d.update(tip="l2"), "tip"),                               # elbow beyond the tip
        (lambda d: d.update(urdf="missing.urdf"), "missing.urdf"),
        (lambda d: d["joints"][0].update(link={"mass": 1.0}), "link"),       # links come from the URDF
        (lambda d: d["joints"].reverse(), "base to tip"),
        (lambda d: d["joints"][2].update(slow_rotor={"mass": 0.2, "com": [0, 0, 0], "inertia": [1, 1, 3, 0, 0, 0]}),
         "triangle"),
    ]
    for mutate, words in cases:
        doc = copy.deepcopy(urdf_form_doc(old_doc, "arm3.urdf"))
        mutate(doc)
        with pytest.raises(ModelFileError) as err:
            rscasadi.load(_write(urdf_dir, doc))
        assert words in str(err.value) and "arm3_urdf.toml" in str(err.value)


def test_commands_take_the_urdf_form(tmp_path, capsys):
    """info and codegen on a URDF-based file; the compiled forward dynamics of the UR5 (axes
    along y) equals Pinocchio parsing the URDF."""
    from rscasadi.cli import main
    ur5 = REAL_ARMS[1]
    assert main(["info", str(ur5)]) == 0
    assert "shoulder_lift_joint" in capsys.readouterr().out
    assert main(["codegen", str(ur5), "--out", str(tmp_path / "ur5"), "--opt=-O1"]) == 0
    fd = rscasadi.load_compiled(tmp_path / "ur5")["forward_dynamics"]
    arm = rscasadi.load(ur5)
    route, rng = PinocchioRoute.from_urdf(arm.model), np.random.default_rng(9)
    x, tau = random_state(rng, 6), rng.normal(size=6)
    ours = np.concatenate([dm(v) for v in fd(*x, tau)])
    theirs = np.concatenate(route.forward_dynamics(*x, tau))
    assert np.max(np.abs(ours - theirs)) < 1e-9 * np.max(np.abs(theirs))
    traj = tmp_path / "ur5_motion.toml"
    traj.write_text(f'model = "{ur5}"\nperiod = 2.0\nduration = 0.3\nstart = [0.0, -1.0, 1.0, -1.0, 0.5, 0.0]\n'
                    'amplitude = [0.5, 0.3, -0.4, 0.3, 0.3, 0.5]\n')
    assert main(["paper", "--trajectory", str(traj), "--out", str(tmp_path / "paper"), "--no-sweep", "--ocp", ""]) == 0
    tracking = json.loads((tmp_path / "paper" / "tracking.json").read_text())
    assert max(tracking["methods"]["rotor_separated"]["max_error"]) < 1e-5         # the feedforward tracks on the UR5 too


def test_a_model_file_read_again_is_parsed_again_only_when_it_or_its_urdf_changed(arm3, urdf_dir):
    """read() keeps a parsed model while its file and its URDF are unchanged, byte for byte: an
    edit of either (here of the same length, right after the read, within the clock's tick) is
    read; each call returns its own copy."""
    from rscasadi.model.modelfile import read
    path, urdf = urdf_dir / "arm3_urdf.toml", urdf_dir / "arm3.urdf"
    first = read(path)
    again = read(path)
    again.extra["locked"]["x"] = 1.0
    assert again is not first and "x" not in read(path).extra["locked"]
    mass = lambda m: m.joints[0].link.mass
    text = urdf.read_text()
    heavier = text.replace('<mass value="2.5"/>', '<mass value="3.5"/>', 1)
    assert heavier != text and len(heavier) == len(text)
    urdf.write_text(heavier)
    assert mass(read(path)) != mass(first)                               # the URDF's edit
    doc = path.read_text()
    assert "gear_ratio = 100.0" in doc
    path.write_text(doc.replace("gear_ratio = 100.0", "gear_ratio = 900.0", 1))
    assert read(path).joints[0].gear_ratio == 900.0                       # the model file's edit


def test_a_new_process_finds_the_parsed_model_until_a_file_changes(urdf_dir, monkeypatch):
    """The cache directory keeps a parsed model for the next process: found without parsing while
    the model file and its URDF hash the same; an edit of the URDF (same length) or a damaged
    entry is parsed again."""
    from rscasadi.model import modelfile
    path, urdf = urdf_dir / "arm3_urdf.toml", urdf_dir / "arm3.urdf"
    first = modelfile.read(path)
    parse = modelfile.parse
    monkeypatch.setattr(modelfile, "_READ", {})                          # a new process
    monkeypatch.setattr(modelfile, "parse", lambda *a: pytest.fail("parsed although unchanged"))
    found = modelfile.read(path)
    assert found.joints[0].link.mass == first.joints[0].link.mass and found.path == first.path
    text = urdf.read_text()
    urdf.write_text(text.replace('<mass value="2.5"/>', '<mass value="3.5"/>', 1))
    monkeypatch.setattr(modelfile, "_READ", {})
    monkeypatch.setattr(modelfile, "parse", parse)
    assert modelfile.read(path).joints[0].link.mass == 3.5
    modelfile._entry((str(path), str(path.resolve())), modelfile._stamps([path.resolve()])).write_bytes(b"damaged")
    monkeypatch.setattr(modelfile, "_READ", {})
    assert modelfile.read(path).joints[0].link.mass == 3.5
