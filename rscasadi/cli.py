"""The `rscasadi` command."""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from rscasadi import __version__, interrupt
from rscasadi.files import CheckError, OutputError, write_json
from rscasadi.model.modelfile import ModelFileError
from rscasadi.studies.reproduce import PROBLEMS, TRAJECTORY
from rscasadi.errors import InvalidArgument


class Parser(argparse.ArgumentParser):
    """argparse, with a mistake told in one line (no usage block) and exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")

    def _get_values(self, action, arg_strings):
        # argparse drops "--" from an option's values, so "--margin=--" gave the option [] (no number)
        if action.option_strings and action.nargs is None and arg_strings == ["--"]:
            self.error(f"argument {'/'.join(action.option_strings)}: expected one value, got '--'")
        return super()._get_values(action, arg_strings)


def positive(kind, zero: bool = False, least=None):
    """An argparse type: a finite number of `kind`, > 0 (>= 0 with zero=True, >= least if given)."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'a whole number' if kind is int else 'a number'}")
        low = least if least is not None else 0
        if not np.isfinite(value) or value < low or (value == low and least is None and not zero):
            need = f">= {least}" if least is not None else (">= 0" if zero else "> 0")
            raise argparse.ArgumentTypeError(f"must be {need}, got {text!r}")
        return value
    parse.__name__ = kind.__name__
    return parse


def fraction(text: str) -> float:
    """An argparse type: a number in (0, 1]."""
    value = positive(float)(text)
    if value > 1:
        raise argparse.ArgumentTypeError(f"must be at most 1, got {text!r}")
    return value


