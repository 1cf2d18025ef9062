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
    """A Markdown summary of a model: rotor inertias, couplings and the static holding torques."""
    arm = load(path)
    n, m = arm.n, arm.model
    theta = np.linspace(0.3, -0.6, n)
    M = np.array(arm.mass_matrix()(theta, theta))
    zero = np.zeros(n)
    T = np.array(arm.inverse_dynamics()(theta, theta, zero, zero, zero, zero)[1]).ravel()
    psi = T / m.column("k1")                         # static: k3 correction ignored in the report
    tau = np.array(arm.inverse_dynamics()(theta, theta + psi, zero, zero, zero, zero)[0]).ravel()
    shape = "a serial chain" if m.is_chain else f"a tree with {len(m.children(-1))} joints on the base"
    lines = [f"# Model `{m.name}` ({m.path})", "", f"{n} joints, {shape}; gravity {m.gravity.tolist()} m/s^2.", "",
             "| j | joint | carried by | mu | B_j = Izz(S)+mu^2 Izz(F) (kg m^2) | rotors balanced |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {j + 1} | {jt.name} | {'base' if p < 0 else m.joints[p].name} | {jt.gear_ratio:g} | "
              f"{jt.rotor_inertia:.6g} | {'yes' if jt.slow_rotor.balanced and jt.fast_rotor.balanced else 'no'} |"
              for j, (jt, p) in enumerate(zip(m.joints, m.parent))]
    S = M[:n, n:]
    lines += ["", f"Coupling block S (link rows, rotor columns) at theta = phi = {np.round(theta, 3).tolist()}:", ""]
    lines += ["| link \\ rotor | " + " | ".join(str(j + 1) for j in range(n)) + " |", "|---" * (n + 1) + "|"]
    lines += [f"| {i + 1} | " + " | ".join(f"{S[i, j]:.3g}" for j in range(n)) + " |" for i in range(n)]
    lines += ["", "Static holding at that pose: SEA torque T (N m), deflection psi = T/k1 (rad), motor torque tau (N m):",
              "", "| j | T | psi | tau |", "|---|---|---|---|"]
    lines += [f"| {j + 1} | {T[j]:.4g} | {psi[j]:.4g} | {tau[j]:.4g} |" for j in range(n)]
    if collision:
        lines += collision_report(m)
    return "\n".join(lines) + "\n"
