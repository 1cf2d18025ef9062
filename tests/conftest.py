"""Fixtures: the reference arm and random valid arms written as real model files."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import rscasadi
from rscasadi.model.modelfile import to_toml  # noqa: F401  (tests write model files)

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "problems" / "arm3.toml"


def random_body(rng, mass_range, size, balanced=False):
    """A physically valid body: inertia of a random box (triangle inequality holds), rotated."""
    m = rng.uniform(*mass_range)
    a, b, c = rng.uniform(0.2, 1.0, 3) * size
    if balanced:
        r, h = a / 2, b                                        # a cylinder about z
        I = np.diag([m * (3 * r * r + h * h) / 12] * 2 + [m * r * r / 2])
        com = [0.0, 0.0, rng.uniform(-0.02, 0.02)]
    else:
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        I = Q @ np.diag([m * (b * b + c * c), m * (a * a + c * c), m * (a * a + b * b)]) / 12 @ Q.T
        com = rng.uniform(-0.5, 0.5, 3) * size
    return {"mass": m, "com": com, "inertia": [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]}


def random_arm_doc(rng, n, balanced=False):
    """Random geometry (axes at any angle), gear ratios 2..120, nonlinear springs and losses."""
    joints = []
    for j in range(n):
        joints.append({
            "name": f"j{j + 1}",
            "origin_xyz": rng.uniform(-0.3, 0.3, 3),
            "origin_rpy": rng.uniform(-np.pi, np.pi, 3),
            "gear_ratio": rng.uniform(2.0, 120.0),
            "sea": {"k1": rng.uniform(200, 2000), "k3": rng.uniform(0, 5000), "d": rng.uniform(0, 2)},
            "gear_loss": {"b": rng.uniform(0, 2), "c": rng.uniform(0, 0.5), "eps": rng.uniform(0.005, 0.05)},
            "link": random_body(rng, (0.5, 3.0), 0.4),
            "slow_rotor": random_body(rng, (0.1, 0.5), 0.08, balanced),
            "fast_rotor": random_body(rng, (0.05, 0.3), 0.05, balanced),
        })
    return {"name": f"random-{n}", "gravity": rng.normal(size=3) * 5, "joints": joints}


def random_tree_doc(rng, n, balanced=False):
    """random_arm_doc's joints in a random tree: joint 1 on the base, every later one on the base
    (one in five) or on the link of any joint before it, named by `parent`; at least one link
    carries two joints."""
    doc = random_arm_doc(rng, n, balanced)
    parents = [-1] + [-1 if rng.uniform() < 0.2 else int(rng.integers(0, j)) for j in range(1, n)]
    if n >= 3 and len(set(parents)) == n:
        parents[-1] = parents[-2]
    for jt, p in zip(doc["joints"], parents):
        jt["parent"] = "base" if p < 0 else f"j{p + 1}"
    doc["name"] = f"random-tree-{n}"
    return doc


def with_kinds(doc, kinds, rng=None):
    """The link-list document `doc` with its joints of `kinds` (rscasadi.model.kinds), in order:
    a geared joint keeps its rotors and gear, no spring; spring, free and direct joints keep only
    their links (a spring joint gets a spring to a rest angle, `rng` choosing both)."""
    rng = rng or np.random.default_rng(0)
    for jt, kind in zip(doc["joints"], kinds):
        if kind == "sea":
            continue
        jt["kind"] = kind
        del jt["sea"]
        jt.get("gear_loss", {}).pop("c1", None)
        if kind in ("spring", "free", "direct"):
            for key in ("gear_ratio", "slow_rotor", "fast_rotor", "gear_loss", "torque_constant"):
                jt.pop(key, None)
            lim = jt.get("limits", {})
            for key in ("dphi", "psi") + (("tau",) if kind != "direct" else ()):
                lim.pop(key, None)
        elif kind == "geared":
            jt.get("limits", {}).pop("psi", None)
        if kind == "spring":
            jt["spring"] = {"k": float(rng.uniform(20, 80)), "theta0": float(rng.uniform(-0.3, 0.3))}
    return doc


def check_against_pinocchio(arm, route, rng, frames_of=None):
    """Forward and inverse dynamics, mass matrix, centre of mass, each link's placement and
    Jacobian (frames_of: the frames at the links, default the joints' names), equal to
    Pinocchio's with the rotors as bodies (reference.pinocchio_route) at random states, to 1e-9."""
    import pinocchio as pin
    n, m = arm.n, arm.m
    fd, inv, mass, com = arm.forward_dynamics(), arm.inverse_dynamics(), arm.mass_matrix(), arm.center_of_mass()
    names = frames_of or [jt.name for jt in arm.model.joints]
    place = [arm.frame_placement(f) for f in names]
    jac = [arm.frame_jacobian(f) for f in names]
    rel = lambda a, b: np.max(np.abs(np.asarray(a) - b)) / max(np.max(np.abs(b)), 1e-300)   # noqa: E731
    for _ in range(3):
        x = [rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi, np.pi, m), 2 * rng.normal(size=n), 2 * rng.normal(size=m)]
        tau = rng.normal(size=arm.u)
        ddq = np.concatenate([dm(v) for v in fd(*x, tau)])
        assert rel(ddq, np.concatenate(route.forward_dynamics(*x, tau))) < 1e-9
        M, _ = route.mass_bias(*x)
        assert rel(np.array(mass(x[0], x[1])), M) < 1e-9
        assert rel(dm(inv(*x, ddq[:n], ddq[n:])[0]), tau) < 1e-9
        q = route.G @ np.r_[x[0], x[1]]
        pin.computeJointJacobians(route.model, route.data, q)
        assert rel(dm(com(x[0], x[1])), pin.centerOfMass(route.model, route.data, q)) < 1e-9
        for j, jid in enumerate(route.link_ids):
            R, p = (np.array(v) for v in place[j](x[0]))
            oMi = route.data.oMi[jid]
            assert np.max(np.abs(R - oMi.rotation)) < 1e-9 and np.max(np.abs(p.ravel() - oMi.translation)) < 1e-9
            J = pin.getJointJacobian(route.model, route.data, jid, pin.LOCAL_WORLD_ALIGNED) @ route.G[:, :n]
            assert np.max(np.abs(np.array(jac[j](x[0])) - J)) < 1e-9 * max(1.0, np.max(np.abs(J)))


