"""Design studies: one optimal-control problem solved over a grid, each point a task on Dask
(`rscasadi sweep SWEEP.toml --out DIR [--scheduler ADDRESS] [--workers N]`).

Sweep file (TOML):

    problem = "ocp_min_effort.toml"            # relative to this file
    [grid]                                     # the Cartesian product of these lists
    "elbow_pitch.sea.k1" = [300.0, 600.0, 1200.0]   # model parameters, by their dotted names
    duration = [1.0, 1.5]                      # or problem fields: theta_start, theta_end,
                                               # duration, max_duration, effort_weight

The model parameters are inputs of the NLP, so its C is generated and compiled once, before the
first task, and shared by every point.  Points are solved on the problem's first mesh (no
refinement: a new mesh would be a new NLP) and verified by the replay like `rscasadi ocp`;
the `verified` column says whether the replay met the problem's tolerances.

DIR/sweep.csv gets one row per point (its values, status, success, verified, objective, final
time, solve time), rewritten whole after each point, so an interrupted sweep loses nothing
and a re-run skips the points already done (points that raised an error are tried again).
DIR/sweep.png plots the objective over the grid.
"""
from __future__ import annotations

import csv
import dataclasses
import itertools
import json
import logging
import os
import signal
import time
from pathlib import Path

import numpy as np

from rscasadi.files import replacing
from rscasadi.model.modelfile import ModelFileError, field_checker, read, read_toml
from rscasadi.ocp.problem import SWEEPABLE, check_against_model, load_problem

COLUMNS = ("point", "status", "success", "verified", "objective", "final_time_s", "solve_time_s", "iterations")


@dataclasses.dataclass
class Sweep:
    """A sweep file: the problem it varies and the grid (name -> values)."""
    path: Path
    problem_path: Path
    grid: dict                      # key -> list of values (numbers, or lists for theta_*)

    def points(self) -> list[dict]:
        keys = list(self.grid)
        return [dict(zip(keys, combo)) for combo in itertools.product(*self.grid.values())]


def load_sweep(path) -> Sweep:
    """Read and check a sweep file (docs/user-guide/sweeps.md); errors name the field."""
    path = Path(path)
    d = read_toml(path, "sweep")

    fail = field_checker(path, d, ("problem", "grid"))
    for key in ("problem", "grid"):
        if key not in d:
            fail(key, "missing required field")
    if not isinstance(d["problem"], str) or not d["problem"].strip():
        fail("problem", f"expected the path of a problem file, got {d['problem']!r}")
    if not isinstance(d["grid"], dict) or not d["grid"]:
        fail("grid", "expected a table of lists")
    sweep = Sweep(path, (path.parent / d["problem"]).resolve(), {})
    try:
        problem = load_problem(sweep.problem_path)
        model = read(problem.task.model)
    except ModelFileError as exc:
        fail("problem", str(exc))
    for key, values in d["grid"].items():
        if not isinstance(values, list) or not values:
            fail(f"grid.{key}", f"expected a non-empty list, got {values!r}")
        vector = key in ("theta_start", "theta_end")
        for i, v in enumerate(values):
            ok = (isinstance(v, list) and len(v) == model.n and all(_number(x) for x in v)) if vector else _number(v)
            if not ok:
                fail(f"grid.{key}[{i}]", f"expected {'a list of ' + str(model.n) + ' numbers' if vector else 'a number'}, got {v!r}")
        if key not in SWEEPABLE:
            try:
                check_against_model(problem.replace(parameters={key: 1.0}), model)
            except ModelFileError:
                fail(f"grid.{key}", f"neither a parameter of {problem.task.model.name} nor a sweepable problem "
                     f"field ({', '.join(SWEEPABLE)})")
            if key.endswith(".gear_ratio") and min(values) <= 0:
                fail(f"grid.{key}", f"a gear ratio is positive, got {min(values)!r}")
            if key in problem.task.design:
                fail(f"grid.{key}", "is a design variable of the problem; it cannot also be swept")
        sweep.grid[key] = values
    return sweep


