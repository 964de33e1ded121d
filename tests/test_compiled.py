"""The compiled kernels are made ready before a live stage's first frame: after its nodes' ``kernels`` are loaded
(each stage in a process of its own, as a node's is), labelling, filling, posing and calibrating a capture compiles
nothing and loads nothing more from numba's cache. The kalman bank and the rigid fits give what their written-out
arithmetic gives.

Run as a script (``python test_compiled.py STAGE``), this module is that fresh process: it loads the stage's kernels,
does the stage's work and names the kernels loaded late."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import numpy as np
import pytest
from numba.core.registry import CPUDispatcher

import mocapflow.mocap
from mocapflow.mocap.calibration import build_skeleton
from mocapflow.mocap.filling import FillerConfig, GapFiller
from mocapflow.mocap.kalman import ConstantVelocityBank
from mocapflow.mocap.labelling import Labeller, LabellerConfig
from mocapflow.mocap.labelling.model import TrackedModelLabeller
from mocapflow.mocap.reacquire import Reacquirer
from mocapflow.mocap.rigidfit import fit_one, kabsch
from mocapflow.mocap.rigs import make_rig
from mocapflow.mocap.simulator import SimulatorConfig, simulate, truth_skeleton
from mocapflow.mocap.solve import PoseSolver
from mocapflow.runtime import plugins

STAGES = {"labelling": ["labeller"], "filling": ["occlusion-filler"], "fits": ["skeleton", "joints-closed-form"],
          "skeleton-labelling": ["labeller-skeleton"]}
"""Each stage's work and the plugins that do it: their nodes' ``kernels`` are loaded first (``compile_all`` loads
every stage's)."""


def _kernels() -> list[CPUDispatcher]:
    found = []
    for info in pkgutil.walk_packages(mocapflow.mocap.__path__, "mocapflow.mocap."):
        module = importlib.import_module(info.name)
        found += [obj for obj in vars(module).values()
                  if isinstance(obj, CPUDispatcher) and obj.__module__ == module.__name__]
    return found


def _stage(stage: str) -> list[str]:
    """Load ``stage``'s kernels as its node does, then do its work over a simulated capture (the labeller on a cloud
    with ghosts, and its markers found again after a blackout; the filler given a skeleton and learning one; the pose
    solve and the joint estimator's calibration; the skeleton labeller on the cloud); the kernels compiled or loaded
    during that work."""
    for plugin in STAGES[stage]:
        for load in plugins.load(plugin).kernels:
            load()
    kernels = _kernels()
    assert len(kernels) >= 20
    ready = {kernel: set(kernel.overloads) for kernel in kernels}
    config = SimulatorConfig(rig="human", rate=240, noise_mm=0.5, dropout_rate=0.5, long_gaps=4.0, seed=4)
    labelled = simulate(config, 720)
    skeleton = truth_skeleton(make_rig("human"), labelled.true_positions[0])
    if stage in ("labelling", "skeleton-labelling"):
        cloud = simulate(config.model_copy(update={"unlabelled": True, "ghosts": 1.0}), 720)
        assert cloud.points is not None
        if stage == "labelling":
            labeller = Labeller(LabellerConfig(), cloud.rate)
            for f in range(600):
                labeller.update(cloud.points[f], f / cloud.rate)
            assert len(labeller.labels) >= len(labelled.labels)
            reacquire = Reacquirer(labeller)  # a blackout: the markers found again by their layouts
            for f in range(660, 720):
                reacquire(cloud.points[f], f / cloud.rate)
            assert reacquire.found
        else:
            naming = TrackedModelLabeller(skeleton, cloud.rate)
            named = [naming.update(cloud.points[f], f / cloud.rate)[1] for f in range(720)]
            assert sum(int((n >= 0).sum()) for n in named) > 720 * len(labelled.labels) // 2
    if stage == "filling":
        given = GapFiller(labelled.labels, labelled.rate, FillerConfig(), skeleton)
        learning = GapFiller(labelled.labels, labelled.rate, FillerConfig(), None)
        for f in range(720):
            given.update(labelled.positions[f])
            learning.update(labelled.positions[f])
            given.predict_next()
        assert learning.skeleton is not None
    if stage == "fits":
        solver = PoseSolver(skeleton, labelled.labels)
        for f in range(720):
            solver(labelled.true_positions[f][None])
        groups = [[labelled.labels.index(m) for m in seg.markers] for seg in skeleton.segments]
        build_skeleton(labelled.true_positions, labelled.labels, labelled.rate, groups)
    return [kernel.__name__ for kernel in kernels if set(kernel.overloads) != ready[kernel]]


@pytest.mark.integration
@pytest.mark.parametrize("stage", list(STAGES))
def test_after_its_compile_a_live_stage_compiles_nothing_on_its_frames(stage: str) -> None:
    done = subprocess.run([sys.executable, __file__, stage], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    late = done.stdout.split()
    assert not late, f"{stage}: compiled or loaded on a frame, not by the kernels of {STAGES[stage]}: {late}"


def test_the_kalman_bank_follows_its_equations() -> None:
    bank = ConstantVelocityBank(3, 0.01, 1000.0, 500.0)
    z = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [np.nan, np.nan, np.nan]])
    bank.update(z, np.full(3, 4.0))
    assert bank.started.tolist() == [True, True, False]
    bank.predict(np.array([1.0, 0.5, 1.0]))
    f, q = bank.F, bank.Q
    p = np.array([[4.0, 0.0], [0.0, 500.0**2]])
    p = f @ p @ f.T + q
    np.testing.assert_allclose([bank.p00[0], bank.p01[0], bank.p11[0]], [p[0, 0], p[0, 1], p[1, 1]], rtol=1e-12)
    z2 = np.array([[1.0, 0.0, 0.0], [1.0, 2.0, 3.0], [np.nan, np.nan, np.nan]])
    bank.update(z2, np.full(3, 4.0), np.array([True, False, False]))
    gain = p[:, 0] / (p[0, 0] + 4.0)  # K = P H^T / (H P H^T + R)
    np.testing.assert_allclose(bank.pos[0], [gain[0] * 1.0, 0.0, 0.0], rtol=1e-12)
    np.testing.assert_allclose(bank.vel[0], [gain[1] * 1.0, 0.0, 0.0], rtol=1e-12)
    after = (np.eye(2) - np.outer(gain, [1.0, 0.0])) @ p
    np.testing.assert_allclose([bank.p00[0], bank.p01[0], bank.p11[0]], [after[0, 0], after[0, 1], after[1, 1]],
                               rtol=1e-12)
    np.testing.assert_array_equal(bank.pos[1], [1.0, 2.0, 3.0])  # not selected: left as it was
    assert np.isnan(bank.pos[2]).all()


