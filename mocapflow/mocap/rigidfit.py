"""Rigid fits: the rotation and translation that best map one set of points onto another (Aristidou 2008, 4.3).

One module for every way the project fits a rigid body, all the same least-squares rotation as scipy's
``Rotation.align_vectors`` (Kabsch), found one way: the eigenvector of the largest eigenvalue of Horn's 4x4 quaternion
matrix (Aristidou 4.3, Horn 1987), by a compiled Jacobi iteration (a couple of microseconds, half the cost of an SVD
of the 3x3 cross-covariance through LAPACK):

- ``rotor``: for a batch of vector sets already relative to their centre of rotation; ``fit_pose`` builds on it: a
  segment's pose ``world = R @ local + t`` in every frame from whichever of its markers are visible, either free
  (centroid alignment) or pivoting about a known point such as the joint with its parent.
- ``kabsch`` / ``RigidFit``: weighted point sets aligned at their centroids, for a batch of point sets, ``RigidFit``
  keeping the local points and weights for a caller fitting the same sets to many frames.
- ``fit_one``: the same for a single point set (one frame's segment in the occlusion filler).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit


def rotor(reference: np.ndarray, observed: np.ndarray,
          weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rotations ``q`` with ``observed ≈ q.apply(reference)`` in the weighted least-squares sense, per frame.

    ``reference`` and ``observed`` are (..., n, 3) vectors, already relative to the rotation centre (the caller
    subtracts centroids or a pivot); NaN rows and zero ``weights`` are ignored. Returns scalar-last quaternions
    (..., 4) and the relative gap between the two largest eigenvalues of Horn's matrix N, in [0, 1]: near 0 the
    rotation is not determined (fewer than two non-parallel vectors, e.g. two markers about their common line).
    """
    x = np.asarray(reference, dtype=np.float64)
    y = np.asarray(observed, dtype=np.float64)
    w = np.ones(x.shape[:-1]) if weights is None else np.asarray(weights, dtype=np.float64)
    x, y, w = np.broadcast_arrays(x, y, w[..., None])
    lead, n = x.shape[:-2], x.shape[-2]
    quats, gap = _rotors(*(np.ascontiguousarray(a).reshape(-1, n, 3) for a in (x, y, w)))
    return quats.reshape(*lead, 4), gap.reshape(lead)


@njit(cache=True)
def _rotors(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """``rotor`` over a flat batch: (B, n, 3) points, (B, n, 3) weights (the same in the three columns)."""
    quats, gap = np.empty((len(x), 4)), np.empty(len(x))
    use = np.empty(x.shape[1])
    for b in range(len(x)):
        for i in range(x.shape[1]):
            use[i] = w[b, i, 0] if finite(x[b, i]) and finite(y[b, i]) else 0.0
        gap[b] = _horn(x[b], y[b], use, quats[b])
    return quats, gap


@njit(cache=True)
def det3(m: np.ndarray) -> float:  # pragma: no cover
    """The determinant of a 3x3 matrix."""
    return (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]) - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
            + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]))


@njit(cache=True)
def finite(v: np.ndarray) -> bool:  # pragma: no cover
    """Whether every coordinate of the short vector ``v`` is finite, without a temporary array."""
    for c in v:
        if not np.isfinite(c):
            return False
    return True


@njit(cache=True)
def _horn(x: np.ndarray, y: np.ndarray, w: np.ndarray, q: np.ndarray) -> float:  # pragma: no cover
    """Horn's rotation of one point set into ``q`` (scalar-last), from S = sum w x y^T (Schoenauer 3.7.4; rows of
    zero weight are not read). Returns the relative gap between the two largest eigenvalues of his matrix N (0 where
    N is 0)."""
    xx = xy = xz = yx = yy = yz = zx = zy = zz = 0.0
    for i in range(len(x)):
        if w[i] > 0:
            a0, a1, a2 = w[i] * x[i, 0], w[i] * x[i, 1], w[i] * x[i, 2]
            xx, xy, xz = xx + a0 * y[i, 0], xy + a0 * y[i, 1], xz + a0 * y[i, 2]
            yx, yy, yz = yx + a1 * y[i, 0], yy + a1 * y[i, 1], yz + a1 * y[i, 2]
            zx, zy, zz = zx + a2 * y[i, 0], zy + a2 * y[i, 1], zz + a2 * y[i, 2]
    values = np.empty(4)
    _quaternion(xx, xy, xz, yx, yy, yz, zx, zy, zz, q, values)
    return (values[0] - values[1]) / max(values[3], 1e-300)


CLOSED_FORM_GAP = 0.05
"""The relative gap between the two largest eigenvalues of Horn's matrix above which ``_quaternion`` takes its
closed form: there the eigenvector is found to about 1e-14 (its error grows as the gap shrinks); below it, the
Jacobi method, accurate at any gap."""


