"""`rscasadi view`: one self-contained HTML file that draws and animates the arm, checked in a
real browser (headless Chromium: the arm is drawn, and it has moved between two times given in
the URL), a GIF, and a model file alone."""
import os
import shutil
import subprocess

import numpy as np
import pytest

from rscasadi.cli import main

from conftest import ROOT

SOLUTION = ROOT / "results" / "ocp" / "min_effort" / "solution.json"


@pytest.fixture(scope="session")
def chromium():
    """Chromium, installed from Debian's packages in CI when it is missing (root, apt)."""
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None and os.environ.get("CI") and hasattr(os, "geteuid") and os.geteuid() == 0 \
            and shutil.which("apt-get"):
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
        subprocess.run(["apt-get", "update", "-qq"], env=env, capture_output=True, timeout=600)
        subprocess.run(["apt-get", "install", "-y", "-qq", "chromium"], env=env, capture_output=True, timeout=900)
        found = shutil.which("chromium")
    if found is None:
        pytest.skip("no Chromium to open the page in (Debian: apt-get install chromium)")
    return found


def screenshot(browser, page, t, out):
    subprocess.run([browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader",
                    "--enable-unsafe-swiftshader", "--window-size=800,600", "--virtual-time-budget=4000",
                    f"--screenshot={out}", f"file://{page}#t={t}"], capture_output=True, timeout=120, check=True)
    import matplotlib.image
    return matplotlib.image.imread(out)[:, :, :3]