def test_a_rigid_fit_recovers_a_known_pose_and_ignores_what_weighs_nothing() -> None:
    rng = np.random.default_rng(5)
    local = rng.normal(scale=100.0, size=(4, 3))
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0, 0, 1.0]])
    world = local @ rotation.T + [10.0, -20.0, 30.0]
    fit = fit_one(local, world, np.ones(4))
    assert fit is not None
    np.testing.assert_allclose(fit[0], rotation, atol=1e-12)
    np.testing.assert_allclose(fit[1], [10.0, -20.0, 30.0], atol=1e-9)
    mirrored = world * [1.0, 1.0, -1.0]  # the best rotation, not the reflection
    assert np.linalg.det(fit_one(local, mirrored, np.ones(4))[0]) == pytest.approx(1.0)  # type: ignore[index]
    assert fit_one(local[:2], world[:2], np.ones(2)) is None  # two points fix no rotation
    hidden = world.copy()
    hidden[3] = np.nan  # weighs nothing: its coordinates are not read
    r, t, ok = kabsch(local[None], hidden[None], np.array([[1.0, 1.0, 1.0, 0.0]]))
    assert ok[0]
    np.testing.assert_allclose(r[0], rotation, atol=1e-12)
    np.testing.assert_allclose(t[0], [10.0, -20.0, 30.0], atol=1e-9)


if __name__ == "__main__":
    print(*_stage(sys.argv[1]))
