"""Kinematic model of the Franka Emika Panda: forward kinematics, Jacobians, IK.

The model comes from example-robot-data's `panda.urdf` (kinematics only, no
meshes), with the two finger joints locked, leaving the 7 arm joints. As in
Pinocchio, the model is immutable and shared; the scratch `Data` is one per
thread (`data`), so threads sharing one `PandaKinematics` never read each
other's poses.

Frames: `flange` is `panda_link8` (the flange of joint 7, 0.107 m along its
axis); `camera` and `tcp` are fixed in the flange frame by `T_flange_cam`
(hand-eye calibration) and `T_flange_tcp`. Jacobians are 6x7 in Pinocchio's
LOCAL_WORLD_ALIGNED convention: rows 0-2 are the linear velocity of the frame's
origin and rows 3-5 the angular velocity, both in base-frame axes.
"""

from __future__ import annotations

import functools
import math
import site
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from supervisor.arm.limits import PANDA, arm_limits
from supervisor.errors import DriverError, DriverUnavailable, KinematicsError
from supervisor.geometry import validate_T

N_JOINTS = 7
FLANGE_LINK = "panda_link8"
FINGER_JOINTS = ("panda_finger_joint1", "panda_finger_joint2")
ARM_JOINTS = tuple(f"panda_joint{i}" for i in range(1, N_JOINTS + 1))
URDF_RELPATH = Path("cmeel.prefix/share/example-robot-data/robots/panda_description/urdf/panda.urdf")
FRAMES = ("flange", "camera", "tcp")
_RESTARTS_NEAR = 6  # ik_or_raise: restarts from perturbations of the seed (+-0.4 rad)
_RESTARTS_ANYWHERE = 8  # ... then from uniform samples of the joint range

# Franka Emika Panda datasheet limits (rad, rad/s, rad/s^2, rad/s^3); other arms: supervisor/arm/limits.py.
DATASHEET_Q_MIN = PANDA.q_min
DATASHEET_Q_MAX = PANDA.q_max
DATASHEET_DQ_MAX = PANDA.dq_max
DATASHEET_DDQ_MAX = PANDA.ddq_max
DATASHEET_DDDQ_MAX = PANDA.dddq_max

# libfranka's "ready" posture: flange about 0.31 m in front of the base, 0.59 m up, pointing down.
Q_READY = np.array([0.0, -math.pi / 4, 0.0, -3 * math.pi / 4, 0.0, math.pi / 2, math.pi / 4])


def find_panda_urdf() -> Path:
    """Locate example-robot-data's panda.urdf under any site-packages directory on this interpreter."""
    roots: list[str] = []
    try:
        roots += site.getsitepackages()
    except AttributeError:  # some virtualenv builds lack it
        pass
    try:
        roots.append(site.getusersitepackages())
    except AttributeError:
        pass
    roots += [p for p in sys.path if p]
    seen: set[str] = set()
    for root in roots:
        if root in seen:
            continue
        seen.add(root)
        candidate = Path(root) / URDF_RELPATH
        if candidate.is_file():
            return candidate
    raise DriverUnavailable(
        "Panda URDF not found: install the 'example-robot-data' package (pip install example-robot-data), "
        "or give the robot's urdf path in the configuration"
    )


@functools.lru_cache(maxsize=4)
def _arm_model(urdf: str) -> pin.Model:
    """The 7-joint arm model of a Panda URDF (finger joints locked at 0). Cached: treat as read-only."""
    try:
        full = pin.buildModelFromUrdf(urdf)
    except (RuntimeError, ValueError) as exc:
        raise DriverError(f"{urdf}: cannot build a kinematic model: {exc}") from exc
    missing = [n for n in ARM_JOINTS + FINGER_JOINTS if not full.existJointName(n)]
    if missing:
        raise DriverError(f"{urdf}: not a Panda URDF, missing joints {', '.join(missing)}")
    lock = [full.getJointId(n) for n in FINGER_JOINTS]
    model = pin.buildReducedModel(full, lock, pin.neutral(full))
    if model.nq != N_JOINTS or not model.existFrame(FLANGE_LINK):
        raise DriverError(f"{urdf}: expected 7 arm joints and a {FLANGE_LINK} frame")
    return model


def _rigid(T: np.ndarray | None, name: str) -> pin.SE3 | None:
    if T is None:
        return None
    T = validate_T(T, name)
    return pin.SE3(T[:3, :3].copy(), T[:3, 3].copy())