@njit(cache=True)
def _quaternion(xx: float, xy: float, xz: float, yx: float, yy: float, yz: float, zx: float, zy: float, zz: float,
                q: np.ndarray, values: np.ndarray) -> None:  # pragma: no cover
    """The eigenvector of the largest eigenvalue of Horn's symmetric 4x4 matrix N built from S (entries ``xx`` ..
    ``zz``), as a scalar-last quaternion into ``q`` (Horn's is (w, x, y, z)), its scalar part never negative; into
    ``values`` the three largest eigenvalues, in order, and the largest magnitude of any. The eigenvalues of N are
    sums of S's singular values with signs (Horn 1987): the largest is s1 + s2 + s3, the second s1 - s2 - s3, the
    third -s1 + s2 - s3 (s3 taken negative where det S is), so the first two give the first singular value, the first
    and third the second. Where the first two stand clear of each other (``CLOSED_FORM_GAP``), in closed form
    (``_closed_form``, a sixth of the time); else by the Jacobi method."""
    if _closed_form(xx, xy, xz, yx, yy, yz, zx, zy, zz, q, values):
        return
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33 = _horn_matrix(xx, xy, xz, yx, yy, yz, zx, zy, zz)
    n = np.empty((4, 4))  # filled entry by entry: a nested list would cost an allocation per row
    n[0, 0], n[0, 1], n[0, 2], n[0, 3] = a00, a01, a02, a03
    n[1, 0], n[1, 1], n[1, 2], n[1, 3] = a01, a11, a12, a13
    n[2, 0], n[2, 1], n[2, 2], n[2, 3] = a02, a12, a22, a23
    n[3, 0], n[3, 1], n[3, 2], n[3, 3] = a03, a13, a23, a33
    vectors = np.empty((4, 4))
    _jacobi(n, vectors)
    first, second = 0, 1
    if n[1, 1] > n[0, 0]:
        first, second = 1, 0
    for i in range(2, 4):
        if n[i, i] > n[first, first]:
            first, second = i, first
        elif n[i, i] > n[second, second]:
            second = i
    sign = 1.0 if vectors[0, first] >= 0 else -1.0
    q[0], q[1], q[2], q[3] = (sign * vectors[1, first], sign * vectors[2, first], sign * vectors[3, first],
                              sign * vectors[0, first])
    scale, third = 0.0, -np.inf
    for i in range(4):
        scale = max(scale, abs(n[i, i]))
        if i != first and i != second:
            third = max(third, n[i, i])
    values[0], values[1], values[2], values[3] = n[first, first], n[second, second], third, scale


