"""The arm's collision geometry from a whole-robot URDF: the hand and the fingers merged into the
last link keep their cylinders and boxes, a mesh is held by its bounding capsule, the sidecar
overrides or adds by frame, the payload has a sphere, and `info --collision` lists it all.
Coverage is checked against Pinocchio's own parse (coal shapes) of the same URDF, placed by its
kinematics."""
import re
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import rscasadi
from conftest import to_toml
from rscasadi import ModelFileError
from rscasadi.model.collision import box_capsules, capsules
from rscasadi.model.meshes import bounding_capsule
from test_whole_robot import BAXTER, sidecar

pin = pytest.importorskip("pinocchio")


def _segment_distance(p, a, b):
    d = b - a
    t = 0.0 if not d.any() else np.clip((p - a) @ d / (d @ d), 0.0, 1.0)
    return np.linalg.norm(p - (a + t * d))


def inside_some(p, caps, tol=1e-9) -> bool:
    return any(_segment_distance(p, a, b) <= r + tol for a, b, r in caps)


@pytest.fixture(scope="module")
def stripped(tmp_path_factory):
    """Baxter without its (unshipped) collision meshes: every remaining shape is a cylinder, a
    sphere or a box, which Pinocchio builds as coal shapes."""
    d = tmp_path_factory.mktemp("baxter")
    text = re.sub(r"<collision>(?:(?!</collision>).)*<mesh(?:(?!</collision>).)*</collision>", "", BAXTER.read_text(),
                  flags=re.S)
    (d / "baxter.urdf").write_text(text)
    return d / "baxter.urdf"


def load(tmp_path, **over):
    doc = sidecar(**over)
    path = tmp_path / "arm.toml"
    path.write_text(to_toml(doc))
    return rscasadi.load(path)


def surface_points(geometry, rng, k=60) -> np.ndarray:
    """Points on a coal shape's surface in its own frame: a box's corners and faces, a
    cylinder's rims and side, a sphere's surface."""
    kind = type(geometry).__name__
    if kind == "Box":
        h = np.asarray(geometry.halfSide)
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
        face = rng.uniform(-1, 1, (k, 3))
        face[np.arange(k), rng.integers(0, 3, k)] = rng.choice([-1.0, 1.0], k)
        return np.vstack([corners, face * h])
    if kind == "Cylinder":
        ang = rng.uniform(0, 2 * np.pi, k)
        z = np.r_[np.full(k // 2, geometry.halfLength), np.full(k - k // 2, -geometry.halfLength)]
        z[::3] = rng.uniform(-geometry.halfLength, geometry.halfLength, len(z[::3]))
        return np.c_[geometry.radius * np.cos(ang), geometry.radius * np.sin(ang), z]
    assert kind == "Sphere", kind
    v = rng.normal(size=(k, 3))
    return geometry.radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def test_the_hand_and_fingers_are_held_by_the_last_links_capsules(stripped, tmp_path):
    """With `[collision]` giving only a margin, every moving link takes the URDF's geometry,
    fixed and locked children included: the wrist's, hand's and gripper base's cylinders and the
    fingers' boxes ride on link 7.  Every point on every such shape, placed by Pinocchio from its
    own parse of the URDF, lies inside a capsule of its link placed by our kinematics."""
    from rscasadi.dynamics.kinematics import body_poses
    from rscasadi.reference.pinocchio_route import configuration, urdf_model
    arm = load(tmp_path, urdf=str(stripped), collision={"margin": 0.02})
    on7 = {c.link for c in arm.model.collision.capsules if c.body == 7}
    assert {"left_wrist", "left_hand_link", "left_gripper_base_link", "l_gripper_l_finger",
            "l_gripper_r_finger_tip"} <= on7
    pm = urdf_model(arm.model)
    pdata = pm.createData()
    geom = pin.buildGeomFromUrdf(pm, str(stripped), pin.GeometryType.COLLISION)
    gdata = geom.createData()
    theta = ca.SX.sym("theta", arm.n)
    poses = ca.Function("poses", [theta], [v for b in range(arm.n + 1) for v in body_poses(arm.model, theta)[b]])
    rng = np.random.default_rng(11)
    checked = set()
    for _ in range(3):
        th = rng.uniform(-1.2, 1.2, arm.n)
        pin.updateGeometryPlacements(pm, pdata, geom, gdata, configuration(pm, th))
        P = [np.array(v) for v in poses(th)]
        for i, obj in enumerate(geom.geometryObjects):
            link = pm.frames[obj.parentFrame].name
            if link not in arm.frames() or arm.model.frame(link).body == 0:
                continue
            body = arm.model.frame(link).body
            R, o = P[2 * body], P[2 * body + 1].ravel()
            caps = [(o + R @ c.a, o + R @ c.b, c.radius) for c in arm.model.collision.capsules if c.body == body]
            M = gdata.oMg[i]
            for p in surface_points(obj.geometry, rng) @ M.rotation.T + M.translation:
                assert inside_some(p, caps), (obj.name, p)
            checked.add(link)
    assert {"left_upper_shoulder", "left_wrist", "l_gripper_r_finger_tip", "left_gripper_base_link"} <= checked


def test_a_box_is_held_by_its_capsules():
    """Random boxes at random poses: every corner and random inner point lies in a capsule; a
    flat box gets several thin ones rather than one fat one."""
    rng = np.random.default_rng(2)
    for _ in range(30):
        size = rng.uniform(0.005, 0.3, 3)
        T = np.eye(4)
        T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        T[:3, 3] = rng.normal(size=3)
        caps = box_capsules(T, size)
        pts = np.vstack([np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]),
                         rng.uniform(-1, 1, (200, 3))]) * size / 2
        for p in pts @ T[:3, :3].T + T[:3, 3]:
            assert inside_some(p, caps)
    flat = box_capsules(np.eye(4), [0.3, 0.2, 0.02])
    assert len(flat) == 4 and max(r for *_, r in flat) < 0.04


