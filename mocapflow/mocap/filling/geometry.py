"""Small geometry of the constraint cases: the two-sphere circle (appendix C), the minimal rotation between two
directions, and a camera ray: the projection on it (5.3.5) and the slide along it to a segment's shape (appendices D,
E)."""

from __future__ import annotations

import numpy as np


def nearest_on_circle(
    p1: np.ndarray, p2: np.ndarray, r1: np.ndarray, r2: np.ndarray, guess: np.ndarray
) -> np.ndarray:
    """Points on the circles where spheres (p1, r1) and (p2, r2) meet, nearest to ``guess`` (appendix C).

    All arguments are batched (K, 3) or (K,). Spheres that miss each other (noise) give their closest point on the
    line of centres; a guess on the axis keeps its direction from the closest circle point to it.
    """
    axis = p2 - p1
    d = np.maximum(np.linalg.norm(axis, axis=-1), 1e-9)
    u = axis / d[:, None]
    along = (d**2 + r1**2 - r2**2) / (2 * d)
    radius = np.sqrt(np.maximum(r1**2 - along**2, 0.0))
    centre = p1 + along[:, None] * u
    v = guess - centre
    v -= np.einsum("ki,ki->k", v, u)[:, None] * u
    norm = np.linalg.norm(v, axis=-1)
    v /= np.maximum(norm, 1e-300)[:, None]
    on_axis = ~(norm > 1e-9)
    if on_axis.any():
        fallback = np.cross(u[on_axis], np.where(np.abs(u[on_axis, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        v[on_axis] = fallback / np.linalg.norm(fallback, axis=-1, keepdims=True)
    return centre + radius[:, None] * v


def unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def swing(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``u`` to unit vector ``v``, from the half-way quaternion (always
    orthonormal; written out because it runs per hidden segment and frame)."""
    ux, uy, uz = u.tolist()
    vx, vy, vz = v.tolist()
    w, x, y, z = 1.0 + ux * vx + uy * vy + uz * vz, uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    if w < 1e-9:  # opposite: half a turn about a perpendicular
        w, (x, y, z) = 0.0, np.cross(u, [1.0, 0, 0] if abs(ux) < 0.9 else [0, 1.0, 0]).tolist()
    n = w * w + x * x + y * y + z * z
    s = 2.0 / n
    return np.array([
        [1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)],
        [s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)],
        [s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)]])


def project_on_rays(points: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Orthogonal projections of ``points`` (K, 3) on the lines ``rays`` (K, 6) = origin + direction (5.3.5)."""
    origin, direction = rays[:, :3], rays[:, 3:]
    direction = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    return origin + np.einsum("ki,ki->k", points - origin, direction)[:, None] * direction



def slide_on_rays(z: np.ndarray, seen: np.ndarray, rays: np.ndarray, rows: np.ndarray, marker_seg: np.ndarray,
                  members: list[np.ndarray], offsets: list[np.ndarray], prior_weight: float) -> None:
    """Slide each single-camera marker ``rows`` of ``z`` (N, 3) along its ray to the point whose distances to the
    ``seen`` markers of its segment best match the segment's shape (``members``, ``offsets`` per segment,
    ``marker_seg`` per marker), held near its projected estimate with ``prior_weight`` (a few Gauss-Newton steps on
    the ray parameter). This is the line-circle (appendix D) and line-sphere (appendix E) solutions with the
    projected estimate of 5.3.5 as a prior, which picks the right intersection and steadies the near-tangent cases
    that made the thesis prefer the projection alone."""
    for i in rows:
        k = marker_seg[i]
        vis = seen[members[k]]
        if not vis.any():
            continue
        slot = int(np.flatnonzero(members[k] == i)[0])
        anchors = z[members[k][vis]]
        radii = np.linalg.norm(offsets[k][vis] - offsets[k][slot], axis=1)
        origin, direction = rays[i, :3], unit(rays[i, 3:])
        start = float((z[i] - origin) @ direction)
        ray_s = start
        for _ in range(5):
            diff = origin + ray_s * direction - anchors
            dist = np.maximum(np.linalg.norm(diff, axis=1), 1e-9)
            grad = diff @ direction / dist
            step = -((dist - radii) @ grad + prior_weight * (ray_s - start)) / (grad @ grad + prior_weight)
            ray_s += step
            if abs(step) < 1e-4:
                break
        z[i] = origin + ray_s * direction
