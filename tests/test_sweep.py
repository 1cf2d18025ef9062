"""Sweeps on Dask: a grid of optimal-control problems over model parameters and problem fields,
on a local cluster of 2 workers; nothing lost, resumable, equal to solving each point alone."""
import csv
import json

import numpy as np
import pytest

from rscasadi.cli import main
from rscasadi.ocp import load_problem, solve_once
from rscasadi.ocp.sweep import load_sweep
from rscasadi.model.modelfile import ModelFileError, to_toml

from conftest import ROOT, problem


def write_sweep(directory, name, grid, base="sweep_base.toml"):
    path = directory / name
    path.write_text(f'problem = "{base}"\n\n[grid]\n' + "".join(f"{json.dumps(k)} = {json.dumps(v)}\n"
                                                               for k, v in grid.items()))
    return path


def rows(out):
    with open(out / "sweep.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_sweep_on_two_workers_equals_each_point_solved_alone(pitch_arm, capsys):
    problem(pitch_arm, "sweep_base.toml", objective="min_time", max_duration=5.0,
            transcription={"intervals": 30, "compiled": True})
    grid = {"shoulder_pitch.sea.k1": [500.0, 2000.0], "max_duration": [5.0, 0.05]}   # 0.05 s: infeasible
    path = write_sweep(pitch_arm, "sweep.toml", grid)
    out = pitch_arm / "sweep_out"
    code = main(["sweep", str(path), "--out", str(out), "--workers", "2"])
    text = capsys.readouterr().out
    assert code == 1                                          # two points cannot be solved: said so
    assert "2 workers" in text and "4/4 points" in text
    assert text.count("compiled the condensing kernel") <= 1      # one kernel for every point (or the cache's)
    assert "compiled the NLP" not in text                     # and nothing compiled per point
    table = rows(out)
    assert len(table) == 4 and (out / "sweep.png").exists()
    for r in table:
        k, tmax = json.loads(r["shoulder_pitch.sea.k1"]), json.loads(r["max_duration"])
        if tmax < 0.1:                                         # recorded with its status, not lost
            assert r["success"] == "False" and r["status"] != "Solve_Succeeded"
            continue
        assert r["success"] == "True" and r["verified"] == "True"
        # independently: the spring written into a model file, solved alone
        with open(pitch_arm / "pitch.toml", "rb") as fh:
            import tomllib
            d = tomllib.load(fh)
        d["joints"][0]["sea"]["k1"] = k
        (pitch_arm / f"pitch_{int(k)}.toml").write_text(to_toml(d))
        alone = solve_once(load_problem(problem(pitch_arm, f"alone_{int(k)}.toml", model=f"pitch_{int(k)}.toml",
                                                objective="min_time", max_duration=tmax,
                                                transcription={"intervals": 30})), print_level=0, log=lambda m: None)
        assert abs(float(r["objective"]) - alone["objective"]) < 1e-6 * alone["objective"]
    # resume: nothing to do; a lost row is solved again, alone
    assert main(["sweep", str(path), "--out", str(out), "--workers", "2"]) == 1
    assert "4 already done, 0 to solve" in capsys.readouterr().out
    kept = [r for r in table if r["point"] != "0"]
    with open(out / "sweep.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(table[0]))
        w.writeheader()
        w.writerows(kept)
    main(["sweep", str(path), "--out", str(out), "--workers", "2"])
    assert "3 already done, 1 to solve" in capsys.readouterr().out
    again = {r["point"]: r for r in rows(out)}
    assert len(again) == 4 and np.isclose(float(again["0"]["objective"]), float(table[0]["objective"]), rtol=1e-9)


@pytest.mark.parametrize("grid,field", [
    ({"shoulder_pitch.sea.k9": [1.0]}, "grid.shoulder_pitch.sea.k9"),
    ({"duration": []}, "grid.duration"),
    ({"duration": ["long"]}, r"grid.duration\[0\]"),
    ({"theta_end": [[0.1, 0.2]]}, r"grid.theta_end\[0\]"),
    ({"shoulder_pitch.gear_ratio": [50.0, 0.0]}, "grid.shoulder_pitch.gear_ratio"),
])
def test_bad_sweep_file_names_the_field(pitch_arm, grid, field):
    problem(pitch_arm, "sweep_base.toml")
    with pytest.raises(ModelFileError, match=rf"bad_sweep\.toml: field '{field}'"):
        load_sweep(write_sweep(pitch_arm, "bad_sweep.toml", grid))


def test_a_gear_ratio_grid_is_a_sweep_of_parameters(pitch_arm):
    problem(pitch_arm, "sweep_base.toml")
    sweep = load_sweep(write_sweep(pitch_arm, "gear_sweep.toml", {"shoulder_pitch.gear_ratio": [60.0, 120.0]}))
    assert sweep.grid == {"shoulder_pitch.gear_ratio": [60.0, 120.0]}


def test_sweep_refuses_a_foreign_directory(pitch_arm, tmp_path, capsys):
    problem(pitch_arm, "sweep_base.toml")
    (tmp_path / "notes.txt").write_text("mine")
    code = main(["sweep", str(write_sweep(pitch_arm, "s.toml", {"duration": [1.0]})), "--out", str(tmp_path)])
    assert code == 2 and "refusing" in capsys.readouterr().err
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_unreachable_scheduler_is_named(pitch_arm, tmp_path, capsys):
    problem(pitch_arm, "sweep_base.toml")
    path = write_sweep(pitch_arm, "s2.toml", {"duration": [1.0]})
    code = main(["sweep", str(path), "--out", str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:9"])
    assert code == 2 and "tcp://127.0.0.1:9" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()                    # nothing half-written


def test_interrupt_prints_one_line_and_keeps_the_finished_points(tmp_path):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) during a sweep: one
    line, exit 130, no worker tracebacks; the points finished so far stay for the resume."""
    import os
    import signal
    import subprocess
    import sys
    out = tmp_path / "sweep"
    p = subprocess.Popen([sys.executable, "-m", "rscasadi.cli", "sweep",
                          str(ROOT / "problems" / "sweep_spring_stiffness.toml"), "--out", str(out), "--workers", "2"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    for line in p.stdout:
        if "points  point" in line:
            os.killpg(p.pid, signal.SIGINT)
            break
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert err.strip().splitlines() == ["rscasadi: interrupted; nothing half-written was kept"], err
    rows = (out / "sweep.csv").read_text().splitlines()
    assert len(rows) >= 2 and rows[0].startswith("point,")