@njit(cache=True)
def _closed_form(xx: float, xy: float, xz: float, yx: float, yy: float, yz: float, zx: float, zy: float, zz: float,
                 q: np.ndarray, values: np.ndarray) -> bool:  # pragma: no cover
    """``_quaternion`` without iterating, where the largest eigenvalue of N stands clear of the second; False (and
    nothing written) elsewhere. S's singular values come from the eigenvalues of S^T S (the trigonometric solution of
    a symmetric 3x3's cubic), the smallest as det S / (s1 s2), which keeps it exact when the points are flat; the
    largest eigenvalue of N, s1 + s2 + s3, is polished by Newton's method on N's characteristic polynomial,
    x^4 - 2 |S|^2 x^2 - 8 det S x + det N (Horn 1987), and the eigenvector is the best-scaled column of the adjugate
    of N minus it (a singular symmetric matrix of rank three: its adjugate is a multiple of v v^T)."""
    m00, m11, m22 = xx * xx + yx * yx + zx * zx, xy * xy + yy * yy + zy * zy, xz * xz + yz * yz + zz * zz
    m01, m02, m12 = xx * xy + yx * yy + zx * zy, xx * xz + yx * yz + zx * zz, xy * xz + yy * yz + zy * zz
    det = xx * (yy * zz - yz * zy) - xy * (yx * zz - yz * zx) + xz * (yx * zy - yy * zx)
    mean = (m00 + m11 + m22) / 3.0
    d0, d1, d2 = m00 - mean, m11 - mean, m22 - mean
    spread = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (m01 * m01 + m02 * m02 + m12 * m12)) / 6.0)
    if not spread > 0.0:  # S^T S a multiple of the identity, or not finite
        return False
    half_det = (d0 * (d1 * d2 - m12 * m12) - m01 * (m01 * d2 - m12 * m02) + m02 * (m01 * m12 - d1 * m02)) / (
        2.0 * spread * spread * spread)
    angle = np.arccos(min(max(half_det, -1.0), 1.0)) / 3.0
    e1 = mean + 2.0 * spread * np.cos(angle)
    e3 = mean + 2.0 * spread * np.cos(angle + 2.0 * np.pi / 3.0)
    s1, s2 = np.sqrt(max(e1, 0.0)), np.sqrt(max(3.0 * mean - e1 - e3, 0.0))
    if not s2 > 0.0:
        return False
    s3 = det / (s1 * s2)
    scale = s1 + s2 + abs(s3)
    if not 2.0 * (s2 + s3) >= CLOSED_FORM_GAP * scale:
        return False
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33 = _horn_matrix(xx, xy, xz, yx, yy, yz, zx, zy, zz)
    u0, u1, u2, u3, u4, u5, w0, w1, w2, w3, w4, w5 = _minors(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33)
    det_n = u0 * w5 - u1 * w4 + u2 * w3 + u3 * w2 - u4 * w1 + u5 * w0
    square = -2.0 * (m00 + m11 + m22)
    top = s1 + s2 + s3
    for _ in range(2):
        slope = 4.0 * top * top * top + 2.0 * square * top - 8.0 * det
        if slope == 0.0:
            break
        top -= ((top * top + square) * top * top - 8.0 * det * top + det_n) / slope
    a00, a11, a22, a33 = a00 - top, a11 - top, a22 - top, a33 - top
    u0, u1, u2, u3, u4, u5, w0, w1, w2, w3, w4, w5 = _minors(a00, a01, a02, a03, a11, a12, a13, a22, a23, a33)
    b00, b11 = a11 * w5 - a12 * w4 + a13 * w3, a00 * w5 - a02 * w2 + a03 * w1
    b22, b33 = a03 * u4 - a13 * u2 + a33 * u0, a02 * u3 - a12 * u1 + a22 * u0
    column, size = 0, abs(b00)  # the column of the adjugate whose diagonal entry is largest: the best scaled
    for k, b in enumerate((b11, b22, b33)):
        if abs(b) > size:
            column, size = k + 1, abs(b)
    if column == 0:
        v0, v1, v2, v3 = b00, -a01 * w5 + a02 * w4 - a03 * w3, a13 * u5 - a23 * u4 + a33 * u3, \
            -a12 * u5 + a22 * u4 - a23 * u3
    elif column == 1:
        v0, v1, v2, v3 = -a01 * w5 + a12 * w2 - a13 * w1, b11, -a03 * u5 + a23 * u2 - a33 * u1, \
            a02 * u5 - a22 * u2 + a23 * u1
    elif column == 2:
        v0, v1, v2, v3 = a01 * w4 - a11 * w2 + a13 * w0, -a00 * w4 + a01 * w2 - a03 * w0, b22, \
            -a02 * u4 + a12 * u2 - a23 * u0
    else:
        v0, v1, v2, v3 = -a01 * w3 + a11 * w1 - a12 * w0, a00 * w3 - a01 * w1 + a02 * w0, \
            -a03 * u3 + a13 * u1 - a23 * u0, b33
    norm = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2 + v3 * v3)
    if not norm > 0.0:
        return False
    if v0 < 0:
        norm = -norm
    q[0], q[1], q[2], q[3] = v1 / norm, v2 / norm, v3 / norm, v0 / norm
    values[0], values[1], values[2], values[3] = top, s1 - s2 - s3, -s1 + s2 - s3, scale
    return True


@njit(cache=True)
def _horn_matrix(xx: float, xy: float, xz: float, yx: float, yy: float, yz: float, zx: float, zy: float,
                 zz: float) -> tuple[float, ...]:  # pragma: no cover
    """Horn's symmetric 4x4 matrix N of the cross-covariance S (entries ``xx`` .. ``zz``), its upper triangle row by
    row: N00 N01 N02 N03 N11 N12 N13 N22 N23 N33."""
    return (xx + yy + zz, yz - zy, zx - xz, xy - yx, xx - yy - zz, xy + yx, zx + xz, -xx + yy - zz, yz + zy,
            -xx - yy + zz)


@njit(cache=True)
def _minors(a00: float, a01: float, a02: float, a03: float, a11: float, a12: float, a13: float, a22: float, a23: float,
            a33: float) -> tuple[float, ...]:  # pragma: no cover
    """The 2x2 minors of a symmetric 4x4 matrix (upper triangle given) on its rows 0-1 and on its rows 2-3, each by
    column pairs (0,1) (0,2) (0,3) (1,2) (1,3) (2,3): what its determinant and its adjugate are made of."""
    return (a00 * a11 - a01 * a01, a00 * a12 - a01 * a02, a00 * a13 - a01 * a03, a01 * a12 - a11 * a02,
            a01 * a13 - a11 * a03, a02 * a13 - a12 * a03,
            a02 * a13 - a03 * a12, a02 * a23 - a03 * a22, a02 * a33 - a03 * a23, a12 * a23 - a13 * a22,
            a12 * a33 - a13 * a23, a22 * a33 - a23 * a23)


