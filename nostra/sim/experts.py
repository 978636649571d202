"""Scripted experts: waypoint/phase scripts over privileged simulator state (object poses).

Each task's script is a generator that yields 7-d OSC_POSE delta actions; a phase is one
``move``/``hold`` call (approach, descend, grasp, lift, move, place/insert, release, retreat).
Targets are re-read from the simulator every step, so the expert tracks objects that move. The
scripts are deterministic: the same seed and variation give the same actions.

    env = make_env("Lift"); expert = make_expert(env)
    obs = env.reset(seed=3); expert.reset()
    obs, reward, done, info = env.step(expert.act())
"""

from __future__ import annotations

from typing import Callable, Iterator

import mujoco
import numpy as np

from nostra.sim import scene

# OSC_POSE scales an action of 1 to 5 cm / 0.5 rad (robosuite's BASIC controller config).
POS_SCALE, ROT_SCALE = 0.05, 0.5
OPEN, CLOSE = -1.0, 1.0
# Every phase a script names (generate.action_noise_phases picks from these); "done": after the script.
PHASES = ("approach", "descend", "grasp", "lift", "regrasp", "move", "place", "release", "retreat", "rotate",
          "insert", "orient", "reach", "turn", "pull", "settle", "done")
# Gripper pointing straight down; its fingers close along the world y axis (local x) at yaw 0.
R_DOWN = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def down(yaw: float = 0.0) -> np.ndarray:
    """Gripper orientation pointing down, fingers closing along direction yaw + 90 degrees."""
    return rot_z(yaw) @ R_DOWN


def yaw_of(mat: np.ndarray) -> float:
    return float(np.arctan2(mat[1, 0], mat[0, 0]))


def wrap(angle: float, period: float = 2 * np.pi) -> float:
    """Angle in [-period/2, period/2)."""
    return float((angle + period / 2) % period - period / 2)


