"""The figures the README and the user's pages quote, read from the results/ files they come from.

A page marks each quoted block:

    <!-- figures: KEY -->
    ...generated text...
    <!-- /figures -->

KEY is either `results/FILE.md#N`, the N-th markdown table of that file copied as it is, or the
name of a function in BLOCKS below, which reads the results and writes the block.

    python docs/figures.py            # rewrite every block from results/
    python docs/figures.py --check    # list the blocks that differ from results/ (exit 1)

The tests run the check, so a page cannot quote a figure its results file does not hold.
"""
import csv
import math
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
BLOCK = re.compile(r"(<!-- figures: (?P<key>\S+) -->\n)(?P<body>.*?)(<!-- /figures -->)", re.S)
PAGES = ("README.md", "docs/**/*.md")


class FiguresError(Exception):
    """A block names a results file, table or generator that does not exist."""


# ---------------------------------------------------------------- reading results/

def tables(path: Path) -> list[list[list[str]]]:
    """Every markdown table of a file: rows of cells, the header first, the rule left out."""
    found, rows = [], []
    for line in path.read_text().splitlines() + [""]:
        if line.startswith("|"):
            if not re.fullmatch(r"\|(\s*:?-+:?\s*\|)+", line.strip()):
                rows.append([c.strip() for c in line.strip().strip("|").split("|")])
        elif rows:
            found.append(rows)
            rows = []
    return found


def table_text(path: Path, number: int) -> str:
    """The number-th (1-based) markdown table of path, as written there."""
    lines, count, inside = path.read_text().splitlines(), 0, False
    kept = []
    for line in lines + [""]:
        if line.startswith("|"):
            if not inside:
                count, inside = count + 1, True
            if count == number:
                kept.append(line)
        else:
            inside = False
    if not kept:
        raise FiguresError(f"{path.relative_to(ROOT)} has no table {number}")
    return "\n".join(kept) + "\n"


def named_table(path: Path, first_header: str) -> dict[str, list[str]]:
    """The table of path whose header starts with first_header, as {first cell: row}."""
    for rows in tables(path):
        if rows[0][0] == first_header:
            return {r[0]: r for r in rows[1:]} | {"": rows[0]}
    raise FiguresError(f"{path.relative_to(ROOT)}: no table headed {first_header!r}")


def run_date(*paths: Path) -> str:
    """'2026-11-24' (or 'from D1 to D2'): the dates in the files' 'Run of DATE' lines."""
    dates = sorted({m.group(1) for p in paths for m in re.finditer(r"Run of (\d{4}-\d\d-\d\d)", p.read_text())})
    if not dates:
        raise FiguresError("no 'Run of DATE' line in " + ", ".join(str(p.relative_to(ROOT)) for p in paths))
    return dates[0] if len(dates) == 1 else f"from {dates[0]} to {dates[-1]}"


def run_machine(*paths: Path) -> str:
    """'AMD EPYC, 2 cores' (or 'A and B'): the machines in the files' 'Run of DATE on MACHINE,
    OS; commit' lines."""
    found = sorted({m.group(1) for p in paths
                    for m in re.finditer(r"Run of \d{4}-\d\d-\d\d on (.+?), [^,;]+; commit", p.read_text())})
    if not found:
        raise FiguresError("no 'Run of DATE on MACHINE' line in " + ", ".join(str(p.relative_to(ROOT)) for p in paths))
    return " and ".join(found)


def runs(*paths: Path) -> str:
    """Which file ran when and where: '`a.md`, `b.md`: 2026-11-24 on M1; `c.md`: 2026-11-27 on M2'."""
    groups: dict = {}
    for p in paths:
        m = re.search(r"Run of (\d{4}-\d\d-\d\d) on (.+?), [^,;]+; commit", p.read_text())
        if not m:
            raise FiguresError(f"no 'Run of DATE on MACHINE' line in {p.relative_to(ROOT)}")
        groups.setdefault((m.group(1), m.group(2)), []).append(f"`{p.relative_to(RESULTS)}`")
    return "; ".join(f"{', '.join(files)}: {date} on {machine}" for (date, machine), files in sorted(groups.items()))


