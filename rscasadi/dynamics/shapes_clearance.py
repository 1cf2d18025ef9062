"""The URDF's own collision shapes against obstacles, measured by coal (the Flexible Collision
Library's successor, a distance library that shares no code with rscasadi): the check that the
capsules the optimiser keeps clear (rscasadi.model.collision) were never optimistic.

Shapes: every <collision> box, cylinder and sphere of a URDF link on a moving body (a fixed or
locked child's too) as coal's own primitive, and every mesh that can be read as the convex hull
of its vertices (which holds the mesh: its distance is never more than the mesh's).  Meshes that
cannot be read are left out, as the model's collision notes say.  Obstacles: coal's sphere and
box.  Distances are signed (negative: penetration), in metres.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from rscasadi.dynamics.kinematics import body_poses
from rscasadi.model.meshes import mesh_file, vertices


def _geometry(shape, urdf_path):
    """A URDF shape (kind, T, data) as a coal geometry, or None for a mesh that cannot be read."""
    import coal
    kind, _, data = shape
    if kind == "box":
        return coal.Box(*np.asarray(data, float))
    if kind == "cylinder":
        return coal.Cylinder(float(data[0]), float(data[1]))
    if kind == "sphere":
        return coal.Sphere(float(data))
    path, _ = mesh_file(urdf_path, data[0])
    if path is None:
        return None
    try:
        points = vertices(path) * np.asarray(data[1], float)
    except ValueError:
        return None
    hull = coal.StdVec_Vec3s()
    for p in points:
        hull.append(p)
    return coal.Convex.convexHull(hull, False, None)


def urdf_shapes(model) -> list:
    """[(body, T (4 x 4) in the body's frame, coal geometry, URDF link name)] of the model's URDF
    collision shapes on moving bodies (empty for a model without a URDF)."""
    geometry, urdf_path = model.extra.get("collision_geometry") or {}, model.extra.get("urdf")
    out = []
    for f in model.frames:
        if f.body == 0 or f.user:
            continue
        for shape in geometry.get(f.name, ()):
            g = _geometry(shape, urdf_path)
            if g is not None:
                place = np.eye(4)
                place[:3, :3], place[:3, 3] = f.R, f.p
                out.append((f.body, place @ np.asarray(shape[1], float), g, f.name))
    return out


def _obstacle(obstacle):
    import coal
    if obstacle.kind == "sphere":
        return coal.Sphere(float(obstacle.radius))
    return coal.Box(*np.asarray(obstacle.size, float))


def shapes_clearance(model, obstacles, theta) -> np.ndarray:
    """At each column of theta (n x K): the smallest signed distance (m) between the URDF's
    collision shapes and the obstacles, by coal; +inf where there is nothing to measure."""
    import coal
    theta = np.atleast_2d(np.asarray(theta, float).T).T
    shapes = urdf_shapes(model)
    out = np.full(theta.shape[1], np.inf)
    if not shapes or not obstacles:
        return out
    q = ca.SX.sym("theta", model.n)
    poses = ca.Function("poses", [q], [ca.vertcat(*[ca.vertcat(ca.vec(R), o) for R, o in body_poses(model, q)])])
    all_poses = np.array(poses.map(theta.shape[1])(theta))
    others = [(_obstacle(o), coal.Transform3s(np.eye(3), np.asarray(o.center, float))) for o in obstacles]
    request = coal.DistanceRequest()
    for k in range(theta.shape[1]):
        P = all_poses[:, k].reshape(-1, 12)
        for body, T, g, _ in shapes:
            R_b, o_b = P[body, :9].reshape(3, 3, order="F"), P[body, 9:]
            where = coal.Transform3s(R_b @ T[:3, :3], o_b + R_b @ T[:3, 3])
            for obstacle, there in others:
                result = coal.DistanceResult()
                out[k] = min(out[k], coal.distance(g, where, obstacle, there, request, result))
    return out
