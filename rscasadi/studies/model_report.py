"""`rscasadi info`: a model's rotor inertias, couplings and static holding torques, and with
`--collision` every capsule kept clear of obstacles, in Markdown."""
from __future__ import annotations

import numpy as np

from rscasadi.dynamics.arm import load
from rscasadi.model.collision import capsules


def collision_report(model) -> list:
    """Every capsule that keeps clear of obstacles (the [collision] table's and the payload's),
    its ends in its link's frame, and the links with none."""
    lines = ["", "## Collision geometry", ""]
    caps = capsules(model)
    if not caps:
        return lines + ["No [collision] table and no payload radius: obstacles cannot be checked.", ""]
    margin = model.collision.margin if model.collision is not None else 0.0
    lines += [f"{len(caps)} capsules, margin {margin:g} m; ends a, b in the frame of the link their joint moves (m):",
              "", "| link (joint) | from | a | b | radius |", "|---|---|---|---|---|"]
    name = ["base"] + [jt.name for jt in model.joints]
    fmt = lambda v: "[" + ", ".join(f"{x:.4f}" for x in v) + "]"  # noqa: E731
    lines += [f"| {b} ({name[c.body]}) | {c.link} | {fmt(c.a)} | {fmt(c.b)} | {c.radius:.4f} |"
              for b in range(1, model.n + 1) for c in caps if c.body == b]
    bare = [name[b] for b in range(1, model.n + 1) if not any(c.body == b for c in caps)]
    if bare:
        lines += ["", f"Links with no geometry (never checked against obstacles): {', '.join(bare)}."]
    notes = model.collision.notes if model.collision is not None else ()
    if notes:
        lines += ["", "Beside the table, from the URDF:", ""] + [f"- {note}" for note in notes]
    return lines + [""]


def model_report(path, collision: bool = False) -> str:
    """A Markdown summary of a model of joints of any kind: each joint's kind, how it moves and its
    rotors, the links' coupling to the motors, and the statics at a pose (`rest`: the joints
    without an input where they hang, each SEA's motor where its spring holds its link)."""
    from rscasadi.dynamics.statics import rest
    arm = load(path)
    n, m = arm.n, arm.model
    theta, phi, tau = rest(arm, np.linspace(0.3, -0.6, n))
    M = np.array(arm.mass_matrix()(theta, phi))
    shape = "a serial chain" if m.is_chain else f"a tree with {len(m.children(-1))} joints on the base"
    lines = [f"# Model `{m.name}` ({m.path})", "", f"{n} joints, {shape}; {arm.m} motor coordinates, {arm.u} inputs; "
             f"gravity {m.gravity.tolist()} m/s^2.", "",
             "| j | joint | kind | moves | carried by | mu | B_j = Izz(S)+mu^2 Izz(F) (kg m^2) | rotors balanced |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {j + 1} | {jt.name} | {jt.kind} | {'turns' if jt.joint_motion.turns else 'slides'} | "
              f"{'base' if p < 0 else m.joints[p].name} | "
              + (f"{jt.gear_ratio:g} | {jt.rotor_inertia:.6g} | "
                 f"{'yes' if jt.slow_rotor.balanced and jt.fast_rotor.balanced else 'no'} |"
                 if jt.joint_kind.rotors else "- | - | - |")
              for j, (jt, p) in enumerate(zip(m.joints, m.parent))]
    pose = f"theta = {np.round(theta, 3).tolist()}, phi = {np.round(phi, 3).tolist()}"
    if arm.m:
        S, names = M[:n, n:], [m.joints[j].name for j in m.motors]
        lines += ["", f"Coupling block S (link rows, motor columns) at {pose}:", ""]
        lines += ["| link \\ motor | " + " | ".join(names) + " |", "|---" * (arm.m + 1) + "|"]
        lines += [f"| {jt.name} | " + " | ".join(f"{S[i, k]:.3g}" for k in range(arm.m)) + " |"
                  for i, jt in enumerate(m.joints)]
    motors = list(m.motors)
    deflection = phi - theta[motors]
    psi = dict(zip(motors, deflection))
    T = dict(zip(motors, m.column("k1")[motors] * deflection + m.column("k3")[motors] * deflection ** 3))
    inputs = dict(zip(m.actuated, tau))
    lines += ["", f"Static rest at {pose}: SEA torque T and deflection psi (rad), input tau "
                  "(N m; N on a sliding joint):", "", "| j | joint | T | psi | tau |", "|---|---|---|---|---|"]
    fmt = lambda table, j: f"{table[j]:.4g}" if j in table else "-"   # noqa: E731
    lines += [f"| {j + 1} | {jt.name} | {fmt(T, j)} | {fmt(psi, j)} | {fmt(inputs, j)} |" for j, jt in enumerate(m.joints)]
    if collision:
        lines += collision_report(m)
    return "\n".join(lines) + "\n"