_EYE3 = np.eye(3)


def _is_pose(T: np.ndarray, tol: float = 1e-6) -> bool:
    """Finite 4x4 with a proper rotation block: `validate_T`'s test in a quarter of its time (IK's hot path)."""
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    if np.abs(R @ R.T - _EYE3).max() > tol:
        return False
    a, b, c, d, e, f, g, h, i = R.ravel().tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) > 0  # det > 0: no reflection


def _dls_step(J: np.ndarray, e: np.ndarray, pull: np.ndarray | None, sigma_damp: float, damping: float) -> np.ndarray:
    """J^+ e + (I - J^+ J) pull with the SVD pseudo-inverse, damped only near a singularity (Maciejewski-Klein)."""
    U, S, Vt = np.linalg.svd(J, full_matrices=False)
    s_min = S[-1]
    lam2 = 0.0 if s_min >= sigma_damp else (1.0 - (s_min / sigma_damp) ** 2) * damping**2
    S2 = S * S + lam2
    dq = Vt.T @ ((S / S2) * (U.T @ e))
    if pull is not None:  # J^+ J = V diag(S^2 / (S^2 + lam2)) V^T
        dq += pull - Vt.T @ ((S * S / S2) * (Vt @ pull))
    return dq


def _dls_step_at_limits(J: np.ndarray, e: np.ndarray, pull: np.ndarray | None, low: np.ndarray, high: np.ndarray,
                        sigma_damp: float, damping: float) -> np.ndarray:
    """`_dls_step` where joints at a limit that the step would push outward leave the solve (two passes)."""
    free = np.ones(N_JOINTS, dtype=bool)
    for _ in range(2):  # second pass only if a joint at its limit would be pushed outward
        dq = _dls_step(J * free, e, None if pull is None else pull * free, sigma_damp, damping)
        blocked = (low & (dq < 0)) | (high & (dq > 0))
        if not np.any(blocked & free):
            break
        free &= ~blocked
    return dq * free


@dataclass(frozen=True)
class IKResult:
    """Outcome of one IK solve; `q` is the last iterate even when `success` is False."""

    q: np.ndarray
    success: bool
    pos_err: float  # m
    rot_err: float  # rad
    iterations: int