def _number(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and np.isfinite(v)


def point_problem(problem, point: dict):
    """The problem at one grid point: parameters as NLP inputs, fields replaced."""
    params = {k: float(v) for k, v in point.items() if k not in SWEEPABLE}
    fields = {k: (np.asarray(v, float) if isinstance(v, list) else float(v)) for k, v in point.items() if k in SWEEPABLE}
    # one thread per point unless the problem file asks: the workers (one per core) are the parallelism
    return problem.replace(parameters=params, rounds=0, threads=problem.solver.threads or 1, **fields)


def solve_point(problem_path: str, names: list, point: dict, index: int) -> dict:
    """One task: solve and verify the problem at `point`; never raises (errors become rows)."""
    from rscasadi.ocp.solving import checks, solve_once, verify
    row = {"point": index, **{k: json.dumps(v) for k, v in point.items()}}
    try:
        base = load_problem(problem_path)
        # every point carries all swept parameter names, so all share one NLP
        problem = point_problem(base, {**{k: v for k, v in _nominal(base, names).items()}, **point})
        sol = solve_once(problem, print_level=0, log=lambda m: None)
        report = verify(sol)
        row.update(status=sol["status"], success=sol["success"], verified=not checks(problem, report),
                   objective=sol["objective"], final_time_s=sol["t"][-1], solve_time_s=sol["solve_time_s"],
                   iterations=sol["iterations"])
    except Exception as exc:                           # recorded, never lost
        row.update(status=f"error: {type(exc).__name__}: {exc}"[:300], success=False, verified=False)
    return row


def _nominal(problem, names) -> dict:
    from rscasadi.model.modelfile import read
    from rscasadi.model.parameters import value
    model = read(problem.task.model)
    return {k: value(model, k) for k in names}


def _key(point: dict) -> str:
    return json.dumps({k: point[k] for k in sorted(point)})


def _read_done(csv_path: Path, keys: list) -> dict:
    done = {}
    if csv_path.exists():
        with open(csv_path, newline="") as fh:
            for row in csv.DictReader(fh):
                if not row.get("status", "").startswith("error"):
                    point = {k: json.loads(row[k]) for k in keys}
                    done[_key(point)] = row
    return done


def _write_csv(csv_path: Path, keys: list, rows: list):
    with replacing(csv_path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["point", *keys, *COLUMNS[1:]], extrasaction="ignore")
        w.writeheader()
        for row in sorted(rows, key=lambda r: int(r["point"])):
            w.writerow(row)


def _bar(done: int, total: int, width: int = 30) -> str:
    fill = int(width * done / max(total, 1))
    return f"[{'#' * fill}{'.' * (width - fill)}] {done}/{total} points"


def check_reachable(scheduler: str, seconds: float = 3.0):
    """A TCP connection to a tcp://HOST:PORT scheduler, before any work (Dask's client would
    retry a refused one for its whole timeout); other schemes are left to Dask."""
    import socket
    from urllib.parse import urlsplit
    where = urlsplit(scheduler if "://" in scheduler else f"tcp://{scheduler}")
    if where.scheme != "tcp" or not where.hostname or where.port is None:
        return
    try:
        socket.create_connection((where.hostname, where.port), timeout=seconds).close()
    except OSError as exc:
        raise ModelFileError(f"--scheduler {scheduler}: cannot reach a Dask scheduler there "
                             f"({exc.strerror or exc})") from None


def run(sweep_file, out, scheduler: str | None = None, workers: int | None = None, log=print) -> dict:
    """Solve every grid point on Dask; write DIR/sweep.csv and DIR/sweep.png."""
    from distributed import Client, LocalCluster, as_completed
    from rscasadi.ocp.solving import solve_once
    from rscasadi.files import check_writable
    sweep = load_sweep(sweep_file)
    out = Path(out)
    check_writable(out)
    if scheduler:
        check_reachable(scheduler)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "sweep.csv").exists())):
        raise ModelFileError(f"{out}: exists and was not written by rscasadi sweep (no sweep.csv); refusing to write there")
    keys = list(sweep.grid)
    names = [k for k in keys if k not in SWEEPABLE]
    points = sweep.points()
    csv_path = out / "sweep.csv"
    done = _read_done(csv_path, keys)
    rows = [dict(r, point=i) for i, p in enumerate(points) if (r := done.get(_key(p)))]
    todo = [(i, p) for i, p in enumerate(points) if _key(p) not in done]
    log(f"{sweep.path}: {len(points)} points over {', '.join(keys)}; {len(rows)} already done, {len(todo)} to solve")
    t0 = time.perf_counter()                  # points per second: from the first task on
    if todo:
        base = load_problem(sweep.problem_path)
        if base.transcription.compiled:                   # compile the shared NLP once, here, before the tasks
            log("compiling the shared NLP (model parameters as its inputs) ...")
            solve_once(point_problem(base, {**_nominal(base, names), **todo[0][1]}), print_level=0, log=log)
        cluster = None
        if scheduler:
            try:
                client = Client(scheduler, timeout=10)
            except (OSError, TimeoutError) as exc:
                raise ModelFileError(f"--scheduler {scheduler}: cannot reach a Dask scheduler there ({exc})") from None
        else:
            # the workers inherit an ignored SIGINT: Ctrl-C reaches this process alone, which
            # closes the cluster, instead of every worker printing its own traceback; their logs
            # are silenced below CRITICAL (a worker's heartbeat to the closing scheduler fails
            # with an ERROR); a point that fails still comes back as its row's status
            previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
            try:
                cluster = LocalCluster(n_workers=workers or os.cpu_count(), threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=logging.CRITICAL)
            finally:
                signal.signal(signal.SIGINT, previous)
            client = Client(cluster)
        try:
            log(f"Dask: {len(client.scheduler_info()['workers'])} workers"
                + (f" at {scheduler}" if scheduler else " (local cluster)"))
            t0 = time.perf_counter()
            out.mkdir(parents=True, exist_ok=True)
            futures = [client.submit(solve_point, str(sweep.problem_path), names, p, i, pure=False) for i, p in todo]
            for k, fut in enumerate(as_completed(futures), 1):
                try:
                    row = fut.result()
                except Exception as exc:                  # a worker died: still a row
                    i = todo[futures.index(fut)][0]
                    row = {"point": i, **{kk: json.dumps(v) for kk, v in points[i].items()},
                           "status": f"error: {type(exc).__name__}: {exc}"[:300], "success": False, "verified": False}
                rows.append(row)
                _write_csv(csv_path, keys, rows)
                log(f"{_bar(len(rows), len(points))}  point {row['point']}: {row['status']}")
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    else:
        out.mkdir(parents=True, exist_ok=True)
        _write_csv(csv_path, keys, rows)
    elapsed = time.perf_counter() - t0
    _plot(out, keys, rows)
    ok = sum(str(r["success"]) == "True" for r in rows)
    log(f"wrote {csv_path} and {out / 'sweep.png'}: {ok} of {len(points)} points solved"
        + (f", {len(todo) / elapsed:.2f} points/s" if todo else ""))
    return {"rows": rows, "points_per_second": len(todo) / elapsed if todo else None, "solved": ok}


def _plot(out: Path, keys: list, rows: list):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4.5))
    x_key, other = keys[0], keys[1:]
    groups: dict = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in other), []).append(r)
    for label, rs in groups.items():
        rs = sorted(rs, key=lambda r: json.loads(r[x_key]) if not r[x_key].startswith("[") else int(r["point"]))
        xs = [json.loads(r[x_key]) if not r[x_key].startswith("[") else int(r["point"]) for r in rs]
        ys = [float(r["objective"]) if str(r["success"]) == "True" else np.nan for r in rs]
        line = ax.plot(xs, ys, "o-", label=", ".join(f"{k} = {v}" for k, v in zip(other, label)) or None)[0]
        bad = [x for x, r in zip(xs, rs) if str(r["success"]) != "True"]
        ax.plot(bad, [np.nanmin(ys) if np.isfinite(np.nanmin(ys + [np.inf])) else 0.0] * len(bad), "x",
                color=line.get_color())
    ax.set(xlabel=x_key, ylabel="objective", title="sweep (x: not solved)")
    if other:
        ax.legend(fontsize=7)
    fig.tight_layout()
    with replacing(out / "sweep.png") as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
