"""A bank of constant-velocity Kalman filters, one per marker, advanced together (Aristidou 2008, 5.2 and A.2).

Every marker follows the same constant-velocity model (state: position and velocity). Process and measurement noise
are isotropic, so the three axes of a marker share one 2x2 covariance: the bank stores states as (N, 2, 3) and
covariances as (N, 2, 2), and one predict or update is a handful of batched numpy operations over all markers at
once, so its cost stays flat as markers are added.
"""

from __future__ import annotations

import numpy as np
from filterpy.common import Q_discrete_white_noise, kinematic_kf


class ConstantVelocityBank:
    """``n`` independent constant-velocity filters sharing one model; a filter starts at its marker's first sight."""

    def __init__(self, n: int, dt: float, accel_sd: float, initial_speed_sd: float) -> None:
        """``accel_sd`` (mm/s^2) is the white-noise acceleration driving the model; ``initial_speed_sd`` (mm/s) the
        spread of the unknown velocity when a marker is first seen."""
        model = kinematic_kf(dim=1, order=1, dt=dt)
        self.F = np.asarray(model.F, dtype=float)  # (2, 2): [[1, dt], [0, 1]]
        self.H = np.asarray(model.H, dtype=float)  # (1, 2): observes the position
        self.Q = np.asarray(Q_discrete_white_noise(dim=2, dt=dt, var=accel_sd**2), dtype=float)
        self.initial_speed_var = float(initial_speed_sd) ** 2
        self.x = np.full((n, 2, 3), np.nan)
        self.P = np.zeros((n, 2, 2))
        self.started = np.zeros(n, dtype=bool)

    @property
    def position(self) -> np.ndarray:
        """(N, 3) current position estimates; NaN for markers never seen."""
        return self.x[:, 0]

    def predict(self, velocity_gain: np.ndarray | None = None) -> None:
        """Time update of every filter; ``velocity_gain`` (N,) scales velocities first (1 keeps the model as is)."""
        if velocity_gain is not None:
            self.x[:, 1] *= velocity_gain[:, None]
        self.x = self.F @ self.x
        self.P = self.F @ self.P @ self.F.T + self.Q

    def predicted_position(self, velocity_gain: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) positions one step ahead as ``predict`` would make them, without changing the state."""
        velocity = self.x[:, 1] if velocity_gain is None else self.x[:, 1] * velocity_gain[:, None]
        return self.x[:, 0] + self.F[0, 1] * velocity

    def update(self, z: np.ndarray, variance: np.ndarray) -> None:
        """Measurement update with ``z`` (N, 3); rows holding NaN are skipped. ``variance`` (N,): per-axis noise (mm^2).

        A marker seen for the first time starts at its measurement with an unknown velocity.
        """
        has = np.isfinite(z).all(axis=1)
        fresh = has & ~self.started
        if fresh.any():
            self.x[fresh, 0] = z[fresh]
            self.x[fresh, 1] = 0.0
            self.P[fresh] = np.diag([0.0, self.initial_speed_var])
            self.P[fresh, 0, 0] = variance[fresh]
            self.started |= fresh
        live = has & ~fresh
        pht = self.P @ self.H[0]  # (N, 2): P H^T
        gain = pht / (pht[:, :1] + variance[:, None])  # (N, 2): P H^T (H P H^T + R)^-1
        gain[~live] = 0.0
        innovation = z - self.x[:, 0]  # (N, 3)
        innovation[~live] = 0.0
        self.x += gain[:, :, None] * innovation[:, None, :]
        self.P -= gain[:, :, None] * pht[:, None, :]