def test_a_mesh_is_held_by_its_bounding_capsule(stripped, tmp_path):
    """A collision mesh inside the robot's package (an STL written by trimesh, scaled in the URDF)
    is held by one capsule containing every vertex; a mesh outside the package, or missing, is an
    error naming the link and the file, with the way out."""
    import trimesh
    pkg = tmp_path / "pkg"
    (pkg / "meshes").mkdir(parents=True)
    (pkg / "package.xml").write_text("<package><name>pkg</name></package>")
    mesh = trimesh.creation.cylinder(radius=0.05, height=0.3, sections=24)
    mesh.apply_translation([0.01, 0.0, 0.02])
    mesh.export(pkg / "meshes" / "wrist.stl")
    cylinder = re.search(r'(<link name="left_wrist">.*?<collision>.*?)<cylinder[^>]*/>', stripped.read_text(), re.S)
    text = stripped.read_text().replace(cylinder.group(0), cylinder.group(1) +
                                        '<mesh filename="package://pkg/meshes/wrist.stl" scale="2 2 1"/>', 1)
    (pkg / "baxter.urdf").write_text(text)
    arm = load(tmp_path, urdf=str(pkg / "baxter.urdf"), collision={"margin": 0.0, "links": {"left_wrist": "urdf"}})
    caps = [(c.a, c.b, c.radius) for c in arm.model.collision.capsules if c.link == "left_wrist"]
    assert len(caps) == 1
    f = arm.model.frame("left_wrist")
    verts = mesh.vertices * [2, 2, 1]                    # the wrist's collision origin is the identity
    assert all(inside_some(f.R @ v + f.p, caps, 1e-9) for v in verts)
    assert caps[0][2] < 0.1001 and np.linalg.norm(caps[0][1] - caps[0][0]) < 0.3 + 1e-6      # tight: the cylinder itself
    outside = text.replace("package://pkg/meshes/wrist.stl", str(tmp_path / "elsewhere.stl"))
    mesh.export(tmp_path / "elsewhere.stl")
    (pkg / "outside.urdf").write_text(outside)
    with pytest.raises(ModelFileError, match=r"collision.links.left_wrist.*left_wrist.*elsewhere.stl.*outside.*capsule radius"):
        load(tmp_path, urdf=str(pkg / "outside.urdf"), collision={"links": {"left_wrist": "urdf"}})
    (pkg / "missing.urdf").write_text(text.replace("wrist.stl", "gone.stl"))
    with pytest.raises(ModelFileError, match=r"gone.stl.*not found inside the robot's package"):
        load(tmp_path, urdf=str(pkg / "missing.urdf"), collision={})


def test_bounding_capsule_holds_random_clouds():
    rng = np.random.default_rng(4)
    for _ in range(20):
        pts = rng.normal(size=(rng.integers(1, 80), 3)) * rng.uniform(0.01, 1, 3)
        a, b, r = bounding_capsule(pts)
        assert all(_segment_distance(p, a, b) <= r for p in pts)


