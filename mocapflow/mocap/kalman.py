"""A bank of constant-velocity Kalman filters, one per marker, advanced together (Aristidou 2008, 5.2 and A.2).

Every marker follows the same constant-velocity model (state: position and velocity). Process and measurement noise
are isotropic, so the three axes of a marker share one 2x2 covariance, and one predict or update is a handful of
batched numpy operations over all markers at once, so its cost stays flat as markers are added.
"""

from __future__ import annotations

import numpy as np
from filterpy.common import Q_discrete_white_noise, kinematic_kf


class ConstantVelocityBank:
    """``n`` independent constant-velocity filters sharing one model; a filter starts at its marker's first sight.

    The model matrices come from filterpy; the bank applies them written out on per-marker arrays (positions and
    velocities (N, 3), the three distinct covariance entries (N,)), which keeps a predict and an update at a dozen
    vectorised operations each.
    """

    def __init__(self, n: int, dt: float, accel_sd: float, initial_speed_sd: float) -> None:
        """``accel_sd`` (mm/s^2) is the white-noise acceleration driving the model; ``initial_speed_sd`` (mm/s) the
        spread of the unknown velocity when a marker is first seen."""
        model = kinematic_kf(dim=1, order=1, dt=dt)
        self.F = np.asarray(model.F, dtype=float)  # (2, 2): [[1, dt], [0, 1]]
        self.H = np.asarray(model.H, dtype=float)  # (1, 2): observes the position
        self.Q = np.asarray(Q_discrete_white_noise(dim=2, dt=dt, var=accel_sd**2), dtype=float)
        self.dt = float(self.F[0, 1])
        self.initial_speed_var = float(initial_speed_sd) ** 2
        self.pos = np.full((n, 3), np.nan)
        self.vel = np.full((n, 3), np.nan)
        self.p00, self.p01, self.p11 = np.zeros(n), np.zeros(n), np.zeros(n)  # covariance [[p00, p01], [p01, p11]]
        self.started = np.zeros(n, dtype=bool)
        self.all_started = n == 0  # every filter has started: no first sight left to check for

    def grow(self, extra: int) -> None:
        """Add ``extra`` filters, started at their markers' first sight like the others."""
        self.pos = np.vstack([self.pos, np.full((extra, 3), np.nan)])
        self.vel = np.vstack([self.vel, np.full((extra, 3), np.nan)])
        self.p00, self.p01, self.p11 = (np.append(p, np.zeros(extra)) for p in (self.p00, self.p01, self.p11))
        self.started = np.append(self.started, np.zeros(extra, dtype=bool))
        self.all_started = self.all_started and extra == 0

    @property
    def position(self) -> np.ndarray:
        """(N, 3) current position estimates; NaN for markers never seen."""
        return self.pos

    def predict(self, velocity_gain: np.ndarray | None = None) -> None:
        """Time update of every filter; ``velocity_gain`` (N,) scales velocities first (1 keeps the model as is):
        x <- F x, P <- F P F^T + Q."""
        dt, q = self.dt, self.Q
        if velocity_gain is not None:
            self.vel *= velocity_gain[:, None]
        self.pos += dt * self.vel
        self.p00 += 2 * dt * self.p01 + dt * dt * self.p11 + q[0, 0]
        self.p01 += dt * self.p11 + q[0, 1]
        self.p11 += q[1, 1]

    def predicted_position(self, velocity_gain: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) positions one step ahead as ``predict`` would make them, without changing the state."""
        velocity = self.vel if velocity_gain is None else self.vel * velocity_gain[:, None]
        return self.pos + self.dt * velocity

    def update(self, z: np.ndarray, variance: np.ndarray, rows: np.ndarray | None = None) -> None:
        """Measurement update with ``z`` (N, 3) for the markers selected by ``rows`` (N,) bool, by default those
        whose row holds no NaN. ``variance`` (N,): per-axis noise (mm^2).

        A marker seen for the first time starts at its measurement with an unknown velocity.
        """
        has = np.isfinite(z).all(axis=1) if rows is None else rows
        if not self.all_started:
            fresh = has & ~self.started
            if fresh.any():
                self.pos[fresh] = z[fresh]
                self.vel[fresh] = 0.0
                self.p00[fresh], self.p01[fresh], self.p11[fresh] = variance[fresh], 0.0, self.initial_speed_var
                self.started |= fresh
                self.all_started = bool(self.started.all())
                has = has & ~fresh
        p00, p01 = self.p00, self.p01
        s = p00 + variance  # H P H^T + R
        k0: np.ndarray = p00 / s  # gain K = P H^T / s
        k1: np.ndarray = p01 / s
        innovation: np.ndarray = z - self.pos
        if not has.all():  # the others keep their state
            k0 = np.where(has, k0, 0.0)
            k1 = np.where(has, k1, 0.0)
            innovation = np.where(has[:, None], innovation, 0.0)
        self.pos += k0[:, None] * innovation
        self.vel += k1[:, None] * innovation
        self.p11 -= k1 * p01  # P <- P - K H P
        self.p01 -= k0 * p01
        self.p00 -= k0 * p00