def paced_rt(path: Path) -> tuple[float, float, float | None]:
    """(median, 99.9th percentile) in us of the paced example's step under SCHED_FIFO in a
    bench_mpc file, and its feedback phase's median (None where the file predates the split)."""
    text = path.read_text().split("rt (SCHED_FIFO):", 1)
    found = re.search(r"median ([0-9.]+) us, 99\.9% ([0-9.]+) us", text[-1]) if len(text) == 2 else None
    if not found:
        raise FiguresError(f"{path.relative_to(ROOT)}: no paced rt (SCHED_FIFO) line")
    feedback = re.search(r"mpc_feedback median ([0-9.]+) us", text[-1].split("\n\n")[0])
    return float(found.group(1)), float(found.group(2)), float(feedback.group(1)) if feedback else None


def codegen_ns() -> dict[tuple[int, str], dict[str, float]]:
    """bench_codegen.csv as {(n, function): row} with the Panda's row as n = 7."""
    rows = {(int(r["n"]), r["function"]): {k: float(v) for k, v in r.items() if k not in ("n", "function")}
            for r in csv.DictReader((RESULTS / "bench_codegen.csv").open())}
    panda = named_table(RESULTS / "bench_codegen.md", "forward_dynamics (ns)")
    header, values = panda[""], next(v for k, v in panda.items() if k)
    cell = dict(zip(header, values))
    rows[(7, "forward_dynamics")] = {"c_ns": float(cell["forward_dynamics (ns)"])}
    rows[(7, "forward_dynamics_jacobian")] = {"c_ns": float(cell["forward_dynamics_jacobian (ns)"]),
                                              "pinocchio_route_ns": float(cell["Pinocchio ABA derivatives (ns)"])}
    rows[(7, "step_jacobian")] = {"c_ns": float(cell["step_jacobian (ns)"])}
    return rows


# ---------------------------------------------------------------- formats

def ns(value: float) -> str:
    """A time in ns below 1 us, else in us with one decimal."""
    return f"{value:.0f} ns" if value < 1000 else f"{value / 1000:.1f} us"


def percent(value: float, digits: int = 2, sign: bool = True) -> str:
    return f"{value:+.{digits}f}" if sign else f"{abs(value):.{digits}f}"


# ---------------------------------------------------------------- blocks

def _feedback(paced) -> str:
    return f"; {paced[2]:.0f} us" if paced[2] is not None else ""