def rotor_pixels(img):
    """Pixels of the rotors' blue."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (b > r + 0.25) & (b > g + 0.1)


def test_the_page_draws_the_arm_moving_offline(chromium, tmp_path, capsys):
    page = tmp_path / "view.html"
    assert main(["view", str(SOLUTION), "--out", str(page), "--gif", str(tmp_path / "view.gif")]) in (0, None)
    html = page.read_text()
    assert "http://" not in html.split("<script>", 2)[2][:2000] and "<script src" not in html   # nothing fetched
    assert (tmp_path / "view.gif").read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    start = screenshot(chromium, page, 0.0, tmp_path / "start.png")
    middle = screenshot(chromium, page, 0.75, tmp_path / "middle.png")
    assert rotor_pixels(start).sum() > 200 and rotor_pixels(middle).sum() > 200        # the arm is drawn
    moved = np.abs(start - middle).max(axis=2) > 0.1
    assert moved.sum() > 500                                                           # ... and it moved


def test_a_model_file_alone(chromium, tmp_path):
    page = tmp_path / "model.html"
    assert main(["view", str(ROOT / "problems" / "panda_sea.toml"), "--out", str(page)]) in (0, None)
    assert rotor_pixels(screenshot(chromium, page, 0.0, tmp_path / "panda.png")).sum() > 200


def test_view_refuses_what_it_cannot_draw(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"theta": []}')
    assert main(["view", str(bad), "--out", str(tmp_path / "x.html")]) == 2
    assert "not a solution.json" in capsys.readouterr().err and not (tmp_path / "x.html").exists()
    assert main(["view", str(SOLUTION), "--out", str(tmp_path / "no" / "such" / "x.html")]) == 2


def _cube_stl(half: float) -> str:
    """An ASCII STL cube of half-width `half` (m)."""
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)])
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6), (0, 2, 6),
             (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    rows = ["solid cube"]
    for f in faces:
        a, b, c = v[list(f)]
        normal = np.cross(b - a, c - a)
        if normal @ (a + b + c) < 0:                     # outward, counter-clockwise seen from outside
            f, normal = f[::-1], -normal
        normal = normal / np.linalg.norm(normal)
        rows += [f"facet normal {' '.join(map(str, normal))}", "outer loop"] + \
                [f"vertex {' '.join(map(str, v[i]))}" for i in f] + ["endloop", "endfacet"]
    return "\n".join(rows + ["endsolid cube"]) + "\n"


def test_urdf_visual_meshes_at_hand_are_drawn(chromium, tmp_path):
    """A Panda whose URDF's link-4 visual is an STL in its package (a package:// name found under
    the folder with the package.xml): the scene draws it instead of the link's capsule, and the
    page differs from the capsules' by the cube's pixels."""
    from rscasadi.view import scene_of
    (tmp_path / "urdf").mkdir()
    (tmp_path / "package.xml").write_text("<package><name>panda_description</name></package>\n")
    text = (ROOT / "problems" / "urdf" / "panda.urdf").read_text().replace("meshes/visual/link4.dae",
                                                                           "meshes/visual/link4.stl")
    (tmp_path / "urdf" / "panda.urdf").write_text(text)
    mesh = tmp_path / "robots" / "panda_description" / "meshes" / "visual" / "link4.stl"
    mesh.parent.mkdir(parents=True)
    mesh.write_text(_cube_stl(0.12))
    model = (ROOT / "problems" / "panda_sea.toml").read_text()
    (tmp_path / "panda.toml").write_text(model)
    scene = scene_of(tmp_path / "panda.toml")
    assert [kind for kind, *_ in scene.visuals[4]] == ["mesh"] and set(scene.visuals) == {4}
    pages = {}
    for name, folder in (("capsules", ROOT / "problems"), ("mesh", tmp_path)):
        page = tmp_path / f"{name}.html"
        assert main(["view", str(folder / "panda_sea.toml" if name == "capsules" else folder / "panda.toml"),
                     "--out", str(page)]) in (0, None)
        pages[name] = screenshot(chromium, page, 0.0, tmp_path / f"{name}.png")
    assert (np.abs(pages["mesh"] - pages["capsules"]).max(axis=2) > 0.1).sum() > 2000


def test_view_reads_no_file_outside_the_robots_package(tmp_path, capsys):
    """A hostile URDF's meshes: an absolute path, a package:// name climbing out, a relative one
    climbing out, a symlink named *.stl to a secret, a FIFO named *.stl, a secret with a mesh's
    name outside the package.  None is read: the page holds no byte of the planted secrets, and
    `view` names every mesh it skipped; a mesh inside the package is still drawn."""
    import os
    secret = "SECRET-TOKEN-5f2c9e"
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.stl").write_text(f"solid {secret}\nendsolid\n")
    (outside / "shadow").write_text(secret)
    pkg = tmp_path / "robot"
    (pkg / "urdf").mkdir(parents=True)
    (pkg / "meshes").mkdir()
    (pkg / "package.xml").write_text("<package><name>robot</name></package>\n")
    (pkg / "meshes" / "good.stl").write_text(_cube_stl(0.05))
    os.symlink(outside / "shadow", pkg / "meshes" / "link.stl")
    os.mkfifo(pkg / "meshes" / "fifo.stl")
    names = [str(outside / "secret.stl"), "package://robot/../outside/secret.stl", "../../outside/secret.stl",
             "package://robot/meshes/link.stl", "package://robot/meshes/fifo.stl", "file://" + str(outside / "secret.stl"),
             "package://robot/meshes/good.stl"]
    text = (ROOT / "problems" / "urdf" / "panda.urdf").read_text()
    for k, name in enumerate(names, start=1):          # the visuals of links 1..7
        text = text.replace(f"package://example-robot-data/robots/panda_description/meshes/visual/link{k}.dae", name)
    (pkg / "urdf" / "panda.urdf").write_text(text)
    model = (ROOT / "problems" / "panda_sea.toml").read_text().replace('urdf = "urdf/panda.urdf"', 'urdf = "robot/urdf/panda.urdf"')
    (tmp_path / "panda.toml").write_text(model)
    page = tmp_path / "view.html"
    assert main(["view", str(tmp_path / "panda.toml"), "--out", str(page)]) in (0, None)
    out = capsys.readouterr().out
    html = page.read_text()
    import base64
    for shift in range(3):                             # the secret inlined at any byte alignment
        encoded = base64.b64encode(b"x" * shift + secret.encode()).decode()[4:16]
        assert secret not in html and encoded not in html, shift
    for name in names[:-1]:
        assert f"skipped mesh {name!r}" in out, (name, out)
    assert "good.stl" not in out
    from rscasadi.view import scene_of
    scene = scene_of(tmp_path / "panda.toml")
    assert [v[0] for v in scene.visuals.get(7, [])] == ["mesh"]


MALFORMED = {                                         # field, what replaces it
    "t": ["abc", [], [1.0, 0.5], [0.0, 1e12], [0.0, None]],
    "theta": [[[0.0]], [[0.0], [0.0, 1.0], []], [[None, None]] * 3, 5],
    "model": [5, "/no/such/model.toml"],
    "obstacles": ["ball", [{"kind": "sphere"}]],
    "goal": ["x", {"frame": "nope", "position": [0, 0, 0]}],
    "path": [{"points": "x"}],
    "payload": ["x", {"mass": "heavy"}],
}


@pytest.mark.parametrize("field,value", [(k, v) for k, vs in MALFORMED.items() for v in vs])
def test_a_malformed_solution_is_refused_by_field_without_a_traceback(field, value, tmp_path, capsys):
    import json
    data = json.loads(SOLUTION.read_text())
    if field == "t" and isinstance(value, list) and len(value) == 2:
        data["theta"] = [[0.0, 0.0]] * 3
    data[field] = value
    bad = tmp_path / "solution.json"
    bad.write_text(json.dumps(data))
    assert main(["view", str(bad), "--out", str(tmp_path / "x.html")]) == 2
    err = capsys.readouterr().err
    assert f"field '{field}'" in err and "Traceback" not in err, err
    assert not (tmp_path / "x.html").exists()


def test_the_view_shows_the_motion_to_its_last_instant(tmp_path):
    """T = 0.3635 s: the animation's last frame is at T (it was 0.333 s: the arm never drawn at
    the goal), with the arm posed at the solution's last angles."""
    import json
    from rscasadi.view import scene_of
    data = json.loads(SOLUTION.read_text())
    t = np.asarray(data["t"], float)
    data["t"] = (t * 0.3635 / t[-1]).tolist()
    path = tmp_path / "solution.json"
    path.write_text(json.dumps(data))
    scene = scene_of(path)
    assert scene.times[-1] == pytest.approx(0.3635, abs=1e-12) and np.all(np.diff(scene.times) <= 1 / 30 + 1e-12)
    last = scene_of(path)
    end = np.asarray(data["theta"], float)[:, -1]
    from rscasadi.view.scene import _poses
    from rscasadi.ocp.solution import solution_arm
    assert np.allclose(last.poses[-1], _poses(solution_arm(data), end[:, None])[0], atol=1e-12)


