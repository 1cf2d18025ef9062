"""Joint kinds (docs/user-guide/model.md section 4): what a joint has besides its link.

Each kind is one small constant object: which coordinates the joint adds, what its two rotors
turn with, whether it takes a torque input, and which [[joints]] keys it needs or cannot have.
Every caller reads these attributes; none asks for a kind by name.

| kind     | coordinates            | rotors (bodies on the parent link)   | input  | force on the link                 |
|----------|------------------------|--------------------------------------|--------|-----------------------------------|
| `sea`    | theta, phi (`.motor`)  | turn with phi: slow 1, fast -mu      | tau    | the spring T(phi - theta)         |
| `geared` | theta                  | turn with theta: slow 1, fast -mu    | tau    | -mu tau - gear loss, through gear |
| `spring` | theta                  | none                                 | none   | -k (theta - theta0)               |
| `free`   | theta                  | none                                 | none   | none                              |
| `direct` | theta                  | none                                 | tau    | tau on the joint                  |

A joint turns its link about its axis (URDF revolute or continuous), or slides it along the axis
(prismatic: spring, free and direct only, its coordinate in m and its force in N; rotors turn).
A `geared` joint is an `sea` joint whose spring is rigid: k1 -> infinity takes one to the other.
Every kind also feels its link-side loss (`link_loss`).  A `locked` joint is not a joint of the
model: a URDF's [locked] table holds it, its child link merged into its parent.
"""
from __future__ import annotations

from dataclasses import dataclass

REVOLUTE = ("revolute", "continuous")
SLIDING = REVOLUTE + ("prismatic",)


@dataclass(frozen=True)
class Kind:
    """One kind of joint: its coordinates, its rotors, its input and its [[joints]] keys."""
    name: str
    motor: bool          # a motor coordinate phi_j of its own: the SEA's slow side, behind the spring
    rotors: str          # what the two rotors turn with: "motor" (phi_j), "link" (theta_j), "" (no rotors)
    actuated: bool       # a motor torque input tau_j
    required: tuple      # [[joints]] keys it needs beside name (and link, in the link-list form)
    refused: tuple       # [[joints]] keys it cannot have
    fits: tuple          # the URDF joint types it can model

    def coordinates(self, joint: str) -> list:
        """The names of the joint's coordinates: `<joint>` and, with a motor, `<joint>.motor`."""
        return [joint] + ([f"{joint}.motor"] if self.motor else [])


_ROTOR_KEYS = ("gear_ratio", "slow_rotor", "fast_rotor", "gear_loss", "torque_constant")
SEA = Kind("sea", True, "motor", True, ("gear_ratio", "sea", "slow_rotor", "fast_rotor"), ("spring",), REVOLUTE)
GEARED = Kind("geared", False, "link", True, ("gear_ratio", "slow_rotor", "fast_rotor"), ("sea", "spring"), REVOLUTE)
SPRING = Kind("spring", False, "", False, ("spring",), _ROTOR_KEYS + ("sea", "counterbalance"), SLIDING)
FREE = Kind("free", False, "", False, (), _ROTOR_KEYS + ("sea", "spring"), SLIDING)
DIRECT = Kind("direct", False, "", True, (), _ROTOR_KEYS + ("sea", "spring"), SLIDING)
KINDS = {k.name: k for k in (SEA, GEARED, SPRING, FREE, DIRECT)}


def kind_of(name) -> Kind | None:
    """The kind called `name`, or None."""
    return KINDS.get(name) if isinstance(name, str) else None


def require_sea(model, what: str) -> None:
    """Refuse, naming every other joint, a robot whose joints are not all SEAs for `what` (the
    capabilities written for the paper's arm of SEAs: docs/user-guide/model.md section 4)."""
    from rscasadi.errors import InvalidArgument
    other = [f"{jt.name} ({jt.kind})" for jt in model.joints if jt.kind != "sea"]
    if other:
        raise InvalidArgument(f"{model.path}: {what} takes robots whose joints are all SEAs; "
                              f"joints of other kinds: {', '.join(other)}")