def readme_speed() -> str:
    """The README's speed table: generated C, Pinocchio, the NMPC step, the 6- and 7-joint OCP."""
    c = codegen_ns()
    arms = {r["arm"].split()[0]: r for r in csv.DictReader((RESULTS / "bench_ocp_arms.csv").open())}
    mpc3, mpc7 = paced_rt(RESULTS / "bench_mpc.md"), paced_rt(RESULTS / "bench_mpc_panda.md")
    files = (RESULTS / "bench_codegen.md", RESULTS / "bench_mpc_panda.md",
             RESULTS / "bench_mpc_horizon.md", RESULTS / "bench_ocp_arms.md", RESULTS / "bench_tasks.md")
    where = runs(*files)
    horizon = tables(RESULTS / "bench_mpc_horizon.md")
    head, *body = next(rows for rows in horizon if rows[0][:2] == ["QP", "N"])
    col = {name: i for i, name in enumerate(head)}
    fastest = {N: min((r for r in body if r[1] == N and r[0].startswith("riccati")),
                      key=lambda r: float(r[col["step median (us)"]])) for N in ("10", "20")}
    task = min(next(rows for rows in horizon if rows[0][:2] == ["QP", "step median (us)"])[1:], key=lambda r: float(r[1]))
    ocp = {a: f"{float(r['setup_cold_s']):.1f} s; {float(r['solve_s']):.2f} s" for a, r in arms.items()}
    head_t, *body_t = tables(RESULTS / "bench_tasks.md")[0]
    tasks = {r[0]: float(r[head_t.index("wall (s)")]) for r in body_t}
    task_ocp = ", ".join(f"{arm} {tasks[f'{name}, cold cache']:.0f} s; {tasks[f'{name}, warm cache, --cold']:.0f} s; "
                         f"{tasks[f'{name}, warm cache, its solution kept']:.0f} s"
                         for arm, name in (("Panda", "Panda shelf task"), ("Baxter", "Baxter left arm task")))

    def row(label, function, column="c_ns", form=ns):
        return f"| {label} | " + " | ".join(form(c[(n, function)][column]) for n in (3, 6, 7, 12)) + " |"
    return "\n".join([
        f"In `results/`: {where}; `bench_mpc.md` (n = 3): {runs(RESULTS / 'bench_mpc.md').split(': ', 1)[1]}.",
        "",
        "| | n = 3 | n = 6 | n = 7 (Panda) | n = 12 |",
        "|---|---|---|---|---|",
        row("forward dynamics", "forward_dynamics"),
        row("its Jacobian, d(ddq)/d(x, tau)", "forward_dynamics_jacobian"),
        row("Pinocchio's computeABADerivatives (tree, before projection)", "forward_dynamics_jacobian",
            "pinocchio_route_ns"),
        row("RK4 step Jacobian", "step_jacobian", form=lambda v: f"{v / 1000:.1f} us"),
        f"| NMPC step, median (99.9 %, rt){'; its feedback phase' if mpc3[2] or mpc7[2] else ''} | "
        f"{mpc3[0]:.0f} us ({mpc3[1]:.0f} us; -O2){_feedback(mpc3)} | | "
        f"{mpc7[0]:.0f} us ({mpc7[1]:.0f} us; -O3, native){_feedback(mpc7)} | |",
        "| NMPC step (Riccati, the fastest build), median: N = 10 (its feedback phase); N = 20; task space, "
        f"N = 10 | | | {fastest['10'][col['step median (us)']]} us ({fastest['10'][col['feedback (us)']]} us); "
        f"{fastest['20'][col['step median (us)']]} us; {task[1]} us | |",
        f"| minimum-time OCP, N = 150, both cores: first compile; solve | | {ocp['UR5']} (UR5) | {ocp['Panda']} | |",
        f"| task OCP (a tool goal, obstacles, a payload), verified: empty cache; filled, --cold; the same problem "
        f"again | | | {task_ocp} | |",
    ]) + "\n"


def _interaction(arm: str) -> dict:
    return json.loads((RESULTS / "interaction" / arm / "study.json").read_text())


def _interaction_cells(study: dict) -> dict[str, str]:
    push = " / ".join(percent(p["error_percent"]) for p in study["push"])
    wall = " / ".join(percent(w["error_percent"], 3, sign=False) for w in study["wall"])
    hit = [study["collision"][m] for m in ("impedance motion", "feedforward motion")]
    collision = (" / ".join(f"{h['delay_ms']:.0f}" for h in hit) + " ms; "
                 + " / ".join(f"{h['error_percent']:.1f}" for h in hit) + " %")
    d = study["reduced"]
    same = max(abs(d["complete"][k] - d["reduced"][k]) for k in d["complete"])
    step = study["timing"]["impedance_step"]
    stiff = study["wall"][-1]
    return {"push": push, "wall": wall, "collision": collision,
            "reduced": f"the same to {10.0 ** math.ceil(math.log10(max(same, 1e-16))):.0e} %",
            "step": f"{step['median_us']:.1f} / {step['worst_us']:.1f} us",
            "opt": study["timing"]["opt"],
            "gap": f"{stiff['bounces']}, {stiff['bounce_um']:.0f} um",
            "links": " (2000: link design)" if any(p["design"] == "link" for p in study["push"]) else ""}


