"""A bank of constant-velocity Kalman filters, one per marker, advanced together (Aristidou 2008, 5.2 and A.2).

Every marker follows the same constant-velocity model (state: position and velocity). Process and measurement noise
are isotropic, so the three axes of a marker share one 2x2 covariance; one predict or update is one compiled pass
over all markers (numba), a few microseconds for 50 markers.
"""

from __future__ import annotations

import numpy as np
from numba import njit


class ConstantVelocityBank:
    """``n`` independent constant-velocity filters sharing one model; a filter starts at its marker's first sight.

    The model matrices come from filterpy; the bank applies them written out on per-marker arrays (positions and
    velocities (N, 3), the three distinct covariance entries (N,)), in one compiled loop each.
    """

    def __init__(self, n: int, dt: float, accel_sd: float, initial_speed_sd: float) -> None:
        """``accel_sd`` (mm/s^2) is the white-noise acceleration driving the model; ``initial_speed_sd`` (mm/s) the
        spread of the unknown velocity when a marker is first seen."""
        # imported here: filterpy's package loads all of its filters and scipy.stats with them (0.8 s of a process's
        # start), which only a process that builds a filter should pay
        from filterpy.common import Q_discrete_white_noise, kinematic_kf

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
        self._steady = np.ones(n)  # the velocity gain that keeps the model as is
        self.all_started = n == 0  # every filter has started: no first sight left to check for

    def grow(self, extra: int) -> None:
        """Add ``extra`` filters, started at their markers' first sight like the others."""
        self.pos = np.vstack([self.pos, np.full((extra, 3), np.nan)])
        self.vel = np.vstack([self.vel, np.full((extra, 3), np.nan)])
        self.p00, self.p01, self.p11 = (np.append(p, np.zeros(extra)) for p in (self.p00, self.p01, self.p11))
        self.started = np.append(self.started, np.zeros(extra, dtype=bool))
        self._steady = np.ones(len(self.pos))
        self.all_started = self.all_started and extra == 0

    @property
    def position(self) -> np.ndarray:
        """(N, 3) current position estimates; NaN for markers never seen."""
        return self.pos

    def predict(self, velocity_gain: np.ndarray | None = None) -> None:
        """Time update of every filter; ``velocity_gain`` (N,) scales velocities first (1 keeps the model as is):
        x <- F x, P <- F P F^T + Q."""
        _predict(self.pos, self.vel, self.p00, self.p01, self.p11, self.dt, self.Q, self._gains(velocity_gain))

    def predicted_position(self, velocity_gain: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) positions one step ahead as ``predict`` would make them, without changing the state."""
        ahead = np.empty_like(self.pos)
        _ahead(self.pos, self.vel, self.dt, self._gains(velocity_gain), ahead)
        return ahead

    def _gains(self, velocity_gain: np.ndarray | None) -> np.ndarray:
        """The per-marker velocity factors of a prediction, as the compiled passes take them."""
        return self._steady if velocity_gain is None else np.asarray(velocity_gain, dtype=np.float64)

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
        _update(self.pos, self.vel, self.p00, self.p01, self.p11, np.asarray(z, dtype=np.float64),
                np.asarray(variance, dtype=np.float64), has)


@njit(cache=True)
def _predict(pos: np.ndarray, vel: np.ndarray, p00: np.ndarray, p01: np.ndarray, p11: np.ndarray, dt: float,
             q: np.ndarray, gain: np.ndarray) -> None:  # pragma: no cover
    """``ConstantVelocityBank.predict`` in place, marker by marker."""
    for i in range(len(pos)):
        for c in range(3):
            vel[i, c] *= gain[i]
            pos[i, c] += dt * vel[i, c]
        p00[i] += 2 * dt * p01[i] + dt * dt * p11[i] + q[0, 0]
        p01[i] += dt * p11[i] + q[0, 1]
        p11[i] += q[1, 1]


@njit(cache=True)
def _ahead(pos: np.ndarray, vel: np.ndarray, dt: float, gain: np.ndarray,
           ahead: np.ndarray) -> None:  # pragma: no cover
    """``ConstantVelocityBank.predicted_position`` into ``ahead``, marker by marker, as ``_predict`` moves them."""
    for i in range(len(pos)):
        for c in range(3):
            ahead[i, c] = pos[i, c] + dt * (vel[i, c] * gain[i])


@njit(cache=True)
def _update(pos: np.ndarray, vel: np.ndarray, p00: np.ndarray, p01: np.ndarray, p11: np.ndarray, z: np.ndarray,
            variance: np.ndarray, has: np.ndarray) -> None:  # pragma: no cover
    """``ConstantVelocityBank.update`` in place for the rows ``has`` selects (filters already started)."""
    for i in range(len(pos)):
        if not has[i]:
            continue
        s = p00[i] + variance[i]  # H P H^T + R
        k0 = p00[i] / s  # gain K = P H^T / s
        k1 = p01[i] / s
        for c in range(3):
            innovation = z[i, c] - pos[i, c]
            pos[i, c] += k0 * innovation
            vel[i, c] += k1 * innovation
        p11[i] -= k1 * p01[i]  # P <- P - K H P
        p01[i] -= k0 * p01[i]
        p00[i] -= k0 * p00[i]