def rotvec(mat: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix."""
    quat, vec = np.zeros(4), np.zeros(3)
    mujoco.mju_mat2Quat(quat, mat.ravel())
    mujoco.mju_quat2Vel(vec, quat, 1.0)
    return vec


class Arm:
    """Privileged view of the scene and the OSC action that drives the gripper to a pose."""

    def __init__(self, env):
        self.env = env
        self.site = env.raw.robots[0].eef_site_id["right"]
        self.base_rot = env.data.xmat[scene.body_id(env.model, "robot0_base")].reshape(3, 3).copy()
        raw = env.raw  # height of the surface objects rest on (the bins' floor in PickPlace)
        self.table_z = float(raw.table_offset[2] if hasattr(raw, "table_offset") else raw.bin1_pos[2])
        self.phase = ""

    @property
    def m(self):
        return self.env.model

    @property
    def d(self):
        return self.env.data

    def eef(self) -> np.ndarray:
        return self.d.site_xpos[self.site].copy()

    def eef_mat(self) -> np.ndarray:
        return self.d.site_xmat[self.site].reshape(3, 3).copy()

    def body_pos(self, name: str) -> np.ndarray:
        return self.d.xpos[scene.body_id(self.m, name)].copy()

    def body_mat(self, name: str) -> np.ndarray:
        return self.d.xmat[scene.body_id(self.m, name)].reshape(3, 3).copy()

    def site_pos(self, name: str) -> np.ndarray:
        return self.d.site_xpos[mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_SITE, name)].copy()

    def joint_qpos(self, name: str) -> float:
        return float(self.d.qpos[self.m.jnt_qposadr[mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_JOINT, name)]])

    def action(self, pos, mat, grip: float, speed: float = 1.0) -> np.ndarray:
        """Delta action towards (pos, mat); `speed` caps the position step (1 = 5 cm)."""
        dpos = self.base_rot.T @ (np.asarray(pos) - self.eef()) / POS_SCALE
        norm = np.linalg.norm(dpos)
        if norm > speed:
            dpos *= speed / norm
        drot = self.base_rot.T @ rotvec(mat @ self.eef_mat().T) / ROT_SCALE
        return np.concatenate([dpos, np.clip(drot, -1, 1), [grip]]).astype(np.float32)

    def move(self, phase: str, target: Callable[[], np.ndarray], mat, grip: float, tol: float = 0.01,
             rot_tol: float = 0.05, speed: float = 1.0, max_steps: int = 100) -> Iterator[np.ndarray]:
        """Go to target() (re-evaluated each step) with orientation mat until within tolerance."""
        self.phase = phase
        for _ in range(max_steps):
            goal = target()
            mat_goal = mat() if callable(mat) else mat
            if (np.linalg.norm(goal - self.eef()) < tol
                    and np.linalg.norm(rotvec(mat_goal @ self.eef_mat().T)) < rot_tol):
                return
            yield self.action(goal, mat_goal, grip, speed)

    def hold(self, phase: str, grip: float, steps: int, mat=None) -> Iterator[np.ndarray]:
        """Stay where the gripper is (e.g. while it closes)."""
        self.phase = phase
        pos, mat = self.eef(), self.eef_mat() if mat is None else mat
        for _ in range(steps):
            yield self.action(pos, mat, grip)


# ---- task scripts ----------------------------------------------------------------------------

def _box_yaw(arm: Arm, body: str, avoid: str | None = None) -> float:
    """Gripper yaw that puts the fingers on two opposite faces of a box. Of the two such yaws
    within 90 degrees of the start, take the one whose fingers stay clear of body `avoid`."""
    base = wrap(yaw_of(arm.body_mat(body)), np.pi / 2)
    candidates = [base, base - np.pi / 2 if base > 0 else base + np.pi / 2]
    if avoid is None:
        return candidates[0]
    d = arm.body_pos(avoid) - arm.body_pos(body)
    toward = np.arctan2(d[1], d[0])
    # fingers close along yaw + 90 degrees: keep that axis perpendicular to the other body
    return max(candidates, key=lambda y: abs(np.sin(y + np.pi / 2 - toward)))


def _half_height(arm: Arm, body: str) -> float:
    geoms = scene.body_geoms(arm.m, scene.body_id(arm.m, body), visual_only=False)
    return float(max(arm.m.geom_size[g][2] for g in geoms if arm.m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX))


def _pick(arm: Arm, body: str, yaw: Callable[[], float], grasp: Callable[[], np.ndarray] | None = None,
          lift_to: float = 0.15, tries: int = 3) -> Iterator[np.ndarray]:
    """Approach above the grasp point (default: the body's origin), descend, close the gripper and
    lift to table + lift_to; retry from the approach when the body did not come up."""
    grasp = grasp or (lambda: arm.body_pos(body))
    for _ in range(tries):
        y, start_z = yaw(), arm.body_pos(body)[2]
        yield from arm.move("approach", lambda: grasp() + [0, 0, 0.08], down(y), OPEN, tol=0.01, max_steps=80)
        yield from arm.move("descend", grasp, down(y), OPEN, tol=0.006, speed=0.5, max_steps=40)
        yield from arm.hold("grasp", CLOSE, steps=12, mat=down(y))
        lift = lambda: np.r_[arm.eef()[:2], arm.table_z + lift_to]  # noqa: E731
        yield from arm.move("lift", lift, down(y), CLOSE, tol=0.02, speed=0.6, max_steps=60)
        if arm.body_pos(body)[2] > start_z + 0.5 * (arm.table_z + lift_to - start_z):
            return
        yield from arm.hold("regrasp", OPEN, steps=8)


def lift_script(arm: Arm) -> Iterator[np.ndarray]:
    yield from _pick(arm, "cube_main", lambda: _box_yaw(arm, "cube_main"), lift_to=0.2)


def stack_script(arm: Arm) -> Iterator[np.ndarray]:
    a, b = "cubeA_main", "cubeB_main"
    yield from _pick(arm, a, lambda: _box_yaw(arm, a, avoid=b), lift_to=0.15)
    yaw = yaw_of(arm.eef_mat() @ R_DOWN.T)
    h_a, h_b = _half_height(arm, a), _half_height(arm, b)
    # Carry cube A so its centre is above cube B's, then lower it until it nearly touches.
    offset = lambda: arm.eef() - arm.body_pos(a)  # noqa: E731
    over = lambda: np.r_[arm.body_pos(b)[:2] + offset()[:2], arm.table_z + 0.15]  # noqa: E731
    yield from arm.move("move", over, down(yaw), CLOSE, tol=0.01, max_steps=80)
    on_top = lambda: np.r_[over()[:2], arm.body_pos(b)[2] + h_b + h_a + offset()[2] + 0.008]  # noqa: E731
    yield from arm.move("place", on_top, down(yaw), CLOSE, tol=0.005, speed=0.4, max_steps=80)
    yield from arm.hold("release", OPEN, steps=10)
    yield from arm.move("retreat", lambda: np.r_[arm.eef()[:2], arm.table_z + 0.2], down(yaw), OPEN,
                        speed=0.5, max_steps=40)


def can_script(arm: Arm) -> Iterator[np.ndarray]:
    env, can = arm.env.raw, "Can_main"
    bin_z = float(env.bin2_pos[2])
    # grasp a little above the can's centre: the palm stays clear of its top
    yield from _pick(arm, can, lambda: 0.0, grasp=lambda: arm.body_pos(can) + [0, 0, 0.01], lift_to=0.25)
    target = np.asarray(env.target_bin_placements[env.object_to_id["can"]], dtype=float)
    offset = lambda: arm.eef() - arm.body_pos(can)  # noqa: E731
    over = lambda: np.r_[target[:2] + offset()[:2], bin_z + 0.25]  # noqa: E731
    yield from arm.move("move", over, down(0.0), CLOSE, tol=0.015, max_steps=100)
    low = lambda: np.r_[over()[:2], bin_z + 0.1 + offset()[2]]  # noqa: E731
    yield from arm.move("place", low, down(0.0), CLOSE, tol=0.01, speed=0.5, max_steps=60)
    yield from arm.hold("release", OPEN, steps=10)
    yield from arm.move("retreat", lambda: np.r_[arm.eef()[:2], bin_z + 0.3], down(0.0), OPEN, speed=0.6,
                        max_steps=40)


def nut_script(arm: Arm) -> Iterator[np.ndarray]:
    nut, handle = "SquareNut_main", "SquareNut_handle_site"
    peg = arm.body_pos("peg1")
    # fingers close across the handle (the nut's local y axis)
    yaw = lambda: wrap(yaw_of(arm.body_mat(nut)), np.pi)  # noqa: E731
    yield from _pick(arm, nut, yaw, grasp=lambda: arm.site_pos(handle) - [0, 0, 0.005], lift_to=0.25)
    # turn the handle away from the peg side (towards -x or +-y) so the arm can reach over the peg
    nut_yaw = yaw_of(arm.body_mat(nut))
    turn = min((wrap(t - nut_yaw) for t in (np.pi / 2, np.pi, -np.pi / 2)), key=abs)
    mat = rot_z(turn) @ arm.eef_mat()
    yield from arm.move("rotate", lambda: np.r_[arm.eef()[:2], arm.table_z + 0.25], mat, CLOSE, tol=0.02,
                        rot_tol=0.03, speed=0.3, max_steps=60)
    # move the nut's centre over the peg, then lower it down the peg
    over = lambda: np.r_[arm.eef()[:2] + peg[:2] - arm.body_pos(nut)[:2], arm.table_z + 0.25]  # noqa: E731
    yield from arm.move("move", over, mat, CLOSE, tol=0.008, max_steps=100)
    yield from arm.hold("settle", CLOSE, steps=5, mat=mat)
    insert = lambda: np.r_[over()[:2], arm.eef()[2] - arm.body_pos(nut)[2] + arm.table_z + 0.02]  # noqa: E731
    yield from arm.move("insert", insert, mat, CLOSE, tol=0.01, speed=0.3, max_steps=80)
    yield from arm.hold("release", OPEN, steps=10)
    yield from arm.move("retreat", lambda: np.r_[arm.eef()[:2], arm.table_z + 0.25], mat, OPEN, speed=0.6,
                        max_steps=40)


LEVER_TURN = -1.45  # radians the lever is turned (up: down runs the wrist into its limit) to free the latch


def axis_rot(axis, angle: float) -> np.ndarray:
    quat, mat = np.zeros(4), np.zeros(9)
    mujoco.mju_axisAngle2Quat(quat, np.asarray(axis, dtype=float), angle)
    mujoco.mju_quat2Mat(mat, quat)
    return mat.reshape(3, 3)


def facing(normal: np.ndarray) -> np.ndarray:
    """Gripper pointing horizontally along -normal, fingers closing vertically (a 90 degree turn
    from pointing down)."""
    z = -np.asarray(normal, dtype=float)
    z[2] = 0.0
    z /= np.linalg.norm(z)
    x = np.array([0.0, 0.0, -1.0])
    return np.stack([x, np.cross(z, x), z], axis=1)


def door_script(arm: Arm) -> Iterator[np.ndarray]:
    handle, hinge, latch = "Door_handle", "Door_hinge", "Door_latch_joint"
    normal = -arm.body_mat("Door_latch")[:, 1]  # the door's outward normal, towards the robot
    if normal[1] < 0:
        normal = -normal
    mat = facing(normal)
    front = lambda: arm.site_pos(handle) + 0.12 * normal  # noqa: E731
    start = arm.eef()
    yield from arm.move("orient", lambda: start, mat, OPEN, tol=0.03, rot_tol=0.1, speed=0.3, max_steps=60)
    yield from arm.move("approach", front, mat, OPEN, tol=0.01, max_steps=100)
    yield from arm.move("reach", lambda: arm.site_pos(handle) - 0.005 * normal, mat, OPEN, tol=0.006, speed=0.4,
                        max_steps=50)
    yield from arm.hold("grasp", CLOSE, steps=12, mat=mat)
    # turn the lever about the latch axis (the gripper turns with it) to free the latch
    latch_id = mujoco.mj_name2id(arm.m, mujoco.mjtObj.mjOBJ_JOINT, latch)
    anchor, axis = arm.d.xanchor[latch_id].copy(), arm.d.xaxis[latch_id].copy()
    grasp = arm.eef()
    for k in range(1, 56):
        turn = axis_rot(axis, LEVER_TURN * min(1.0, k / 40))
        arm.phase = "turn"
        yield arm.action(anchor + turn @ (grasp - anchor), turn @ mat, CLOSE, speed=0.3)
    # pull the door open along its arc around the hinge, keeping the lever turned
    hinge_id = mujoco.mj_name2id(arm.m, mujoco.mjtObj.mjOBJ_JOINT, hinge)
    pivot, start = arm.d.xanchor[hinge_id].copy(), arm.joint_qpos(hinge)
    grasp, held = anchor + turn @ (grasp - anchor), turn @ mat
    for _ in range(150):
        opened = arm.joint_qpos(hinge) - start
        if opened > 0.35:
            break
        arm.phase = "pull"
        swing = rot_z(opened + 0.12)
        yield arm.action(pivot + swing @ (grasp - pivot), swing @ held, CLOSE, speed=0.4)


SCRIPTS: dict[str, Callable[[Arm], Iterator[np.ndarray]]] = {
    "Lift": lift_script,
    "Stack": stack_script,
    "PickPlaceCan": can_script,
    "NutAssemblySquare": nut_script,
    "Door": door_script,
}


class Expert:
    """Runs a task's script; after the script ends it holds still with the gripper as it was."""

    def __init__(self, env, script: Callable[[Arm], Iterator[np.ndarray]]):
        self.env, self.script = env, script
        self.arm: Arm | None = None
        self._gen: Iterator[np.ndarray] | None = None
        self._last = np.zeros(7, dtype=np.float32)

    def reset(self) -> None:
        """Plan from the freshly reset scene (call after env.reset)."""
        self.arm = Arm(self.env)
        self._gen = self.script(self.arm)

    @property
    def phase(self) -> str:
        return self.arm.phase if self.arm else ""

    def act(self, obs=None) -> np.ndarray:
        if self._gen is None:
            raise RuntimeError("call expert.reset() after env.reset() before act()")
        try:
            self._last = next(self._gen)
        except StopIteration:
            self.arm.phase = "done"
            self._last = np.r_[np.zeros(6), self._last[6]].astype(np.float32)
        return self._last


def make_expert(env) -> Expert:
    name = env.spec.env_name  # variants of a task (LiftD1) share its script
    if name not in SCRIPTS:
        raise ValueError(f"no scripted expert for task {name!r}; tasks with experts: {', '.join(SCRIPTS)}")
    return Expert(env, SCRIPTS[name])