def interaction_table(readme: bool) -> str:
    a, p = _interaction_cells(_interaction("arm3_tool")), _interaction_cells(_interaction("panda_sea"))
    date = run_date(*(RESULTS / "interaction").glob("*/study.md"))
    machine = run_machine(*(RESULTS / "interaction").glob("*/study.md"))
    if readme:
        head = f"At 1 kHz through quantised encoders (results of {date}, {machine}):\n\n"
        rows = [("15 N push: F / K error at K = 200 / 1000 / 2000 N/m", "push", " %"),
                ("5 mm into walls of 1e4 / 1e5 / 1e6 N/m: force error", "wall", " %"),
                ("collision in an impedance / feedforward motion: flagged after; torque error", "collision", ""),
                ("designed on the reduced (DLR) model instead", "reduced", ""),
                ("`impedance_step` in C, median / worst", "step", "")]
    else:
        head = f"Results of {date} on {machine} (`results/interaction/*/study.md`):\n\n"
        rows = [("(a) F / K error, K = 200 / 1000 / 2000 N/m", "push", " %"),
                ("(b) force error, walls 1e4 / 1e5 / 1e6 N/m", "wall", " %"),
                ("(b) after the touch, 1e6 N/m wall: separations, largest gap", "gap", ""),
                ("(c) impedance / feedforward motion: flagged after; torque error", "collision", ""),
                ("(d) reduced-model design against complete", "reduced", ""),
                (f"`impedance_step` median / worst ({a['opt']})", "step", "")]
    lines = ["| | reference arm + tool | Panda (7 joints) |", "|---|---|---|"]
    for label, key, unit in rows:
        extra = a["links"] if key == "push" and not readme else ""
        lines.append(f"| {label} | {a[key]}{unit}{extra} | {p[key]}{unit} |")
    return head + "\n".join(lines) + "\n"


def interaction_gap() -> str:
    """The largest separation from the stiffest wall over both arms, in um."""
    gap = max(w["bounce_um"] for arm in ("arm3_tool", "panda_sea") for w in _interaction(arm)["wall"])
    return f"{gap:.0f} um"


def panda_shelf() -> str:
    """The Panda shelf task's times with and without the part and its MPC's tracking."""
    times = json.loads((RESULTS / "ocp" / "panda_shelf" / "comparison.json").read_text())
    loop = json.loads((RESULTS / "mpc_panda_shelf" / "closed_loop.json").read_text())
    untold, told = (loop[k]["MPC (C)"]["max_error"] * 1e3 for k in ("untold_payload", "told_payload"))
    return (f"The Panda with an FS-SEA in every joint moves a 2 kg part between shelves in minimum time, the\n"
            f"hand pointing down, around a ball and above the table (`problems/ocp_panda_shelf.toml`): "
            f"{times['with_part_s']:.4f} s,\nverified on the complete model; {times['without_part_s']:.4f} s "
            f"without the part, because the slow-side speed limits bind\n(the part only moves which springs "
            f"bind). The task-space MPC follows it with the part untold\n({untold:.1f} mm) or told "
            f"({told:.1f} mm; `problems/mpc_panda_shelf.toml`).\n")


def _compile_seconds() -> dict[int, float]:
    for rows in tables(RESULTS / "bench_codegen.md"):
        if rows[0] == ["n", "generate + compile (s)"]:
            return {int(r[0]): float(r[1]) for r in rows[1:]}
    raise FiguresError("results/bench_codegen.md: no 'generate + compile (s)' table")


def codegen_tutorial() -> str:
    """The codegen tutorial's tables: the reference arm against its targets, then n = 3, 6, 12."""
    c, built = codegen_ns(), _compile_seconds()
    targets = {"forward_dynamics": "<= 250 ns", "inverse_dynamics": "<= 150 ns",
               "forward_dynamics_jacobian": "<= 2 us", "step_jacobian": "<= 2 us"}
    functions = ("forward_dynamics", "inverse_dynamics", "forward_dynamics_jacobian", "step", "step_jacobian",
                 "feedforward_step")
    lines = [f"Run of {run_date(RESULTS / 'bench_codegen.md')} on {run_machine(RESULTS / 'bench_codegen.md')}, "
             "-O3 with `--native`:", "",
             "| function (reference arm) | C | target |", "|---|---|---|"]
    lines += [f"| {f} | {ns(c[(3, f)]['c_ns'])} | {targets.get(f, '')} |" for f in functions]
    lines += [f"| generate + compile, all | {built[3]:.1f} s | < 30 s |", "",
              "| n | " + " | ".join(functions) + " | generate + compile |",
              "|---|" + "---|" * (len(functions) + 1)]
    lines += [f"| {n} | " + " | ".join(ns(c[(n, f)]["c_ns"]) for f in functions) + f" | {built[n]:.1f} s |"
              for n in (3, 6, 12)]
    return "\n".join(lines) + "\n"