def mujoco_against_model(arm, m, d, T, x, tau) -> tuple:
    """MuJoCo's model `m` (data `d`, gear map T: rscasadi.export.mujoco.gear_map) at the model's
    state x = (theta, phi, dtheta, dphi) under tau: the relative differences of its mass matrix
    and of its forces (passive, actuators, less bias) from the model's, M and M ddq."""
    import mujoco
    ddq = np.concatenate([dm(v) for v in arm.forward_dynamics()(*x, tau)])
    d.qpos[:], d.qvel[:], d.ctrl[:] = T @ np.r_[x[0], x[1]], T @ np.r_[x[2], x[3]], tau
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    ours = np.array(arm.mass_matrix()(x[0], x[1]))
    rel = lambda a, b: np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)   # noqa: E731
    return rel(T.T @ M @ T, ours), rel(T.T @ (d.qfrc_passive + d.qfrc_actuator - d.qfrc_bias), ours @ ddq)


def write_arm(tmp_path, doc, name="arm.toml"):
    path = Path(tmp_path) / name
    path.write_text(to_toml(doc))
    return path


def heavier_reference(tmp_path) -> Path:
    """The reference arm with 20 % heavier links and 10 % softer springs, its zeros and balanced
    rotors kept: another arm of its parameter family (an identified one, say), as a model file."""
    import copy
    import tomllib
    with open(REFERENCE, "rb") as fh:
        doc = tomllib.load(fh)
    heavier = copy.deepcopy(doc)
    for jt in heavier["joints"]:
        jt["link"]["mass"] *= 1.2
        jt["sea"]["k1"] *= 0.9
    return write_arm(tmp_path, heavier, "heavier.toml")