@njit(cache=True)
def _jacobi(a: np.ndarray, v: np.ndarray) -> None:  # pragma: no cover
    """In place, the cyclic Jacobi method on a symmetric 4x4 ``a``: its diagonal becomes the eigenvalues and ``v``'s
    columns their unit eigenvectors (accurate to rounding, and a few hundred operations: no LAPACK call). Each
    rotation updates only the entries it changes, keeping ``a`` symmetric."""
    v[:] = 0.0
    scale = 0.0
    for i in range(4):
        v[i, i] = 1.0
        for j in range(4):
            scale = max(scale, abs(a[i, j]))
    for _ in range(32):
        off = 0.0
        for p in range(3):
            for q in range(p + 1, 4):
                off += a[p, q] * a[p, q]
        if off <= (1e-17 * scale) ** 2:
            return
        for p in range(3):
            for q in range(p + 1, 4):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                a[p, p] -= t * apq
                a[q, q] += t * apq
                a[p, q] = a[q, p] = 0.0
                for r in range(4):
                    if r != p and r != q:
                        arp, arq = a[r, p], a[r, q]
                        a[r, p] = a[p, r] = c * arp - s * arq
                        a[r, q] = a[q, r] = s * arp + c * arq
                for k in range(4):
                    kp, kq = v[k, p], v[k, q]
                    v[k, p], v[k, q] = c * kp - s * kq, s * kp + c * kq