def urdf_panda() -> str:
    """The URDF tutorial's Panda table: its generated C, Pinocchio on its tree, its minimum-time OCP."""
    cell = named_table(RESULTS / "bench_codegen.md", "forward_dynamics (ns)")
    cell = dict(zip(cell[""], next(v for k, v in cell.items() if k)))
    ocp = next(r for r in csv.DictReader((RESULTS / "bench_ocp_arms.csv").open()) if r["arm"].startswith("Panda"))
    fd, crba = float(cell["forward_dynamics (ns)"]), float(cell["Pinocchio crba + rnea (ns)"])
    return "\n".join([
        f"In `results/`: {runs(RESULTS / 'bench_codegen.md', RESULTS / 'bench_ocp_arms.md')}.", "",
        "| Panda (7 joints) | measured | target |", "|---|---|---|",
        f"| forward dynamics, generated C (-O3, native) | {ns(fd)} | 5x faster than Pinocchio: {crba / fd:.1f}x |",
        f"| Pinocchio crba + rnea on the same 21-body tree (C++, before projection and solve) | {ns(crba)} | |",
        f"| inverse dynamics, generated C | {ns(float(cell['inverse_dynamics (ns)']))} | |",
        f"| forward-dynamics Jacobian, generated C | {ns(float(cell['forward_dynamics_jacobian (ns)']))} | |",
        f"| generate + compile all functions | {float(cell['generate + compile (s)']):.1f} s | < 30 s |",
        f"| minimum-time OCP, 150 intervals, fatrop, both cores: first compile; solve | "
        f"{float(ocp['setup_cold_s']):.1f} s; {float(ocp['solve_s']):.2f} s ({ocp['iterations']} iterations) "
        f"| < 30 s; < 0.5 s |",
    ]) + "\n"


def _rad(value: float) -> str:
    return f"{value:.2f} rad" if value >= 0.1 else f"{value:.1e} rad"


def mpc_closed_loop() -> str:
    """The MPC tutorial's closed-loop table, from the main job's results/mpc/closed_loop.json."""
    loop = json.loads((RESULTS / "mpc" / "closed_loop.json").read_text())
    plants = {"heavier_tip": "20 % heavier last link / nominal", "identified_on_true_arm": "true arm / identified model"}
    lines = ["| plant / controllers' model | controller | max error | RMS error | limit violation | step median / worst |",
             "|---|---|---|---|---|---|"]
    for plant, label in plants.items():
        runs = loop[plant]
        for i, (name, r) in enumerate(runs.items()):
            step = (f"{1e6 * r['step_median_s']:.0f} / {1e6 * r['step_worst_s']:.0f} us" if "step_median_s" in r else "")
            gain = (f" ({runs['feedforward + PD']['max_error'] / r['max_error']:.1f}x below PD)"
                    if name == "MPC (C)" else "")
            lines.append(f"| {label if i == 0 else ''} | {name} | {_rad(r['max_error'])}{gain} | "
                         f"{_rad(r['rms_error'])} | {r['max_limit_violation']:.2g} | {step} |")
    return "\n".join(lines) + "\n"


def mpc_steps() -> str:
    """The MPC tutorial's step-time table: the paced example program of bench_mpc.md."""
    text = (RESULTS / "bench_mpc.md").read_text()
    found = re.findall(r"(normal scheduling|rt \(SCHED_FIFO\)):\n\s*# .*?median ([0-9.]+) us, 99\.9% ([0-9.]+) us, "
                       r"worst ([0-9.]+) us over (\d+) steps(?: \(prepare \+ feedback\); mpc_feedback median ([0-9.]+) us"
                       r"[^;]*)?; (\d+) deadline", text)
    if len(found) != 2:
        raise FiguresError("results/bench_mpc.md: want the paced runs under normal and rt scheduling")
    split = all(f[5] for f in found)
    lines = [f"Run of {run_date(RESULTS / 'bench_mpc.md')} on {run_machine(RESULTS / 'bench_mpc.md')} "
             "(`results/bench_mpc.md`), reference arm:", "",
             "| `examples/mpc.c`, paced at 1 kHz, 10 s | median | 99.9 % | worst | steps over 1 ms |"
             + (" feedback phase, median |" if split else ""),
             "|---|---|---|---|---|" + ("---|" if split else "")]
    lines += [f"| {how} | {float(m):.0f} us | {float(p):.0f} us | {float(w):.0f} us | {miss} of {steps} |"
              + (f" {float(fb):.0f} us |" if split else "")
              for how, m, p, w, steps, fb, miss in found]
    return "\n".join(lines) + "\n"