def c_identifier(text: str) -> str:
    """A C identifier: letters, digits and underscores, not starting with a digit."""
    from rscasadi.native.generate import C_IDENTIFIER
    if not C_IDENTIFIER.match(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a C identifier")
    return text


def names_list(text: str) -> list:
    """A comma-separated list of names, none empty."""
    names = [t.strip() for t in text.split(",")]
    if not all(names):
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of names")
    return names


def float_list(text: str) -> list:
    """A comma-separated list of finite numbers."""
    try:
        values = [float(t) for t in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of numbers")
    if not all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"{text!r} holds a number that is not finite")
    return values


def opt_flag(text: str) -> str:
    """An optimisation flag for the C compiler, one the library takes (`OPT_LEVELS`)."""
    from rscasadi.native.build import OPT_LEVELS
    if text not in OPT_LEVELS:
        raise argparse.ArgumentTypeError(f"{text!r} is not one of {', '.join(OPT_LEVELS)}"
                                         + (" (-Ofast's -ffast-math would drop the NaN checks)" if text == "-Ofast" else ""))
    return text


def _cmd_info(args):
    from rscasadi.studies.model_report import model_report
    print(model_report(args.model, collision=args.collision), end="")


def _cmd_paper(args):
    from rscasadi.studies.paper import run
    run(args.trajectory, args.out, duration=args.duration, sweeps=not args.no_sweep,
        log=lambda msg: print(msg, flush=True), ocp_problem=args.ocp or None)


def _cmd_ocp(args):
    from rscasadi.ocp import run
    sol = run(args.problem, args.out, warm_file=args.warm, log=lambda msg: print(msg, flush=True),
              print_level=0 if args.quiet else (10 if args.verbose else 5), solver=args.solver, reuse=not args.cold)
    verdict = ("verified on the complete model" if sol["success"] else
               "NOT verified: the solver failed" if not sol["solver_success"] else
               "NOT verified: the replay on the complete model misses its tolerances")
    print(f"rscasadi ocp: wrote {Path(args.out) / 'solution.json'}, {sol['status']}, "
          f"{sol['t'][-1]:.4f} s of motion; {verdict}")
    return 0 if sol["success"] else 1


def _cmd_sweep(args):
    from rscasadi.ocp.sweep import run
    res = run(args.sweep, args.out, scheduler=args.scheduler, workers=args.workers,
              log=lambda msg: print(msg, flush=True))
    return 0 if res["solved"] == len(res["rows"]) else 1


def _cmd_mpc(args):
    from rscasadi.mpc import closed_loop, generate_mpc, plot_closed_loop
    from rscasadi.mpc.problem import mpc_problem
    from rscasadi.files import check_writable
    check_writable(args.out)
    generate_mpc(args.problem, args.out, opt=args.opt, log=lambda msg: print(msg, flush=True), model=args.model,
                 native=args.native, prefix=args.prefix or "")
    if args.study is not None and mpc_problem(args.problem).task_space:
        from rscasadi.mpc import plot_task_study, task_study
        res = task_study(args.problem, args.out, plant_mass=args.plant_payload, log=lambda msg: print(msg, flush=True))
        write_json(Path(args.out) / "closed_loop.json", res)
        plot_task_study(res, Path(args.out) / "closed_loop.png")
        print(f"wrote {Path(args.out) / 'closed_loop.json'} and closed_loop.png")
    elif args.study is not None:
        traces = {}
        res = closed_loop(args.problem, args.out, duration=args.study or None, log=lambda msg: print(msg, flush=True),
                          model=args.model, traces=traces)
        out = Path(args.out)
        from rscasadi.files import replacing
        with replacing(out / "closed_loop.png") as tmp_png:         # both files, or neither
            plot_closed_loop({"heavier_tip": traces}, tmp_png)
            write_json(out / "closed_loop.json", res)
        print(f"wrote {out / 'closed_loop.json'} and closed_loop.png")


def _cmd_simulate(args):
    from rscasadi.identification.synthetic import simulate_log
    simulate_log(args.model, args.trajectory, args.out, rate=args.rate, noise=args.noise, perturb=args.perturb,
                 true_model=args.true_model, simulator=args.simulator, columns=args.columns, log_rate=args.log_rate,
                 log=lambda msg: print(msg, flush=True))


def _cmd_view(args):
    from rscasadi.files import check_output_file
    from rscasadi.view import scene_of, write_gif, write_html
    if args.gif and Path(args.gif).suffix.lower() != ".gif":
        raise InvalidArgument(f"--gif {args.gif}: the animation's file name must end in .gif")
    for target in [args.out] + ([args.gif] if args.gif else []):
        check_output_file(target)
    scene = scene_of(args.result, model=args.model)
    for name, why in scene.skipped:
        print(f"skipped mesh {name!r}: {why}; its link is drawn by its capsules")
    write_html(scene, Path(args.out))
    print(f"wrote {args.out} ({len(scene.times)} frames over {scene.times[-1]:.3f} s)")
    if args.gif:
        write_gif(scene, Path(args.gif))
        print(f"wrote {args.gif}")


def _cmd_export_mujoco(args):
    from rscasadi.export import export_mujoco
    from rscasadi.files import check_writable
    check_writable(args.out)
    export_mujoco(args.model, args.out, log=lambda msg: print(msg, flush=True),
                  variant="armature" if args.armature else "reduced" if args.reduced else "complete")


def _cmd_reproduce(args):
    from rscasadi.studies.reproduce import run
    summary = run(args.out, log=lambda msg: print(msg, flush=True))
    failed = [name for name, state, _ in summary if state != "ok"]
    if failed:
        print(f"rscasadi: error: parts failed or skipped: {', '.join(failed)}", file=sys.stderr)
        return 1


def _cmd_codegen(args):
    from rscasadi.codegen import generate
    t0 = time.perf_counter()
    manifest = generate(args.model, args.out, prefix=args.prefix, opt=args.opt,
                        log=lambda msg: print(msg, flush=True), parametric=args.parametric, native=args.native,
                        frames=args.frames, external=args.external, only=args.only)
    for name, info in manifest["functions"].items():
        print(f"  {info['symbol']:40s} n_instructions {info['n_instructions']}")
    for name, why in manifest["omitted"].items():
        print(f"  omitted {name}: {why}")
    print(f"wrote {Path(args.out) / manifest['library']} and {manifest['header']} "
          f"({time.perf_counter() - t0:.1f} s)")


def _cmd_observer(args):
    from rscasadi.files import check_writable
    from rscasadi.interaction import generate_observer
    if args.gain * args.sample_time >= 1.0:
        raise InvalidArgument(f"--gain {args.gain:g} 1/s at --sample-time {args.sample_time:g} s: K times the sample "
                         "time must be below 1 (the discrete observer is unstable otherwise)")
    check_writable(args.out)
    generate_observer(args.model, args.out, args.gain, args.sample_time, threshold=args.threshold, opt=args.opt,
                      log=lambda msg: print(msg, flush=True), prefix=args.prefix or "")


def _cmd_impedance(args):
    from rscasadi.files import check_writable
    from rscasadi.interaction import generate_impedance
    log = lambda msg: print(msg, flush=True)  # noqa: E731
    check_writable(args.out)
    if not args.study:
        generate_impedance(args.model, args.out, None if args.joint_space else args.frame, design=args.design,
                           opt=args.opt, log=log, prefix=args.prefix or "")
        return 0
    from rscasadi.dynamics.arm import load
    from rscasadi.interaction.study import study
    if args.joint_space or args.theta is None:
        raise InvalidArgument("--study: needs --frame and --theta (the configuration the arm is held at)")
    arm = load(args.model)
    if len(args.theta) != arm.n:
        raise InvalidArgument(f"--theta: {len(args.theta)} angles for the {arm.n} joints of {args.model}")
    if args.frame not in arm.frames():
        raise InvalidArgument(f"--frame: {args.model} has no frame {args.frame!r} (frames: {', '.join(arm.frames())})")
    trajectory = None
    if args.trajectory is not None:
        from rscasadi.sim.trajectory import load_trajectory
        trajectory = load_trajectory(args.trajectory)
        if trajectory.n != arm.n:
            raise InvalidArgument(f"--trajectory: {args.trajectory} moves {trajectory.n} joints, {args.model} has {arm.n}")
    study(arm, args.frame, args.theta, args.out, gain=args.gain, threshold=args.threshold, trajectory=trajectory,
          short=args.short, opt=args.opt, log=log)
    return 0

def _cmd_excite(args):
    from rscasadi.identification.excitation import run
    run(args.model, args.out, period=args.period, harmonics=args.harmonics, starts=args.starts, samples=args.samples,
        max_iter=args.max_iter, hessian=args.hessian, margin=args.margin, max_condition=args.max_condition,
        log=lambda msg: print(msg, flush=True))


def _cmd_frf(args):
    from rscasadi.identification.frf import run as run_frf
    run_frf(args.model, args.out, args.log, joint=args.joint, output=args.output, pose=args.pose,
            resolution=args.resolution, say=lambda m: print(m, flush=True))


def _cmd_identify(args):
    if args.only == "payload":
        from rscasadi.identification.payload import run as run_payload
        run_payload(args.model, args.logs, args.out, validate=args.validate, cutoff=args.cutoff,
                    log=lambda msg: print(msg, flush=True))
        return
    from rscasadi.identification.identify import run
    run(args.model, args.logs, args.out, validate=args.validate, cutoff=args.cutoff, explain=args.explain,
        reduced=args.reduced, log=lambda msg: print(msg, flush=True))


def build_parser() -> argparse.ArgumentParser:
    """The `rscasadi` command's parser: one subcommand per job, every option checked by its type."""
    parser = Parser(prog="rscasadi", description="Rotor-separated FS-SEA arm dynamics in CasADi")
    parser.add_argument("--version", action="version", version=f"rscasadi {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    p = sub.add_parser("info", help="summarise a model file")
    p.add_argument("model")
    p.add_argument("--collision", action="store_true",
                   help="list every capsule kept clear of obstacles (link, ends, radius) and the links with none")
    p.set_defaults(func=_cmd_info)
    p = sub.add_parser("codegen", help="generate and compile C for a model's functions")
    p.add_argument("model")
    p.add_argument("--out", required=True, help="directory for the sources, header, library and manifest.json")
    p.add_argument("--prefix", default=None, type=c_identifier, help="C identifier put before every function name (P_name)")
    p.add_argument("--opt", default="-O3", type=opt_flag, help="optimisation flag (default -O3)")
    p.add_argument("--parametric", nargs="?", const="all", default="none", choices=("none", "all", "family"),
                   help="every function takes the parameter vector p last (names in manifest.json): one library "
                        "for every arm with these joints, no recompilation when a number changes; 'family': p "
                        "without the parameters that are zero in this model (folded, near the constant C's speed)")
    p.add_argument("--native", action="store_true",
                   help="compile for this machine's processor (-march=native, fused multiply-adds): the step "
                        "Jacobian's kernel ~20 %% faster; the sources stay portable C99")
    p.add_argument("--frames", type=names_list, default=[],
                   help="comma-separated frames whose placement, Jacobians, velocity and dJ*v (and the centre of "
                        "mass) the library gets")
    p.add_argument("--external", type=names_list, default=[],
                   help="comma-separated frames at which the dynamics take a wrench [force; moment] "
                        "(forward_dynamics_external, inverse_dynamics_external)")
    p.add_argument("--only", type=names_list, default=None,
                   help="comma-separated names of the functions to generate (default: all of them)")
    p.set_defaults(func=_cmd_codegen)
    p = sub.add_parser("paper", help="reproduce the paper's simulation (Figs. 5-11), the cascade study and sweeps")
    p.add_argument("--trajectory", default=str(TRAJECTORY), help="expected-trajectory file (names its model)")
    p.add_argument("--out", default="results/paper")
    p.add_argument("--duration", type=positive(float), default=None, help="simulated time (default: the file's)")
    p.add_argument("--no-sweep", action="store_true", help="skip the parameter sweeps")
    p.add_argument("--ocp", default=str(PROBLEMS / "ocp_tracking.toml"),
                   help="tracking OCP problem for method (c) (empty string: skip)")
    p.set_defaults(func=_cmd_paper)
    p = sub.add_parser("ocp", help="solve an optimal-control problem file, verify it, write solution.json and plots")
    p.add_argument("problem")
    p.add_argument("--out", default="results/ocp")
    p.add_argument("--warm", default=None, help="a previous solution.json to start from")
    p.add_argument("--cold", action="store_true",
                   help="start from the problem's own guess, not from the verified solution of the same problem "
                        "that an earlier run kept in the cache (its refined mesh and states); this run's is kept")
    p.add_argument("--quiet", action="store_true", help="no solver iteration log")
    p.add_argument("--verbose", action="store_true", help="the solver's whole log (fatrop: its iterative refinement too)")
    p.add_argument("--solver", choices=("ipopt", "fatrop"), help="override the problem file's [solver] name")
    p.set_defaults(func=_cmd_ocp)
    p = sub.add_parser("mpc", help="generate a nonlinear MPC (multiple shooting, SQP or real-time iteration on the "
                                   "complete model) as C")
    p.add_argument("problem", help="MPC problem file (TOML)")
    p.add_argument("--out", default="build/mpc")
    p.add_argument("--model", default=None, help="a model file that replaces the problem's (e.g. an identified one)")
    p.add_argument("--prefix", default=None, type=c_identifier,
                   help="C identifier before every symbol and file (P_mpc_init, P_mpc.h): controllers link together")
    p.add_argument("--opt", default="-O3", type=opt_flag, help="optimisation flag for the library (default -O3)")
    p.add_argument("--native", action=argparse.BooleanOptionalAction, default=True,
                   help="compile for this machine's processor (-march=native, fused multiply-adds; the default: "
                        "the fast controller a 1 kHz loop needs); --no-native: a library for any processor of "
                        "this architecture (also for valgrind, which does not know every vector instruction). "
                        "The sources stay portable C99")
    p.add_argument("--study", type=positive(float, zero=True), nargs="?", const=0.0, metavar="SECONDS",
                   help="then run the closed-loop study (heavier tip, quantised encoders) for SECONDS "
                        "(default: the whole trajectory) and write closed_loop.json; a task-space problem: "
                        "its path with the problem's payload, and with --plant-payload kg untold and told")
    p.add_argument("--plant-payload", type=positive(float), default=None, metavar="KG",
                   help="task-space study: the payload the arm really holds (default: 10 times the problem's)")
    p.set_defaults(func=_cmd_mpc)
    p = sub.add_parser("sweep", help="solve an optimal-control problem over a grid of parameters, in parallel on Dask")
    p.add_argument("sweep", help="sweep file (TOML): problem and [grid]")
    p.add_argument("--out", default="results/sweep")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler (default: a local cluster)")
    p.add_argument("--workers", type=positive(int), help="local cluster size (default: this machine's cores)")
    p.set_defaults(func=_cmd_sweep)
    p = sub.add_parser("excite", help="design a periodic excitation trajectory for identification")
    p.add_argument("model")
    p.add_argument("--out", required=True, help="directory for trajectory.toml, feedforward.csv, excitation.json")
    p.add_argument("--period", type=positive(float), default=10.0, help="period of the Fourier series (s), default 10")
    p.add_argument("--harmonics", type=positive(int, least=3), default=5,
                   help="harmonics per joint (at least 3: the rest conditions take two), default 5")
    p.add_argument("--starts", type=positive(int), default=3, help="deterministic starts, the best kept (default 3; "
                   "fewer: faster)")
    p.add_argument("--samples", type=positive(int, least=10), default=None, help="points the limits and the "
                   "information are taken at (default max(60, 12 x harmonics); fewer: faster, coarser)")
    p.add_argument("--max-iter", type=positive(int), default=500, help="IPOPT iterations per start (default 500)")
    p.add_argument("--hessian", choices=("limited-memory", "exact"), default="limited-memory",
                   help="IPOPT's Hessian: limited-memory (default; cheap iterations) or exact (dear ones)")
    p.add_argument("--margin", type=fraction, default=0.85, help="fraction of each limit the design may use "
                   "(default 0.85; the exact feedforward is then scaled into the limits)")
    p.add_argument("--max-condition", type=positive(float), default=1e5, help="the largest condition number "
                   "accepted (default 1e5)")
    p.set_defaults(func=_cmd_excite)
    p = sub.add_parser("simulate", help="a synthetic log of the arm along a trajectory, to try identification")
    p.add_argument("model")
    p.add_argument("trajectory", help="trajectory file (rscasadi excite's trajectory.toml, or start/amplitude)")
    p.add_argument("--out", required=True, help="the log to write (CSV: t and the --columns groups)")
    p.add_argument("--rate", type=positive(float), default=1000.0, help="the control loop's rate (default 1000 Hz)")
    p.add_argument("--log-rate", type=positive(float), default=None, metavar="HZ",
                   help="samples per second in the log (default --rate; it must divide --rate): a robot that "
                        "publishes at 100 Hz while it controls at 1 kHz")
    p.add_argument("--columns", default="theta,phi,tau", metavar="GROUPS",
                   help="the sensors logged, comma-separated groups of theta, phi, tau, T, dtheta, dphi "
                        "(default theta,phi,tau; theta,T: a link-side log, what sold SEA and torque-sensing arms "
                        "publish)")
    p.add_argument("--noise", type=positive(float, zero=True), default=0.005,
                   help="torque noise, a fraction of each joint's torque limit (default 0.005)")
    p.add_argument("--perturb", type=positive(int, zero=True), default=None, metavar="SEED",
                   help="log a different arm of the family (every parameter off by 10-40 %%, cubic springs and "
                        "Coulomb loss added), drawn with this seed")
    p.add_argument("--true-model", default=None, metavar="FILE", help="write the arm that was simulated here")
    p.add_argument("--simulator", choices=("rscasadi", "mujoco"), default="rscasadi",
                   help="whose physics records the log: rscasadi's complete model (RK4), or MuJoCo's of the arm "
                        "exported (rscasadi export mujoco; a perturbed arm then keeps linear springs and no "
                        "Coulomb loss, which MJCF cannot hold)")
    p.set_defaults(func=_cmd_simulate)
    p = sub.add_parser("identify", help="identify the complete model from logs (CSV: t,theta_j and any of "
                       "phi_j, tau_j, T_j, dtheta_j, dphi_j)")
    p.add_argument("model", help="model file: kinematics, gear ratios and the starting guess")
    p.add_argument("logs", nargs="+", help="one or more logs")
    p.add_argument("--out", required=True, help="directory for model.toml, report.json and figures")
    p.add_argument("--validate", default=None, help="a held-out log: prediction error of the identified model")
    p.add_argument("--cutoff", type=positive(float), default=None,
                   help="filter cut-off (Hz); default: 2x the highest SEA mode, or for a link-side log where the "
                        "logged motion ends (report.json: cutoff_why; with --validate, cutoff_check tries others)")
    p.add_argument("--explain", action="store_true", help="print the base parameters as combinations of physical ones")
    p.add_argument("--reduced", action="store_true", help="identify the DLR/Spong reduced model instead (ablation)")
    p.add_argument("--only", choices=["payload"], default=None,
                   help="identify only the model file's [payload], everything else held at the file's values")
    p.set_defaults(func=_cmd_identify)
    p = sub.add_parser("frf", help="a joint's frequency response: the model's (complete and rigid) and a log's")
    p.add_argument("model")
    p.add_argument("log", nargs="?", default=None, help="a log with tau_j (the input): its H1 estimate beside the model's")
    p.add_argument("--joint", type=positive(int), default=1, help="the joint (from 1; default 1)")
    p.add_argument("--output", choices=("phi", "theta"), default="phi",
                   help="the response of the motor angle (default: collocated, anti-resonance and resonance) or the link's")
    p.add_argument("--pose", type=float, nargs="+", default=None, metavar="RAD",
                   help="the link angles to linearise at (default: the log's mean, else mid-range)")
    p.add_argument("--resolution", type=positive(float), default=0.25, metavar="HZ",
                   help="the log estimate's frequency bins (default 0.25 Hz; finer bins average fewer segments)")
    p.add_argument("--out", required=True, help="directory for frf.png and frf.json")
    p.set_defaults(func=_cmd_frf)
    p = sub.add_parser("view", help="a solution.json or a model file as a 3D animation in one HTML file (offline)")
    p.add_argument("result", help="a solution.json (rscasadi ocp) or a model file")
    p.add_argument("--out", required=True, help="the HTML file to write (open it as view.html#t=0.35 for 0.35 s)")
    p.add_argument("--gif", default=None, help="also an animated GIF, for documents")
    p.add_argument("--model", default=None, help="draw this model file instead of the solution's")
    p.set_defaults(func=_cmd_view)
    p = sub.add_parser("controller", help="generate an interaction controller or observer as C")
    kinds = p.add_subparsers(dest="kind", required=True, parser_class=Parser)
    q = kinds.add_parser("observer", help="the generalised-momentum observer of external torques (complete model)")
    q.add_argument("model")
    q.add_argument("--gain", type=positive(float), required=True, metavar="K",
                   help="the observer's bandwidth K (1/s): dr/dt = K (tau_ext - r); K times the sample time < 1")
    q.add_argument("--sample-time", type=positive(float), default=1e-3, metavar="S", help="seconds (default 0.001)")
    q.add_argument("--threshold", type=positive(float), default=float("inf"), metavar="NM",
                   help="observer_step returns OBSERVER_COLLISION (1) while a link's |r| exceeds this (N m)")
    q.add_argument("--out", required=True, help="directory for the sources, header, library and manifest.json")
    q.add_argument("--opt", default="-O2", type=opt_flag, help="optimisation flag (default -O2)")
    q.add_argument("--prefix", default=None, type=c_identifier,
                   help="C identifier before every symbol and file (P_observer_init, P_observer.h)")
    q.set_defaults(func=_cmd_observer)
    q = kinds.add_parser("impedance", help="the impedance controller through the SEAs (complete model), or its study")
    q.add_argument("model")
    where = q.add_mutually_exclusive_group(required=True)
    where.add_argument("--frame", help="Cartesian: the frame whose stiffness is commanded (e.g. tool)")
    where.add_argument("--joint-space", action="store_true", help="joint space: a stiffness per joint")
    q.add_argument("--design", choices=("motor", "link"), default="motor",
                   help="motor: on motor positions, passive (default); link: on link angles, stiffer than the springs")
    q.add_argument("--out", required=True, help="directory for the sources, header, library and manifest.json "
                   "(with --study: for study.md, study.json and study.png)")
    q.add_argument("--opt", default="-O2", type=opt_flag, help="optimisation flag (default -O2)")
    q.add_argument("--prefix", default=None, type=c_identifier,
                   help="C identifier before every symbol and file (P_impedance_init, P_impedance.h)")
    q.add_argument("--study", action="store_true", help="run the closed-loop study instead: push, wall, collision, "
                   "reduced-model design, C time per step (about a minute on 7 joints)")
    q.add_argument("--theta", type=float_list, default=None, help="with --study: the configuration, rad, comma-separated")
    q.add_argument("--gain", type=positive(float), default=50.0, metavar="K",
                   help="with --study: the observer's gain, 1/s (default 50)")
    q.add_argument("--threshold", type=positive(float), default=1.0, metavar="NM",
                   help="with --study: the observer's collision threshold on any link, N m (default 1)")
    q.add_argument("--trajectory", default=None, metavar="FILE",
                   help="with --study: also a collision during this trajectory's feedforward motion")
    q.add_argument("--short", action="store_true", help="with --study: fewer and shorter cases")
    q.set_defaults(func=_cmd_impedance)
    p = sub.add_parser("export", help="the model for another simulator: mujoco (MJCF, the complete model)")
    kinds_export = p.add_subparsers(dest="format", required=True, parser_class=Parser)
    q = kinds_export.add_parser("mujoco", help="MJCF: links and both rotors as bodies, the gear an equality, "
                                "the spring a tendon; RK4 at 1 ms")
    q.add_argument("model")
    q.add_argument("--out", required=True, help="directory for model.xml")
    variant = q.add_mutually_exclusive_group()
    variant.add_argument("--armature", action="store_true",
                         help="the rigid-joint model with the rotors as armature that MuJoCo users write, for comparison")
    variant.add_argument("--reduced", action="store_true",
                         help="the DLR/Spong reduced model: rotors welded to their links, each motor a joint of its own")
    q.set_defaults(func=_cmd_export_mujoco)
    p = sub.add_parser("reproduce", help="the main job: everything the project reproduces, into --out")
    p.add_argument("--out", default="results")
    p.set_defaults(func=_cmd_reproduce)
    return parser


def main(argv=None, exit_on_interrupt: bool = False):
    """Run the command in argv; its exit code.  exit_on_interrupt (the `rscasadi` command): after
    Ctrl-C or SIGTERM end the process at once, inside the handler, once every `finally` has run:
    the interrupted solve's native objects are then never torn down (a fatrop solver stopped
    mid-solve crashes in its destructor)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    interrupt.install(command=exit_on_interrupt)    # Ctrl-C inside a solver stops the command, not just the solver
    try:
        code = args.func(args)
    except BaseException as exc:
        # an interrupt can surface as another exception when it lands inside a C extension
        if isinstance(exc, KeyboardInterrupt) or interrupt.happened():
            word, code = ("terminated", 143) if interrupt.terminated() else ("interrupted", 130)
            if exit_on_interrupt:
                sys.stdout.flush()
                interrupt.say(f"rscasadi: {word}; nothing half-written was kept")
                os._exit(code)
            print(f"rscasadi: {word}; nothing half-written was kept", file=sys.stderr)
            return code
        if isinstance(exc, (ModelFileError, OutputError, CheckError, ValueError)):
            print(f"rscasadi: error: {exc}", file=sys.stderr)
            return 2
        if isinstance(exc, OSError):        # a path, permission or disk problem of the user's
            where = f"{exc.filename}: " if exc.filename else ""
            print(f"rscasadi: error: {where}{exc.strerror or exc}", file=sys.stderr)
            return 2
        raise
    return code or 0


def entry(argv=None):
    """The `rscasadi` command: main's exit code (an interrupt ends the process in main).  A crash
    in native code (a solver's C) prints every thread's Python stack to stderr (faulthandler)."""
    import faulthandler
    faulthandler.enable()
    sys.exit(main(argv, exit_on_interrupt=True))


if __name__ == "__main__":
    entry()