def test_the_sidecar_overrides_and_adds_by_frame(stripped, tmp_path):
    """A radius gives that link one capsule from its joint to the tip; [[collision.capsules]] adds
    one in a frame's coordinates; then every URDF shape those do not hold, on the listed links
    and the others, is added and named in the notes: the geometry is never less than the URDF's."""
    arm = load(tmp_path, urdf=str(stripped), collision={
        "margin": 0.01, "tip": "left_gripper", "links": {"left_lower_forearm": 0.07, "left_wrist": 0.09},
        "capsules": [{"frame": "left_gripper", "a": [0.0, 0.0, 0.0], "b": [0.0, 0.0, 0.1], "radius": 0.03}]})
    caps = arm.model.collision.capsules
    assert [(c.link, c.body) for c in caps[:3]] == [("left_lower_forearm", 6), ("left_wrist", 7), ("left_gripper", 7)]
    added = {c.link for c in caps[3:]}
    notes = " ".join(arm.model.collision.notes)
    assert added and all(f"URDF link {name!r}" in notes for name in added)
    assert {"left_upper_shoulder", "left_upper_elbow"} <= added     # links `links` leaves out
    grip = arm.model.frame("left_gripper")
    assert np.allclose(caps[1].b, grip.p) and caps[1].radius == 0.09
    assert np.allclose(caps[2].b, grip.p + grip.R @ [0, 0, 0.1])
    with pytest.raises(ModelFileError, match=r"collision.capsules\[0\].frame.*no frame 'nowhere'"):
        load(tmp_path, urdf=str(stripped), collision={"capsules": [{"frame": "nowhere", "radius": 0.1}]})
    with pytest.raises(ModelFileError, match=r"collision.capsules\[0\].radius"):
        load(tmp_path, urdf=str(stripped), collision={"capsules": [{"frame": "left_gripper", "radius": -1}]})


def test_the_payload_sphere_keeps_clear_and_reads_back(stripped, tmp_path):
    """A payload radius adds a sphere about its com, on its link: the exact clearance to an
    obstacle at the payload's centre is -(radius + margin) whatever the links do; the model
    file written (link-list form) reads back the same capsules and radius."""
    import copy
    import tomllib

    from rscasadi.dynamics.collision import exact_clearance
    from rscasadi.model.modelfile import document, parse
    from rscasadi.ocp.problem import Obstacle
    held = {"frame": "left_gripper", "mass": 1.0, "com": [0.0, 0.0, 0.05], "inertia": [1e-3, 1e-3, 1e-3, 0, 0, 0],
            "radius": 0.04}
    arm = load(tmp_path, urdf=str(stripped), collision={"margin": 0.01}, payload=held)
    sphere = capsules(arm.model)[-1]
    assert sphere.radius == 0.04 and sphere.body == 7
    th = np.full(arm.n, 0.3)
    R, p = (np.array(v) for v in arm.frame_placement("left_gripper")(th))
    centre = p.ravel() + R @ [0.0, 0.0, 0.05]
    tiny = Obstacle("sphere", centre, 1e-6)
    assert float(exact_clearance(arm.model, [tiny])(th)) == pytest.approx(-0.04 - 0.01 - 1e-6, abs=1e-9)
    away = Obstacle("sphere", centre + R @ [0.0, 0.0, 0.3], 0.1)    # beyond the gripper, 0.2 m from its centre
    gap = float(exact_clearance(arm.model, [away])(th))
    assert gap <= 0.2 - 0.04 - 0.01 + 1e-9
    written = document(arm.model)
    again = parse(copy.deepcopy(tomllib.loads(to_toml(written))))
    assert again.payload.radius == 0.04
    assert len(again.collision.capsules) == len(arm.model.collision.capsules)
    for c, d in zip(arm.model.collision.capsules, again.collision.capsules):
        assert c.body == d.body and np.allclose(c.a, d.a, atol=1e-12) and np.allclose(c.b, d.b, atol=1e-12)


def test_info_lists_every_capsule(stripped, tmp_path, capsys):
    from rscasadi.cli import main
    doc = sidecar(urdf=str(stripped), collision={"margin": 0.02, "links": {"left_wrist": "urdf", "left_lower_shoulder": 0.07}},
                  payload={"frame": "left_gripper", "mass": 0.5, "com": [0.0, 0.0, 0.03],
                           "inertia": [1e-4, 1e-4, 1e-4, 0, 0, 0], "radius": 0.05})
    (tmp_path / "arm.toml").write_text(to_toml(doc))
    assert main(["info", str(tmp_path / "arm.toml"), "--collision"]) in (0, None)
    out = capsys.readouterr().out
    assert "l_gripper_l_finger_tip" in out and "payload (left_gripper)" in out and "| 0.0500 |" in out
    notes = out.split("Beside the table, from the URDF:")[1]                # the links `links` leaves out
    assert "URDF link 'left_upper_shoulder'" in notes and "added" in notes


