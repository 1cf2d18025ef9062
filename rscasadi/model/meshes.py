"""Mesh files a URDF names, read only inside the robot's own package, and the capsule that
holds a mesh.

A robot-description package is the nearest folder holding a package.xml, the URDF's own or up
to three above it, else the URDF's folder.  A mesh name is found relative to the URDF or, as
`package://pkg/...`, under that root (with or without the package's own name).  Absolute
paths, names climbing out of the package, links that leave it, special files and files that
are not STL, OBJ or DAE are never read: a shared model must not make a command read a user's
other files.
"""
from __future__ import annotations

import stat
from functools import lru_cache
from pathlib import Path

from typing import Any
import numpy as np
from rscasadi.errors import InvalidArgument

MESHES = (".stl", ".obj", ".dae")


def package_root(urdf: Path) -> Path:
    """The robot's package: the nearest folder with a package.xml, the URDF's or up to three
    above it, else the URDF's folder."""
    folder = Path(urdf).resolve().parent
    for root in (folder, *folder.parents[:3]):
        if (root / "package.xml").is_file():
            return root
    return folder


def _inside(path: Path, root: Path) -> Path | None:
    """path if it is a regular mesh file inside root once every link is followed, else None."""
    try:
        real = path.resolve(strict=True)
        mode = real.stat().st_mode
    except (OSError, RuntimeError):
        return None
    if not real.is_relative_to(root) or not stat.S_ISREG(mode) or real.suffix.lower() not in MESHES:
        return None
    return real


def _sized(path: Path) -> tuple[Path | None, str]:
    """(path, "") for a mesh small enough to read, else (None, why): checked before trimesh reads it."""
    from rscasadi.files import size_refusal
    why = size_refusal(path, "mesh")
    return (None, why) if why else (path, "")


def mesh_file(urdf: Path, name: str) -> tuple[Path | None, str]:
    """A mesh file inside the robot's package, and why not where there is none."""
    urdf = Path(urdf)
    root = package_root(urdf)
    if name.startswith("file://"):
        name = name[len("file://"):]
    if Path(name).suffix.lower() not in MESHES:
        return None, "not an STL, OBJ or DAE mesh"
    if not name.startswith("package://"):
        if Path(name).is_absolute():
            return None, f"an absolute path (outside the robot's package {root})"
        found = _inside(urdf.resolve().parent / name, root)
        return _sized(found) if found else (None, f"not a mesh file inside the robot's package {root}")
    parts = Path(name[len("package://"):]).parts
    if ".." in parts:
        return None, f"climbs out of the robot's package {root}"
    for k in range(len(parts)):                         # with or without the package's own name
        found = _inside(root.joinpath(*parts[k:]), root)
        if found:
            return _sized(found)
    return None, f"not found inside the robot's package {root} (a package.xml marks its root)"


@lru_cache(maxsize=256)
def _vertices(path: str, mtime_ns: int) -> np.ndarray:
    import trimesh
    loaded: Any = trimesh.load(path, force="mesh", process=False)     # a Trimesh (force="mesh")
    v = np.asarray(loaded.vertices, float)
    if v.ndim != 2 or v.shape[0] == 0 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
        raise InvalidArgument("no finite vertices")
    return v


def vertices(path: Path) -> np.ndarray:
    """A mesh file's vertices (k x 3, in its own units); a ValueError says why it cannot be read."""
    try:
        return _vertices(str(path), Path(path).stat().st_mtime_ns)
    except ValueError:
        raise
    except Exception as exc:                                    # trimesh's readers raise many kinds
        raise InvalidArgument(f"cannot be read ({type(exc).__name__}: {exc})") from None


def bounding_capsule(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """A capsule (a, b, radius) that holds every point, hence their convex hull: its axis the
    points' principal direction through their centroid, its radius the largest distance from
    that axis, and its segment as short as that radius allows."""
    points = np.asarray(points, float)
    c = points.mean(axis=0)
    d = points - c
    axis = np.linalg.svd(d, full_matrices=False)[2][0] if len(points) > 1 else np.array([0.0, 0.0, 1.0])
    t = d @ axis
    rho = np.linalg.norm(d - np.outer(t, axis), axis=1)
    r = float(rho.max()) if rho.max() > 0 else 1e-9
    reach = np.sqrt(np.maximum(r ** 2 - rho ** 2, 0.0))       # how far along the axis a point may lie from an end
    lo, hi = float(np.min(t + reach)), float(np.max(t - reach))
    if lo > hi:                          # any point between them holds them all: a sphere
        lo = hi = 0.5 * (lo + hi)
    return c + lo * axis, c + hi * axis, r * (1 + 1e-9) + 1e-12