class PandaKinematics:
    """Panda forward/inverse kinematics with a camera and an optional tool mounted on the flange.

    `q_min`/`q_max` are the joint limits used everywhere (planning, IK, the
    robot's command check): the URDF's, intersected with the datasheet's, and
    shrunk by `position_margin` on each side. `dq_max`, `ddq_max`, `dddq_max`
    are the datasheet's velocity, acceleration and jerk limits. `arm` ('panda'
    or 'fr3') picks the datasheet table (supervisor/arm/limits.py); an FR3 with
    the default (Panda) URDF takes its table's position limits as they are.
    """

    def __init__(
        self,
        *,
        T_flange_cam: np.ndarray | None = None,
        T_flange_tcp: np.ndarray | None = None,
        urdf: str | Path | None = None,
        position_margin: float = 0.0,
        q_neutral: np.ndarray | None = None,
        arm: str = "panda",
    ) -> None:
        limits = arm_limits(arm)
        self.arm = arm
        if urdf is None:
            urdf_path = find_panda_urdf()
        else:
            urdf_path = Path(urdf)
            if not urdf_path.is_file():
                raise DriverUnavailable(f"Panda URDF not found at {urdf_path}")
        self.urdf = urdf_path
        base = _arm_model(str(urdf_path.resolve()))
        model = pin.Model(base)  # our own copy: we add the camera/tcp frames to it
        flange_id = model.getFrameId(FLANGE_LINK)
        flange = model.frames[flange_id]
        self._fid = {"flange": flange_id}
        self.T_flange_cam = None if T_flange_cam is None else validate_T(T_flange_cam, "T_flange_cam").copy()
        self.T_flange_tcp = None if T_flange_tcp is None else validate_T(T_flange_tcp, "T_flange_tcp").copy()
        for name, T in (("camera", T_flange_cam), ("tcp", T_flange_tcp)):
            M = _rigid(T, f"T_flange_{'cam' if name == 'camera' else name}")
            if M is not None:
                frame = pin.Frame(name, flange.parentJoint, flange_id, flange.placement * M, pin.FrameType.OP_FRAME)
                self._fid[name] = model.addFrame(frame)
        self.model = model
        # pinocchio's Data is scratch space every call writes: one per thread, so that threads sharing this
        # instance (the control loop, the driver's hold thread, a camera rendering from the arm's state, a
        # run's summary) never read each other's poses.
        self._local = threading.local()
        # Reach bound per frame: joint 2's origin does not move with q, and no frame can be farther from it
        # than the summed lengths of the links after it (triangle inequality). Used to reject a goal at once.
        j1, j2 = model.jointPlacements[1], model.jointPlacements[2]
        self._shoulder = np.array(j1.translation + j1.rotation @ j2.translation)  # fixed: j2 sits on j1's axis
        links = sum(float(np.linalg.norm(model.jointPlacements[j].translation)) for j in range(3, model.njoints))
        self._reach = {name: links + float(np.linalg.norm(model.frames[fid].placement.translation))
                       for name, fid in self._fid.items()}

        if not math.isfinite(position_margin) or position_margin < 0:
            raise ValueError(f"position_margin must be a finite non-negative number, got {position_margin}")
        self.position_margin = float(position_margin)
        self.urdf_q_min = np.array(model.lowerPositionLimit, dtype=float)
        self.urdf_q_max = np.array(model.upperPositionLimit, dtype=float)
        # The default URDF is the Panda's: an FR3 takes its own table unless its URDF is given.
        with_urdf = arm == "panda" or urdf is not None
        self.q_min = (np.maximum(self.urdf_q_min, limits.q_min) if with_urdf else limits.q_min) + position_margin
        self.q_max = (np.minimum(self.urdf_q_max, limits.q_max) if with_urdf else limits.q_max) - position_margin
        if np.any(self.q_min >= self.q_max):
            raise ValueError(f"position_margin {position_margin} rad leaves no joint range")
        urdf_v = np.array(model.velocityLimit, dtype=float)
        self.velocity_limit_source = (
            "urdf (equal to datasheet)" if np.allclose(urdf_v, limits.dq_max)
            else f"datasheet (urdf gave {urdf_v.tolist()})"
        )
        self.dq_max = limits.dq_max.copy()
        self.ddq_max = limits.ddq_max.copy()
        self.dddq_max = limits.dddq_max.copy()
        for a in (self.q_min, self.q_max, self.dq_max, self.ddq_max, self.dddq_max):
            a.setflags(write=False)

        qn = Q_READY if q_neutral is None else np.asarray(q_neutral, dtype=float)
        if qn.shape != (N_JOINTS,) or not self.within_limits(qn):
            raise ValueError(f"q_neutral must be 7 joint angles within limits, got {qn}")
        self.q_neutral = qn.copy()
        self.q_neutral.setflags(write=False)

    # -- bookkeeping ---------------------------------------------------------
    @property
    def q_ready(self) -> np.ndarray:
        """A safe default start posture (libfranka's ready pose)."""
        return Q_READY.copy()

    @property
    def frames(self) -> tuple[str, ...]:
        """Frame names this instance can evaluate."""
        return tuple(f for f in FRAMES if f in self._fid)

    @property
    def data(self) -> pin.Data:
        """The calling thread's pinocchio scratch data (created at its first use)."""
        d = getattr(self._local, "data", None)
        if d is None:
            d = self._local.data = self.model.createData()
        return d

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        del state["_local"]  # per-thread scratch: the receiving process makes its own
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._local = threading.local()

    def within_limits(self, q: np.ndarray, tol: float = 0.0) -> bool:
        """True if `q` is 7 finite angles inside [q_min - tol, q_max + tol]."""
        q = np.asarray(q, dtype=float)
        return bool(
            q.shape == (N_JOINTS,) and np.all(np.isfinite(q))
            and np.all(q >= self.q_min - tol) and np.all(q <= self.q_max + tol)
        )

    def _frame_id(self, frame: str) -> int:
        try:
            return self._fid[frame]
        except KeyError:
            if frame in FRAMES:
                raise ValueError(f"no {frame} frame: T_flange_{'cam' if frame == 'camera' else frame} "
                                 "was not given") from None
            raise ValueError(f"unknown frame {frame!r}; expected one of {FRAMES}") from None

    @staticmethod
    def _q(q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.shape != (N_JOINTS,):
            raise ValueError(f"expected 7 joint angles, got shape {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"joint angles must be finite, got {q}")
        return q

    # -- kinematics ----------------------------------------------------------
    def fk(self, q: np.ndarray, frame: str = "flange") -> np.ndarray:
        """`T_base_<frame>` at joint angles `q`."""
        fid = self._frame_id(frame)
        d = self.data
        pin.forwardKinematics(self.model, d, self._q(q))
        return pin.updateFramePlacement(self.model, d, fid).homogeneous

    def body_points(self, q: np.ndarray) -> np.ndarray:
        """Points along the arm at joint angles `q`, in base coordinates: every joint's origin, the flange and
        the camera/tcp frames this instance has, (N, 3). What a clearance check measures (no link geometry)."""
        d = self.data
        pin.forwardKinematics(self.model, d, self._q(q))
        pts = [d.oMi[j].translation for j in range(1, self.model.njoints)]
        pts += [pin.updateFramePlacement(self.model, d, fid).translation for fid in self._fid.values()]
        return np.array(pts)

    def jacobian(self, q: np.ndarray, frame: str = "flange") -> np.ndarray:
        """6x7 Jacobian of `frame`, LOCAL_WORLD_ALIGNED: [v_origin; omega] in base axes."""
        fid = self._frame_id(frame)
        return pin.computeFrameJacobian(self.model, self.data, self._q(q), fid, pin.LOCAL_WORLD_ALIGNED)

    def _fk_jac(self, q: np.ndarray, fid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, rotation and LOCAL_WORLD_ALIGNED Jacobian of frame `fid` in one pass."""
        d = self.data
        pin.computeJointJacobians(self.model, d, q)
        M = pin.updateFramePlacement(self.model, d, fid)
        J = pin.getFrameJacobian(self.model, d, fid, pin.LOCAL_WORLD_ALIGNED)
        return M.translation, M.rotation, J

    def ik(
        self,
        T_base_goal: np.ndarray,
        q_seed: np.ndarray | None = None,
        frame: str = "camera",
        *,
        tol_pos: float = 1e-5,
        tol_rot: float = 1e-4,
        max_iter: int = 100,
        null_gain: float = 0.1,
        max_step: float = 0.3,
        sigma_damp: float = 0.05,
        damping: float = 0.05,
    ) -> IKResult:
        """Damped-least-squares IK for `frame` to reach `T_base_goal`, starting at `q_seed`.

        Each iteration solves J dq = e (e = [position error; rotation vector of
        R_goal R^T], base axes) with the pseudo-inverse from the SVD of J, damped
        only when the smallest singular value falls below `sigma_damp`
        (Maciejewski-Klein), adds a null-space pull toward `q_neutral` with gain
        `null_gain`, caps the step at `max_step` rad per joint and clamps to the
        joint limits; joints held at a limit leave the solve. Converged when the
        position error <= `tol_pos` (m) and the rotation error <= `tol_rot` (rad).
        """
        fid = self._frame_id(frame)
        T_goal = np.asarray(T_base_goal, dtype=float)
        if not _is_pose(T_goal):
            validate_T(T_goal, "T_base_goal")  # raises, saying what is wrong
        p_goal, R_goal = T_goal[:3, 3], T_goal[:3, :3]
        q_min, q_max = self.q_min, self.q_max
        q = np.clip(self._q(self.q_neutral if q_seed is None else q_seed), q_min, q_max)
        e = np.empty(6)
        it = 0
        while True:
            p, R, J = self._fk_jac(q, fid)
            e[:3] = p_goal - p
            e[3:] = pin.log3(R_goal @ R.T)
            pos_err = math.sqrt(e[:3] @ e[:3])
            rot_err = math.sqrt(e[3:] @ e[3:])
            if pos_err <= tol_pos and rot_err <= tol_rot:
                return IKResult(q, True, pos_err, rot_err, it)
            if it >= max_iter:
                return IKResult(q, False, pos_err, rot_err, it)
            it += 1
            # The pull decays geometrically so it shapes the early iterations but
            # cannot hold the residual above tolerance (a null-space step is only
            # first-order free of task error).
            gain = null_gain * 0.5 ** (it - 1)
            pull = gain * (self.q_neutral - q) if gain > 0 else None
            low, high = q <= q_min, q >= q_max
            if np.any(low | high):
                dq = _dls_step_at_limits(J, e, pull, low, high, sigma_damp, damping)
            else:
                dq = _dls_step(J, e, pull, sigma_damp, damping)
            peak = float(np.max(np.abs(dq)))
            if peak > max_step:
                dq *= max_step / peak
            q = np.clip(q + dq, q_min, q_max)

    def why_stuck(self, q: np.ndarray, frame: str = "camera", *, near: float = 1e-3,
                  sigma_singular: float = 0.02) -> str:
        """What blocks an IK iterate that stopped short of its goal: the joints held at a limit, or a
        singularity (smallest singular value of the frame's Jacobian), said in words."""
        q = np.asarray(q, dtype=float)
        parts = []
        for j in np.flatnonzero(q <= self.q_min + near):
            parts.append(f"joint {j + 1} at its lower limit {math.degrees(self.q_min[j]):.2f} deg")
        for j in np.flatnonzero(q >= self.q_max - near):
            parts.append(f"joint {j + 1} at its upper limit {math.degrees(self.q_max[j]):.2f} deg")
        sigma = float(np.linalg.svd(self.jacobian(q, frame), compute_uv=False)[-1])
        if sigma < sigma_singular:
            parts.append(f"near a singularity (smallest Jacobian singular value {sigma:.4f})")
        if not parts:
            return f"no joint is at a limit and the arm is not singular (smallest singular value {sigma:.3f})"
        return "blocked by " + ", ".join(parts)

    def ik_or_raise(self, T_base_goal: np.ndarray, q_seed: np.ndarray | None = None, frame: str = "camera",
                    **options: float) -> np.ndarray:
        """Like `ik` but returns only `q`, raising KinematicsError (with `.result`) if no solution is found.

        A goal beyond the arm's reach bound fails at once (`.result` None); otherwise a failed
        first solve is retried from the neutral posture, from 6 perturbations of the seed and
        from 8 samples of the joint range (deterministic), best residual reported on failure.
        """
        self._frame_id(frame)  # an unknown frame is misuse (ValueError), not an unreachable pose
        p_goal = validate_T(T_base_goal, "T_base_goal")[:3, 3]
        dist = float(np.linalg.norm(p_goal - self._shoulder))
        if dist > self._reach[frame]:
            err = KinematicsError(
                f"IK for the {frame} frame: goal at {np.round(p_goal, 4).tolist()} m in the base frame is out of "
                f"reach ({dist:.3f} m from the shoulder, the arm reaches at most {self._reach[frame]:.3f} m)"
            )
            err.result = None  # type: ignore[attr-defined]
            raise err
        res = self.ik(T_base_goal, q_seed, frame, **options)
        if not res.success:
            # DLS can stall in a local minimum (a joint held at its limit) or crawl near a singularity:
            # retry from the neutral posture, from perturbations of the seed (solutions near the seed
            # first), then from anywhere in the joint range, before declaring the pose unreachable.
            # The restarts are deterministic (fixed RNG seed) so a run is reproducible.
            base = self.q_neutral if q_seed is None else np.asarray(q_seed, dtype=float)
            rng = np.random.default_rng(12345)
            near = [base + rng.uniform(-0.4, 0.4, N_JOINTS) for _ in range(_RESTARTS_NEAR)]
            anywhere = [rng.uniform(self.q_min, self.q_max) for _ in range(_RESTARTS_ANYWHERE)]
            for seed in [self.q_neutral, *near, *anywhere]:
                retry = self.ik(T_base_goal, np.clip(seed, self.q_min, self.q_max), frame, **options)
                if retry.success:
                    return retry.q
                if retry.pos_err + retry.rot_err < res.pos_err + res.rot_err:
                    res = retry
            if not res.success and res.pos_err < 2e-3 and res.rot_err < math.radians(1.0):
                # Close but crawling (a joint near its limit, a shallow valley): let the best iterate go on.
                polish = self.ik(T_base_goal, res.q, frame, **{**options, "max_iter": 400, "null_gain": 0.0})
                if polish.success:
                    return polish.q
                if polish.pos_err + polish.rot_err < res.pos_err + res.rot_err:
                    res = polish
        if not res.success:
            err = KinematicsError(
                f"IK for the {frame} frame did not converge after {res.iterations} iterations: "
                f"position error {res.pos_err * 1000:.3f} mm, rotation error {math.degrees(res.rot_err):.4f} deg "
                f"(goal at {np.round(np.asarray(T_base_goal)[:3, 3], 4).tolist()} m in the base frame); "
                f"{self.why_stuck(res.q, frame)}"
            )
            err.result = res  # type: ignore[attr-defined]
            raise err
        return res.q