@pytest.fixture(scope="session")
def arm3():
    return rscasadi.load(REFERENCE)


@pytest.fixture(scope="session")
def random_arms(tmp_path_factory):
    """n = 1..7, unbalanced rotors (complete model only)."""
    rng, d = np.random.default_rng(20261122), tmp_path_factory.mktemp("arms")
    return [rscasadi.load(write_arm(d, random_arm_doc(rng, n), f"arm{n}.toml")) for n in range(1, 8)]


@pytest.fixture(scope="session")
def balanced_arms(tmp_path_factory):
    """n = 1..7, balanced rotors (both models)."""
    rng, d = np.random.default_rng(7), tmp_path_factory.mktemp("barms")
    return [rscasadi.load(write_arm(d, random_arm_doc(rng, n, True), f"arm{n}.toml")) for n in range(1, 8)]


def random_state(rng, n, scale=1.0):
    theta = rng.uniform(-np.pi, np.pi, n)
    return [theta, theta + rng.normal(size=n) * 0.05, rng.normal(size=n) * scale, rng.normal(size=n) * scale]


def dm(v):
    return np.array(v, dtype=float).ravel()


@pytest.fixture(scope="session", autouse=True)
def private_cache(tmp_path_factory, worker_id):
    """Every test session compiles for real (at -O1, fast) into its own cache, which its workers
    share (the build step locks each library: what one worker compiled, the other loads)."""
    mp = pytest.MonkeyPatch()
    base = tmp_path_factory.getbasetemp()
    mp.setenv("RSCASADI_CACHE", str((base if worker_id == "master" else base.parent) / "cache"))
    yield
    mp.undo()


@pytest.fixture(scope="session")
def built(tmp_path_factory, private_cache):
    """The reference arm generated and compiled (-O1): (directory, manifest)."""
    from rscasadi.codegen import generate
    out = tmp_path_factory.mktemp("gen") / "arm3"
    return out, generate(REFERENCE, out, opt="-O1", log=lambda m: None)


@pytest.fixture(scope="session")
def panda_built(tmp_path_factory, private_cache):
    """The Panda (7 joints) generated and compiled (-O1): its directory."""
    from rscasadi.codegen import generate
    out = tmp_path_factory.mktemp("gen") / "panda"
    generate(ROOT / "problems" / "panda_sea.toml", out, opt="-O1", log=lambda m: None)
    return out


def cc():
    return shutil.which("cc") or shutil.which("gcc")


def build_example(name: str, exe, libraries: dict, defines=()):
    """Compile examples/NAME.c as a user would (-std=c99 -Wall -Wextra -Werror -O2) against the
    generated `libraries` ({directory: library name, as in -l}) into `exe`; returns exe."""
    import subprocess
    dirs = list(libraries)
    subprocess.run([cc(), "-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", *[f"-D{d}" for d in defines],
                    *[f"-I{d}" for d in dirs],
                    str(ROOT / "examples" / f"{name}.c"), *[f"-L{d}" for d in dirs],
                    *[f"-l{lib}" for lib in libraries.values()], *[f"-Wl,-rpath,{d}" for d in dirs], "-lm",
                    "-o", str(exe)], check=True)
    return exe


# ------------------------------------------------------------- optimal-control problems

@pytest.fixture(scope="session")
def pitch_arm(tmp_path_factory):
    """The reference arm's shoulder pitch alone: one joint working against gravity."""
    import tomllib
    with open(REFERENCE, "rb") as fh:
        doc = tomllib.load(fh)
    doc["joints"] = [doc["joints"][1]]
    d = tmp_path_factory.mktemp("ocp")
    (d / "pitch.toml").write_text(to_toml(doc))
    return d


TABLES = ("transcription", "solver", "design", "refinement", "verification")