def test_clear_path_goes_around_a_ball_the_straight_line_crosses():
    """The first guess around obstacles (collision.clear_path), checked by the replay's exact
    clearance (segments sampled every r / 8, no smoothing) along the polygon between its nodes."""
    from rscasadi.dynamics.arm import Arm
    from rscasadi.dynamics.collision import clear_path, exact_clearance
    from rscasadi.model.modelfile import read
    from rscasadi.task.objects import Obstacle
    model = read(Path(__file__).resolve().parents[1] / "problems" / "panda_sea.toml")
    start = np.array([-0.412, 0.157, -0.257, -2.085, 0.05, 2.236, 0.089])
    end = np.array([0.412, 0.157, 0.257, -1.7, -0.05, 1.9, 0.089])
    middle = np.array(Arm(model).frame_placement("panda_hand_tcp")((start + end) / 2)[1]).ravel()
    # beside the hand's middle point (at it, the distance's gradient would be 0 / 0)
    ball = Obstacle.from_dict({"kind": "sphere", "center": (middle + [0.0, 0.02, 0.0]).tolist(), "radius": 0.06})
    gap = exact_clearance(model, [ball])
    line = np.linspace(start, end, 41).T
    assert float(np.min(np.array(gap.map(41)(line)))) < -0.05            # the straight line goes through it
    path = clear_path(model, [ball], start, end)
    assert path["success"] and path["min_clearance"] >= 0.01 - 1e-6
    theta = path["theta"]
    assert np.allclose(theta[:, 0], start) and np.allclose(theta[:, -1], end)
    fine = np.hstack([np.linspace(a, b, 5, endpoint=False).T for a, b in zip(theta.T[:-1], theta.T[1:])] + [end[:, None]])
    assert float(np.min(np.array(gap.map(fine.shape[1])(fine)))) > 0.0     # clear between the nodes too


def test_clearance_functions_are_shared_only_by_the_same_geometry():
    """The clearance Functions are built once per geometry and shared (refinement rounds, the
    guess, the replay): the same geometry read again gets the same Function; a moved obstacle, a
    fatter capsule or another margin gets its own, with the value it implies."""
    import dataclasses
    from rscasadi.dynamics.collision import clearance_function, exact_clearance
    from rscasadi.model.modelfile import read
    from rscasadi.task.objects import Obstacle
    path = Path(__file__).resolve().parents[1] / "problems" / "panda_sea.toml"
    model = read(path)
    theta = np.array([-0.412, 0.157, -0.257, -2.085, 0.05, 2.236, 0.089])
    ball = Obstacle.from_dict({"kind": "sphere", "center": [0.45, 0.0, 0.33], "radius": 0.1})
    gap = float(exact_clearance(model, [ball])(theta))
    assert exact_clearance(read(path), [ball]) is exact_clearance(model, [ball])
    assert clearance_function(read(path), [ball]) is clearance_function(model, [ball])
    moved = Obstacle.from_dict({"kind": "sphere", "center": [0.45, 0.0, 0.43], "radius": 0.1})
    assert abs(float(exact_clearance(model, [moved])(theta)) - gap) > 1e-3
    wider = dataclasses.replace(model, collision=dataclasses.replace(model.collision, margin=model.collision.margin + 0.01))
    assert np.isclose(float(exact_clearance(wider, [ball])(theta)), gap - 0.01)
    smooth = np.array(clearance_function(model, [ball])(theta)).ravel()
    assert np.allclose(np.array(clearance_function(wider, [ball])(theta)).ravel(), smooth - 0.01)
    caps = model.collision.capsules
    fatter = dataclasses.replace(model, collision=dataclasses.replace(
        model.collision, capsules=tuple(dataclasses.replace(c, radius=c.radius + 0.005) for c in caps)))
    assert float(exact_clearance(fatter, [ball])(theta)) < gap - 1e-3


Z1 = Path(__file__).resolve().parent / "data" / "z1_sea.toml"