def kabsch(local: np.ndarray, world: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares rigid transforms ``world ~ R @ local + t`` for a batch of point sets.

    ``local``/``world`` (B, M, 3), ``weight`` (B, M) with zero for absent points (whose coordinates are not read).
    Each set's rotation is Horn's, from its 3x3 cross-covariance, in compiled code: this runs every frame of the
    occlusion filler. Returns R (B, 3, 3), t (B, 3) and ``ok`` (B,): False where the points do not fix a rotation
    (fewer than three, or collinear).
    """
    return RigidFit(local, weight)(world)


class RigidFit:
    """``kabsch`` with its local points and weights fixed: what depends on them alone is worked out once, for a
    caller fitting the same point sets to many frames."""

    def __init__(self, local: np.ndarray, weight: np.ndarray) -> None:
        self.weight = np.ascontiguousarray(weight / np.maximum(weight.sum(axis=1), 1e-300)[:, None], dtype=np.float64)
        # writable too: a read-only view (a layout broadcast over a batch of one) would be compiled for anew
        self.local = np.require(local, np.float64, ["C", "W"])
        self.enough = (weight > 0).sum(axis=1) >= 3

    def __call__(self, world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """R, t and ``ok`` of ``kabsch`` for the world points (B, M, 3)."""
        r, t, ok = _kabsch_batch(self.local, np.ascontiguousarray(world, dtype=np.float64), self.weight)
        return r, t, self.enough & ok

    def into(self, positions: np.ndarray, rows: np.ndarray, where: np.ndarray, r: np.ndarray, t: np.ndarray,
             ok: np.ndarray) -> None:
        """``__call__`` for the world points ``positions[rows]`` (rows (B, M) of (N, 3)), written into the rows
        ``where`` (B,) of ``r``, ``t`` and ``ok``, in one compiled pass."""
        _kabsch_rows(self.local, np.ascontiguousarray(positions, dtype=np.float64), rows, self.weight, self.enough,
                     where, r, t, ok)


def fit_one(local: np.ndarray, world: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``kabsch`` for a single point set (M, 3), compiled; None where the points do not fix a rotation."""
    w = np.asarray(weight, dtype=np.float64)
    r, t = np.empty((3, 3)), np.empty(3)
    if not kabsch_into(np.asarray(local, dtype=np.float64), np.asarray(world, dtype=np.float64), w / w.sum(), r, t):
        return None
    return r, t


@njit(cache=True)
def _kabsch_batch(local: np.ndarray, world: np.ndarray, weight: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """``kabsch`` of each point set of a batch, normalised ``weight`` (B, M)."""
    r, t, ok = np.empty((len(local), 3, 3)), np.empty((len(local), 3)), np.empty(len(local), np.bool_)
    for b in range(len(local)):
        ok[b] = kabsch_into(local[b], world[b], weight[b], r[b], t[b])
    return r, t, ok


@njit(cache=True)
def _kabsch_rows(local: np.ndarray, positions: np.ndarray, rows: np.ndarray, weight: np.ndarray, enough: np.ndarray,
                 where: np.ndarray, r: np.ndarray, t: np.ndarray, ok: np.ndarray) -> None:  # pragma: no cover
    """``RigidFit.into``: ``kabsch`` of each point set ``positions[rows[b]]``, normalised ``weight`` (B, M), into
    ``r``, ``t`` and ``ok`` at ``where[b]``."""
    world = np.empty((rows.shape[1], 3))
    for b in range(len(rows)):
        for m in range(rows.shape[1]):
            world[m] = positions[rows[b, m]]
        ok[where[b]] = kabsch_into(local[b], world, weight[b], r[where[b]], t[where[b]]) and enough[b]


@njit(cache=True)
def kabsch_into(local: np.ndarray, world: np.ndarray, w: np.ndarray, r: np.ndarray,
                t: np.ndarray) -> bool:  # pragma: no cover
    """The least-squares ``world ~ r @ local + t`` for points (M, 3) with normalised weights ``w`` (zero for points
    to leave out, whose coordinates may be anything, NaN too), into ``r`` and ``t``: Horn's rotation of the
    cross-covariance (``_quaternion``); False where the points do not fix a rotation (the cross-covariance's second
    singular value below 1e-6 of its first)."""
    cl, cw = np.zeros(3), np.zeros(3)
    for m in range(len(w)):
        if w[m] == 0.0:
            continue
        for c in range(3):
            cl[c] += w[m] * local[m, c]
            cw[c] += w[m] * world[m, c]
    h = np.zeros((3, 3))
    for m in range(len(w)):
        if w[m] == 0.0:
            continue
        for a in range(3):
            for b in range(3):
                h[a, b] += (local[m, a] - cl[a]) * ((world[m, b] - cw[b]) * w[m])
    if not np.isfinite(h).all():
        r[:], t[:] = np.nan, np.nan
        return False
    q, values = np.empty(4), np.empty(4)
    _quaternion(h[0, 0], h[0, 1], h[0, 2], h[1, 0], h[1, 1], h[1, 2], h[2, 0], h[2, 1], h[2, 2], q, values)
    if not _matrix(q, r):
        r[:], t[:] = np.nan, np.nan
        return False
    for a in range(3):
        t[a] = cw[a] - (r[a, 0] * cl[0] + r[a, 1] * cl[1] + r[a, 2] * cl[2])
    return values[0] + values[2] > 1e-6 * (values[0] + values[1])


@dataclass
class PoseFit:
    """Per-frame poses of one segment: ``world = R @ local + t``; NaN where too few markers were visible."""

    rotations: np.ndarray  # (F, 4) scalar-last quaternions
    translations: np.ndarray  # (F, 3) mm
    determined: np.ndarray  # (F,) bool: the data fixed all three rotation angles
    rotation_matrices: np.ndarray  # (F, 3, 3) the rotations as matrices, NaN where the pose is unknown
    local: np.ndarray  # (n, 3) the markers in the segment frame
    observed: np.ndarray  # (F, n, 3) the markers fitted, NaN where unseen

    @cached_property
    def residual(self) -> np.ndarray:
        """(F,) RMS distance between fitted and observed markers, mm; NaN where the pose is unknown. Worked out on
        first use: a caller that only poses (the skeleton, frame after frame) does not pay for it."""
        fitted = np.einsum("f...ab,...nb->f...na", self.rotation_matrices, self.local) + self.translations[..., None, :]
        seen = np.isfinite(self.observed).all(-1)
        err = np.where(seen, ((fitted - self.observed) ** 2).sum(-1), 0.0).sum(-1)
        known = np.isfinite(self.rotations).all(-1)
        return np.where(known, np.sqrt(err / np.maximum(seen.sum(-1), 1)), np.nan)

    def subset(self, frames: np.ndarray) -> PoseFit:
        """The poses of some frames only."""
        return PoseFit(self.rotations[frames], self.translations[frames], self.determined[frames],
                       self.rotation_matrices[frames], self.local, self.observed[frames])


def quaternion_matrices(quaternions: np.ndarray) -> np.ndarray:
    """(..., 3, 3) matrices of scalar-last quaternions, NaN rows giving NaN matrices (scipy rejects NaN).

    The arithmetic of scipy's ``Rotation.from_quat(q).as_matrix()`` (normalise, then the products of ``_matrix``),
    operation for operation, so the matrices are bit for bit scipy's, without building a ``Rotation`` on every
    call."""
    q = np.ascontiguousarray(quaternions, dtype=np.float64)
    out = np.empty((*q.shape[:-1], 3, 3))
    if not _matrices(q.reshape(-1, 4), out.reshape(-1, 3, 3)):
        raise ValueError("Found zero norm quaternions in `quat`.")
    return out


@njit(cache=True)
def _matrices(q: np.ndarray, out: np.ndarray) -> bool:  # pragma: no cover
    """``quaternion_matrices`` of (B, 4) into (B, 3, 3); False if a quaternion is zero."""
    for b in range(len(q)):
        if not _matrix(q[b], out[b]):
            return False
    return True


@njit(cache=True)
def _matrix(q: np.ndarray, out: np.ndarray) -> bool:  # pragma: no cover
    """The rotation matrix of one scalar-last quaternion into ``out``, scipy's arithmetic; False if it is zero."""
    norm = np.sqrt(((q[0] * q[0] + q[1] * q[1]) + q[2] * q[2]) + q[3] * q[3])
    if norm == 0:
        return False
    x, y, z, w = q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm
    xx, yy, zz, ww = x * x, y * y, z * z, w * w
    out[0, 0], out[1, 1], out[2, 2] = ((xx - yy) - zz) + ww, ((-xx + yy) - zz) + ww, ((-xx - yy) + zz) + ww
    out[0, 1], out[0, 2] = 2 * (x * y - z * w), 2 * (x * z + y * w)
    out[1, 0], out[1, 2] = 2 * (x * y + z * w), 2 * (y * z - x * w)
    out[2, 0], out[2, 1] = 2 * (x * z - y * w), 2 * (y * z + x * w)
    return True


MIN_GAP = 1e-3
"""Below this eigenvalue gap (``rotor``) a fit's points fix one direction only: its rotation is not determined."""


def fit_pose(local: np.ndarray, observed: np.ndarray, pivot_local: np.ndarray | None = None,
             pivot_world: np.ndarray | None = None, *, hold: bool = False, min_gap: float = MIN_GAP) -> PoseFit:
    """Pose of a rigid marker set in every frame, from the visible markers only.

    ``local`` (n, 3) are the markers in the segment frame, ``observed`` (F, n, 3) their positions with NaN gaps.
    Free fit (Horn): align the centroids of the markers visible in that frame, so a missing marker moves neither
    centroid. With a pivot (``pivot_local`` (3,), ``pivot_world`` (F, 3)), the segment only rotates about that point,
    which stays exactly where it is (Schoenauer 3.8.2): one marker and the pivot then give a pose, and frames whose
    pivot is NaN fall back to the free fit. Frames whose rotation the points do not fix (eigenvalue gap below
    ``min_gap``: one direction only) are flagged in ``determined``; with ``hold`` their rotation becomes the smallest
    turn of the previous frame's (before a first determined frame: the next one's) that matches the visible
    direction, so a segment seen through two points keeps turning plausibly instead of spinning about them.

    Several segments are fitted in one call by giving them a batch axis after the frames: ``local`` (S, n, 3),
    ``observed`` (F, S, n, 3), pivots (S, 3) and (F, S, 3), each segment's markers padded to a common n with rows
    that are never seen (any finite ``local``, NaN ``observed``); every result then has that axis too, and each
    segment's numbers are exactly those of fitting it alone.

    The arithmetic is compiled (numba), frame by frame and segment by segment: one call costs microseconds, where the
    same steps as numpy operations on a frame or two (the live skeleton) cost far more in per-call overhead than in
    arithmetic.
    """
    local = np.asarray(local, dtype=np.float64)
    obs = np.asarray(observed, dtype=np.float64)
    single = local.ndim == 2
    segments = local.reshape(-1, *local.shape[-2:])
    frames = np.ascontiguousarray(obs.reshape(obs.shape[0], len(segments), *local.shape[-2:]))
    pin_local = np.zeros((len(segments), 3))
    pin_world = np.full((len(frames), len(segments), 3), np.nan)
    if pivot_local is not None and pivot_world is not None:
        pin_local[:] = np.asarray(pivot_local, dtype=np.float64).reshape(-1, 3)
        pin_world[:] = np.asarray(pivot_world, dtype=np.float64).reshape(len(frames), -1, 3)
    quats, determined, origin_loc, origin_obs = fit_frames(np.ascontiguousarray(segments), frames, pin_local,
                                                            pin_world, min_gap)
    if hold:  # only segments with a frame to hold and one to hold it from, in the world
        todo = (np.isfinite(quats).all(-1) & ~determined).any(0) & determined.any(0)
        world = np.tile([0.0, 0.0, 0.0, 1.0], (len(frames), 1))
        for s in np.flatnonzero(todo):
            hold_turns(quats[:, s], determined[:, s], segments[s], frames[:, s], origin_loc[:, s], origin_obs[:, s],
                       world, np.full(4, np.nan), 0)
    matrices, translations = pose_matrices(quats, origin_loc, origin_obs)
    if single:
        quats, determined, matrices, translations = quats[:, 0], determined[:, 0], matrices[:, 0], translations[:, 0]
    return PoseFit(quats, translations, determined, matrices, local, obs)


@njit(cache=True)
def fit_frames(local: np.ndarray, observed: np.ndarray, pivot_local: np.ndarray, pivot_world: np.ndarray,
               min_gap: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """``fit_pose`` before holding: per frame and segment ((F, S) of ``observed`` (F, S, n, 3)), the quaternion
    (NaN where too few points), whether the points fix it, and the two origins it turns about (centroids of the
    visible markers, or the pivot where ``pivot_world`` is finite): ``fit_frame`` of each."""
    count_f, count_s, n = observed.shape[0], observed.shape[1], observed.shape[2]
    quats = np.empty((count_f, count_s, 4))
    determined = np.empty((count_f, count_s), np.bool_)
    origin_loc, origin_obs = np.empty((count_f, count_s, 3)), np.empty((count_f, count_s, 3))
    seen, x, y = np.empty(n), np.empty((n, 3)), np.empty((n, 3))
    for f in range(count_f):
        for s in range(count_s):
            determined[f, s] = fit_frame(local[s], observed[f, s], pivot_local[s], pivot_world[f, s], min_gap, seen, x,
                                         y, quats[f, s], origin_loc[f, s], origin_obs[f, s])
    return quats, determined, origin_loc, origin_obs


@njit(cache=True)
def fit_frame(local: np.ndarray, observed: np.ndarray, pivot_local: np.ndarray, pivot_world: np.ndarray,
              min_gap: float, seen: np.ndarray, x: np.ndarray, y: np.ndarray, quat: np.ndarray, origin_loc: np.ndarray,
              origin_obs: np.ndarray) -> bool:  # pragma: no cover
    """``fit_frames`` of one frame of one segment, (n, 3) points, into ``quat`` (NaN where too few points),
    ``origin_loc`` and ``origin_obs`` (zero where no point at all); whether the points fix the rotation. ``seen``
    (n,), ``x`` and ``y`` (n, 3) are scratch space: a caller fitting frame after frame allocates them once."""
    n = len(local)
    count = 0
    for i in range(n):
        seen[i] = 1.0 if finite(observed[i]) else 0.0
        count += int(seen[i])
    pinned = finite(pivot_world)
    for c in range(3):
        origin_loc[c], origin_obs[c] = 0.0, 0.0
        if pinned:
            origin_loc[c], origin_obs[c] = pivot_local[c], pivot_world[c]
        elif count:
            for i in range(n):
                if seen[i]:
                    origin_loc[c] += local[i, c] / count
                    origin_obs[c] += observed[i, c] / count
    quat[:] = np.nan
    if count < (1 if pinned else 2):
        return False
    for i in range(n):
        for c in range(3):
            x[i, c] = local[i, c] - origin_loc[c]
            y[i, c] = observed[i, c] - origin_obs[c]
    return _horn(x, y, seen, quat) >= min_gap


@njit(cache=True)
def pose_matrices(quats: np.ndarray, origin_loc: np.ndarray, origin_obs: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Rotation matrices and translations (``world = R @ local + t`` maps ``origin_loc`` onto ``origin_obs``) of
    (F, S) poses; NaN where the quaternion is: ``pose_matrix`` of each."""
    count_f, count_s = quats.shape[0], quats.shape[1]
    matrices = np.empty((count_f, count_s, 3, 3))
    translations = np.empty((count_f, count_s, 3))
    for f in range(count_f):
        for s in range(count_s):
            pose_matrix(quats[f, s], origin_loc[f, s], origin_obs[f, s], matrices[f, s], translations[f, s])
    return matrices, translations


@njit(cache=True)
def pose_matrix(quat: np.ndarray, origin_loc: np.ndarray, origin_obs: np.ndarray, matrix: np.ndarray,
                translation: np.ndarray) -> None:  # pragma: no cover
    """``pose_matrices`` of one pose, into ``matrix`` and ``translation`` (NaN where the quaternion is)."""
    if finite(quat) and _matrix(quat, matrix):
        for a in range(3):
            translation[a] = (-matrix[a, 0] * origin_loc[0] - matrix[a, 1] * origin_loc[1]
                              - matrix[a, 2] * origin_loc[2] + origin_obs[a])
    else:
        matrix[:], translation[:] = np.nan, np.nan


@njit(cache=True)
def place(matrix: np.ndarray, point: np.ndarray, shift: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``out = matrix @ point + shift`` for a 3x3 matrix, in scalar arithmetic (a matrix product on arrays this small
    costs a library call)."""
    for a in range(3):
        out[a] = matrix[a, 0] * point[0] + matrix[a, 1] * point[1] + matrix[a, 2] * point[2] + shift[a]


@njit(cache=True)
def hold_turns(quats: np.ndarray, determined: np.ndarray, local: np.ndarray, observed: np.ndarray,
               origin_loc: np.ndarray, origin_obs: np.ndarray, reference: np.ndarray, before: np.ndarray,
               before_at: int) -> None:  # pragma: no cover
    """In place, for one segment's (F,) frames: undetermined frames take the smallest turn that points their longest
    visible vector (from the origin) at the data, from the rotation interpolated (slerp) between the nearest
    determined frames before and after (or the nearest one, at an end), each taken relative to ``reference`` (F, 4)
    in its frame: the identity holds the rotation in the world, a parent segment's rotation holds the turn from the
    parent, which then carries the segment through the gap. With no determined frame at all, the rotation held is
    ``reference`` itself. ``before`` is the segment's rotation relative to its reference (``relative_turn``) in the
    last determined frame before these (NaN for none) and ``before_at`` that frame's index (negative), so that
    frames fitted in successive calls hold as one call over them all would."""
    known = np.flatnonzero(determined)
    earlier = finite(before)
    prior, turned, matrix = np.empty(4), np.empty(4), np.empty((3, 3))
    held, rel_a, rel_b = np.empty(4), np.empty(4), np.empty(4)
    pointing = np.empty(3)
    for f in range(len(quats)):
        if determined[f] or not finite(quats[f]):
            continue
        k = int(np.searchsorted(known, f))
        if 0 < k < len(known):
            a, b = known[k - 1], known[k]
            relative_turn(reference[a], quats[a], rel_a)
            relative_turn(reference[b], quats[b], rel_b)
            _slerp(rel_a, rel_b, (f - a) / (b - a), held)
        elif k == 0 and earlier and len(known):
            relative_turn(reference[known[0]], quats[known[0]], rel_b)
            _slerp(before, rel_b, (f - before_at) / (known[0] - before_at), held)
        elif k == 0 and earlier:
            held[:] = before
        elif len(known):
            edge = known[min(k, len(known) - 1)]
            relative_turn(reference[edge], quats[edge], held)
        else:
            held[:3], held[3] = 0.0, 1.0
        _multiply(reference[f], held, prior)
        longest, u = -1.0, np.zeros(3)
        w = np.zeros(3)
        for i in range(len(local)):
            if finite(observed[f, i]):
                v = local[i] - origin_loc[f]
                if np.sqrt((v * v).sum()) > longest:
                    longest, u, w = np.sqrt((v * v).sum()), v, observed[f, i] - origin_obs[f]
        _matrix(prior, matrix)
        place(matrix, u, np.zeros(3), pointing)
        _shortest_turn(pointing, w, turned)
        _multiply(turned, prior, quats[f])


@njit(cache=True)
def relative_turn(reference: np.ndarray, quat: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """The rotation ``quat`` relative to ``reference`` (both scalar-last quaternions), ``reference^-1 * quat``, into
    ``out``."""
    _multiply(np.array([-reference[0], -reference[1], -reference[2], reference[3]]), quat, out)


@njit(cache=True)
def _multiply(p: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """The product ``p * q`` of scalar-last quaternions (``q`` applied first) into ``out``."""
    px, py, pz, pw = p[0], p[1], p[2], p[3]
    qx, qy, qz, qw = q[0], q[1], q[2], q[3]
    out[0] = pw * qx + px * qw + py * qz - pz * qy
    out[1] = pw * qy - px * qz + py * qw + pz * qx
    out[2] = pw * qz + px * qy - py * qx + pz * qw
    out[3] = pw * qw - px * qx - py * qy - pz * qz


@njit(cache=True)
def _turn(axis: np.ndarray, angle: float, out: np.ndarray) -> None:  # pragma: no cover
    """The quaternion of a turn by ``angle`` about the unit ``axis``, into ``out``."""
    out[:3] = axis * np.sin(angle / 2)
    out[3] = np.cos(angle / 2)


@njit(cache=True)
def _slerp(a: np.ndarray, b: np.ndarray, t: float, out: np.ndarray) -> None:  # pragma: no cover
    """The rotation a fraction ``t`` of the shortest way from ``a`` to ``b``, into ``out``."""
    relative = np.empty(4)
    relative_turn(a, b, relative)
    if relative[3] < 0:
        relative = -relative
    sine = np.sqrt((relative[:3] ** 2).sum())
    part = np.array([0.0, 0.0, 0.0, 1.0])
    if sine > 0:
        _turn(relative[:3] / sine, t * 2 * np.arctan2(sine, relative[3]), part)
    _multiply(a, part, out)


@njit(cache=True)
def _shortest_turn(u: np.ndarray, w: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """The smallest rotation pointing direction ``u`` along ``w``, into ``out`` (a half turn about an axis square
    to ``u`` where they are opposite)."""
    axis = _cross(u, w)
    sine, cosine = np.sqrt((axis * axis).sum()), (u * w).sum()
    if sine == 0 and cosine >= 0:
        out[:3], out[3] = 0.0, 1.0
        return
    if sine == 0:  # opposite: about the axis square to u and to the coordinate axis it is least along
        least = np.zeros(3)
        least[0 if abs(u[0]) <= min(abs(u[1]), abs(u[2])) else 1 if abs(u[1]) <= abs(u[2]) else 2] = 1.0
        axis = _cross(u, least)
        sine = np.sqrt((axis * axis).sum())
    _turn(axis / sine, np.arctan2(sine, cosine), out)


@njit(cache=True)
def _cross(u: np.ndarray, w: np.ndarray) -> np.ndarray:  # pragma: no cover
    """The cross product of two 3-vectors."""
    return np.array([u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]])