def test_the_page_frames_an_arm_far_from_the_origin(chromium, tmp_path):
    """Baxter's left arm sits about a metre to the side of the URDF's root: the page looks at it,
    not at the origin. The arm (links and rotors, everything not background, floor or text)
    spans a good part of the window and its centre is near the window's; the GIF frames it too."""
    import sys
    sys.path.insert(0, str(ROOT / "tests"))
    from test_whole_robot import sidecar
    from rscasadi.model.modelfile import to_toml
    model = tmp_path / "baxter.toml"
    model.write_text(to_toml(sidecar()))
    page = tmp_path / "baxter.html"
    assert main(["view", str(model), "--out", str(page), "--gif", str(tmp_path / "baxter.gif")]) in (0, None)
    img = screenshot(chromium, page, 0.0, tmp_path / "baxter.png")
    arm = (img.max(axis=2) - img.min(axis=2) > 0.12) | (img.max(axis=2) < 0.7)     # coloured or dark: drawn
    arm[-40:, :] = False                                                          # the clock's text
    arm[:30, -260:] = False                                                       # MeshCat's controls button
    rows, cols = np.nonzero(arm)
    h, w = arm.shape
    assert np.ptp(cols) > 0.35 * w and np.ptp(rows) > 0.15 * h, (np.ptp(cols), np.ptp(rows))
    assert abs(np.mean(cols) / w - 0.5) < 0.2 and abs(np.mean(rows) / h - 0.5) < 0.25
    from PIL import Image
    gif = Image.open(tmp_path / "baxter.gif")
    assert gif.size == (800, 600)