def _z1_with_a_box_hand(tmp_path) -> Path:
    """Unitree's Z1 whose hand (gripperStator, fixed to link06) has a box as its collision model
    in place of its unshipped mesh, and a model file whose [collision] gives the hand's link a
    capsule too thin to hold it (as a user writes `links` by eye)."""
    import tomllib
    urdf = (Z1.parent / "z1_description" / "urdf" / "z1.urdf").read_text()
    urdf = re.sub(r'<mesh filename="package://example-robot-data/robots/z1_description/meshes/collision/'
                  r'z1_GripperStator.STL" scale="1 1 1"/>', '<box size="0.11 0.07 0.06"/>', urdf)
    urdf = urdf.replace('<box size="0.11 0.07 0.06"/>\n      </geometry>',
                        '<box size="0.11 0.07 0.06"/>\n      </geometry>\n      <origin xyz="0.045 0 0" rpy="0 0 0"/>', 1)
    (tmp_path / "z1.urdf").write_text(urdf)
    doc = tomllib.loads(Z1.read_text())
    doc.update(urdf=str(tmp_path / "z1.urdf"),
               collision={"margin": 0.0, "tip": "gripperStator", "links": {"link02": 0.03, "link06": 0.02}})
    (tmp_path / "z1.toml").write_text(to_toml(doc))
    return tmp_path / "z1.toml"


def test_capsules_are_never_optimistic_against_the_urdfs_own_shapes(tmp_path):
    """The Z1 with a box hand and thin capsules given by eye: the URDF shapes they do not hold
    (the hand's box, link06's and link02's cylinders, and those of links `links` leaves out) are
    added and named; at 300 random poses against random spheres and boxes, a clearance the
    optimiser sees as positive (its smooth covering spheres) is never more than the URDF shapes' own,
    measured by coal (which shares no code with the capsules), nor the verification's (each axis
    sampled every r / 8) by more than its sampling error r / 512; the given capsules alone were
    optimistic by centimetres."""
    from rscasadi.dynamics.collision import clearance_function, exact_clearance
    from rscasadi.dynamics.shapes_clearance import shapes_clearance, urdf_shapes
    from rscasadi.model.types import Collision
    from rscasadi.ocp.problem import Obstacle
    import dataclasses
    arm = rscasadi.load(_z1_with_a_box_hand(tmp_path))
    c = arm.model.collision
    assert any("gripperStator" in note and "box" in note and "added" in note for note in c.notes), c.notes
    assert any("link03" in note and "added" in note for note in c.notes), c.notes
    assert {kind for *_, g, _ in urdf_shapes(arm.model) for kind in [type(g).__name__]} >= {"Box", "Cylinder"}
    given_only = dataclasses.replace(arm.model, collision=Collision(0.0, c.capsules[:2], c.tip))
    rng = np.random.default_rng(8)
    lo, hi = (np.array([jt.limits["theta"][i] for jt in arm.model.joints]) for i in (0, 1))
    worst, sampled, optimistic, near = -np.inf, -np.inf, 0.0, 0
    for k in range(30):
        theta = rng.uniform(lo, hi, (10, arm.n)).T
        theta[:, 1:] = theta[:, :1] + rng.normal(0, 0.05, (arm.n, 9))     # near the pose the obstacle is placed at
        theta = np.clip(theta, lo[:, None], hi[:, None])
        R, p = (np.array(v) for v in arm.frame_placement("gripperStator")(theta[:, 0]))
        centre = p.ravel() + rng.normal(0, 0.08, 3)
        obstacle = Obstacle("sphere", centre, rng.uniform(0.01, 0.05)) if k % 2 else \
            Obstacle("box", centre, size=rng.uniform(0.02, 0.1, 3))
        smooth = np.array(clearance_function(arm.model, [obstacle]).map(10)(theta)).min(axis=0)
        exact = np.array(exact_clearance(arm.model, [obstacle]).map(10)(theta)).ravel()
        thin = np.array(exact_clearance(given_only, [obstacle]).map(10)(theta)).ravel()
        coal_gap = shapes_clearance(arm.model, [obstacle], theta)
        clear = smooth > 0                                # a claim is made only where it says clear
        near += int(np.sum(clear & (coal_gap < 0.05)))
        worst = max(worst, float(np.max((smooth - coal_gap)[clear], initial=-np.inf)))
        sampled = max(sampled, float(np.max((exact - coal_gap)[exact > 0], initial=-np.inf)))
        optimistic = max(optimistic, float(np.max((thin - coal_gap)[thin > 0], initial=0.0)))
    assert near > 60 and worst <= 1e-9, (near, worst)
    assert sampled <= max(cap.radius for cap in c.capsules) / 512, sampled
    assert optimistic > 0.01, optimistic                   # the test can tell: the thin capsules were optimistic