BLOCKS = {
    "codegen-tutorial": codegen_tutorial,
    "urdf-panda": urdf_panda,
    "mpc-closed-loop": mpc_closed_loop,
    "mpc-steps": mpc_steps,
    "readme-speed": readme_speed,
    "readme-interaction": lambda: interaction_table(readme=True),
    "interaction": lambda: interaction_table(readme=False),
    "panda-shelf": panda_shelf,
}


def generate(key: str) -> str:
    """The text of the block KEY (see the module's docstring)."""
    if key.startswith("results/"):
        path, _, number = key.partition("#")
        if not (ROOT / path).is_file() or not number.isdigit():
            raise FiguresError(f"block {key!r}: want results/FILE.md#N with an existing file")
        return table_text(ROOT / path, int(number))
    if key not in BLOCKS:
        raise FiguresError(f"block {key!r}: no such generator (known: {', '.join(BLOCKS)})")
    return BLOCKS[key]()


# ---------------------------------------------------------------- pages

def pages() -> list[Path]:
    return sorted({p for pattern in PAGES for p in ROOT.glob(pattern)})


def refreshed(text: str) -> str:
    return BLOCK.sub(lambda m: m.group(1) + generate(m.group("key")) + m.group(4), text)


def _identification() -> dict:
    return json.loads((RESULTS / "identification" / "summary.json").read_text())


def held_out() -> str:
    """The identification demo's held-out motor-torque errors, '1.5 %, 0.9 % and 1.3 %'."""
    errors = [f"{100 * v['relative']:.1f} %" for v in _identification()["validation"]["prediction"].values()]
    return ", ".join(errors[:-1]) + " and " + errors[-1]


def model_errors() -> str:
    """Against the true torques: '0.10 / 0.08 / 0.15 % (complete) and 0.11 / 0.08 / 0.18 % (reduced)'."""
    e = _identification()["model_error"]
    return " and ".join(" / ".join(f"{100 * v[m]:.2f}" for v in e.values()) + f" % ({m})"
                        for m in ("complete", "reduced"))


def paper_loop() -> str:
    """The open-loop tracking from each model: 'to 0.09 mrad; identified, to 1.5-17 mrad, ...'."""
    loop = _identification()["paper_loop"]

    def span(key):
        worst = loop[key]["max_error"]
        return f"{1e3 * min(worst):.2g}-{1e3 * max(worst):.2g} mrad"
    return (f"to {1e3 * max(loop['true arm (ideal)']['max_error']):.2f} mrad; identified, to "
            f"{span('identified, rotor-separated')}, whichever\nmodel the feedforward uses (DLR from the same "
            f"identified parameters: {span('identified, DLR/Spong feedforward')})")


# figures quoted inside a sentence: each page must contain the text its generator writes
QUOTES = [
    ("README.md", interaction_gap),
    ("docs/user-guide/interaction.md", interaction_gap),
    ("docs/tutorials/identification.md", held_out),
    ("docs/tutorials/identification.md", model_errors),
    ("docs/tutorials/identification.md", paper_loop),
]


def stale() -> list[str]:
    """'page: KEY' for every block or quote whose text is not what its results file says."""
    blocks = [f"{page.relative_to(ROOT)}: {m.group('key')}" for page in pages()
              for m in BLOCK.finditer(page.read_text()) if m.group("body") != generate(m.group("key"))]
    quotes = [f"{page}: {quote.__name__} quotes no {quote()!r}" for page, quote in QUOTES
              if quote() not in (ROOT / page).read_text()]
    return blocks + quotes


def main(argv: list[str]) -> int:
    if "--check" in argv:
        found = stale()
        print("\n".join(f"stale: {s}" for s in found) or "every quoted block matches results/")
        return 1 if found else 0
    for page in pages():
        text = page.read_text()
        if BLOCK.search(text) and refreshed(text) != text:
            page.write_text(refreshed(text))
            print(f"rewrote {page.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