def problem(directory, name="p.toml", **over):
    """Write a problem file for the pitch arm: top-level fields and tables ([transcription] is
    merged into a small default: 40 intervals, not compiled)."""
    text = {"model": "pitch.toml", "objective": "min_effort", "theta_start": [0.2], "theta_end": [0.9],
            "duration": 1.0}
    text.update({k: v for k, v in over.items() if k not in TABLES})
    tables = {"transcription": {"method": "radau", "degree": 3, "intervals": 40, "dynamics": "explicit",
                                "compiled": False}}
    tables["transcription"].update(over.get("transcription", {}))
    tables.update({k: v for k, v in over.items() if k in TABLES and k != "transcription"})
    body = to_toml(text) + "".join(f"\n[{t}]\n" + "".join(f"{json.dumps(k)} = {json.dumps(v)}\n" for k, v in d.items())
                                   for t, d in tables.items())
    path = directory / name
    path.write_text(body)
    return path


def raw_solve(monkeypatch, p, **kw):
    """solve_once, keeping the solver's raw result too (x, lam_g, lam_x as flat arrays; its stats;
    the solver and its arguments as "solver" and "args", to call it again)."""
    from rscasadi.ocp import solve_once, solvers
    raw, make = {}, solvers.make_solver

    def spy(*a, **k):
        s, f = make(*a, **k)

        class Kept:
            def __call__(self, **kw):
                res = s(**kw)
                raw.update({key: np.array(v, float).ravel() for key, v in res.items()})
                raw.update(stats=s.stats(), solver=s, args=kw)
                return res

            def stats(self):
                return s.stats()
        return Kept(), f
    monkeypatch.setattr("rscasadi.ocp.solving.make_solver", spy)
    sol = solve_once(p, **{"print_level": 0, "log": lambda m: None, **kw})
    return sol, raw


# ----------------------------------------------------------------------------- identification workflow
# (session-wide: the identification tests and the MPC's identified-model study share them)

from rscasadi.cli import main  # noqa: E402
from rscasadi.sim.trajectory import load_trajectory  # noqa: E402
from rscasadi.identification.logs import write_log  # noqa: E402
from rscasadi.identification.synthetic import perturbed_arm, record  # noqa: E402


@pytest.fixture(scope="session")
def excitation(tmp_path_factory):
    out = tmp_path_factory.mktemp("excite") / "arm3"
    assert main(["excite", str(REFERENCE), "--out", str(out), "--period", "10", "--harmonics", "5"]) == 0
    return out


@pytest.fixture(scope="session")
def synthetic(excitation, arm3, tmp_path_factory):
    """A different arm (every parameter off by 10-40 %, k3 and Coulomb added), its logs under
    the excitation (identification) and under the paper's trajectory (held out)."""
    rng = np.random.default_rng(2026)
    true = perturbed_arm(arm3, rng)
    d = tmp_path_factory.mktemp("logs")
    logs = {}
    for name, traj in (("identification", load_trajectory(excitation / "trajectory.toml")),
                       ("validation", load_trajectory(ROOT / "problems" / "trajectory_arm3.toml"))):
        lg, _ = record(true, arm3, traj, rng=rng)
        write_log(d / f"{name}.csv", lg)
        logs[name] = d / f"{name}.csv"
    return true, logs


@pytest.fixture(scope="session")
def identified(synthetic, tmp_path_factory):
    _, logs = synthetic
    out = tmp_path_factory.mktemp("ident") / "arm3"
    assert main(["identify", str(REFERENCE), str(logs["identification"]), "--out", str(out),
                 "--validate", str(logs["validation"])]) == 0
    return out


# The two CI workers take whole files (--dist loadfile) in collection order: the longest files
# first, so that no single long file runs alone at the end (the whole-robot day is one 2 min
# test, last in the alphabet; the type checker one 30 s test near it).
LONGEST_FIRST = ("test_whole_robot.py", "test_tasks.py", "test_mpc.py", "test_link_side_logs.py", "test_identification.py",
                 "test_types.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONGEST_FIRST)))
