"""How one discrete action is executed in the MuJoCo scene.

Both executors take a relative move in the drone's heading frame
(``forward/left/up`` metres and a yaw change in degrees, see
:func:`action_deltas`) and report whether the drone crashed (any MuJoCo
contact involving the drone) or passed within ``reach_radius`` of the goal
point during the move.

* :class:`KinematicExecutor` (``execution="kinematic"``): moves the drone's
  free joint straight to the new pose, like a Tello executing "forward 25"
  onboard. The straight path is swept in small sub-steps (<= 4 cm, <= 5 deg)
  with ``mj_kinematics`` + ``mj_collision``; at the first colliding sub-step
  the move stops at the last free pose and the action is a crash. Optional
  Gaussian pose noise perturbs the executed move. Roll and pitch stay zero.
* :class:`PhysicsExecutor` (``execution="physics"``): the four thrust
  actuators are driven by a cascaded PID (:class:`CascadedPID`: position and
  velocity -> desired acceleration -> roll/pitch set-point and collective
  thrust -> body torques -> rotor mixer) that tracks a minimum-jerk reference
  from the current pose to the set-point for ``action_duration`` seconds
  (the reference reaches the set-point at half of it, then holds). The camera sees
  the resulting tilt; the velocity at the end of one action carries over to
  the next.

Example:
    >>> from torchrl_causal.envs.control import action_deltas
    >>> action_deltas(0.25, 15.0)[0], action_deltas(0.25, 15.0)[6]
    ((0.25, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 15.0))
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from ..schema import ACTION_NAMES
from .scene import DRONE_MASS, ROTOR_SPIN, ROTOR_TORQUE_COEF, ROTOR_XY, ROTOR_MAX_THRUST

__all__ = [
    "action_deltas",
    "StepOutcome",
    "KinematicExecutor",
    "PhysicsExecutor",
    "CascadedPID",
    "yaw_of",
]

GRAVITY = 9.81


def action_deltas(step_m: float, turn_deg: float) -> tuple[tuple[float, float, float, float], ...]:
    """Per action ``(forward, left, up, yaw_deg)``, in :data:`~torchrl_causal.schema.ACTION_NAMES` order.

    Example:
        >>> len(action_deltas(0.25, 15.0))
        8
    """
    s, t = float(step_m), float(turn_deg)
    table = {
        "forward": (s, 0.0, 0.0, 0.0),
        "backward": (-s, 0.0, 0.0, 0.0),
        "left": (0.0, s, 0.0, 0.0),
        "right": (0.0, -s, 0.0, 0.0),
        "ascend": (0.0, 0.0, s, 0.0),
        "descend": (0.0, 0.0, -s, 0.0),
        "turn_left": (0.0, 0.0, 0.0, t),
        "turn_right": (0.0, 0.0, 0.0, -t),
    }
    return tuple(table[n] for n in ACTION_NAMES)


def yaw_of(quat) -> float:
    """Heading (rad) of a ``(w, x, y, z)`` quaternion."""
    w, x, y, z = quat
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass
class StepOutcome:
    """Result of executing one action."""

    crashed: bool
    reached: bool
    physics_s: float = 0.0


class _Executor:
    def __init__(self, model, data, qpos_adr: int, qvel_adr: int):
        self.model = model
        self.data = data
        self.qa = qpos_adr
        self.va = qvel_adr

    def pose(self) -> tuple[float, float, float, float]:
        """``(x, y, z, yaw_rad)`` of the drone."""
        x, y, z, qw, qx, qy, qz = self.data.qpos[self.qa : self.qa + 7].tolist()
        return (x, y, z, yaw_of((qw, qx, qy, qz)))

    def set_pose(self, x, y, z, yaw):
        a = self.qa
        q = self.data.qpos
        # element-wise: several times faster than slice assignment from tuples,
        # and the planner calls this hundreds of thousands of times per search
        q[a] = x
        q[a + 1] = y
        q[a + 2] = z
        q[a + 3] = math.cos(yaw / 2)
        q[a + 4] = 0.0
        q[a + 5] = 0.0
        q[a + 6] = math.sin(yaw / 2)

    def reset(self, x, y, z, yaw):
        """Places the drone at rest at the given pose (yaw in radians)."""
        mujoco.mj_resetData(self.model, self.data)
        self.set_pose(x, y, z, yaw)
        self.data.qvel[:] = 0.0
        mujoco.mj_forward(self.model, self.data)

    def in_collision(self) -> bool:
        """Whether the drone currently touches anything (kinematics + collision only)."""
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_collision(self.model, self.data)
        return self.data.ncon > 0


#: The emulated Tello's move imperfections, as :class:`~torchrl_causal.envs.DroneNavEnv`
#: options: 0.05 m of Gaussian noise per moved axis and 3 deg per turn, drawn once per
#: move (``fly_tello.py --noise``, the emulator's ``env_options`` and the training
#: recipe's ``env.noise=tello``).
TELLO_MOVE_NOISE = {"position_noise_std": 0.05, "yaw_noise_std_deg": 3.0}


class KinematicExecutor(_Executor):
    """Sets the new pose directly, sweeping the straight path for collisions.

    Args:
        model: the compiled scene.
        data: its ``MjData``.
        qpos_adr: address of the drone's free joint in ``qpos``.
        qvel_adr: address in ``qvel``.
        position_noise_std: std (m) of Gaussian noise added to each executed
            move, per axis, along the moved axes only.
        yaw_noise_std_deg: std (deg) of noise added to each executed turn.
        max_substep_m: sweep resolution (m).
        max_substep_deg: sweep resolution (deg).

    Example:
        >>> import mujoco, numpy as np
        >>> from torchrl_causal.envs.layouts import thesis_layout
        >>> from torchrl_causal.envs.scene import build_model
        >>> model, ids = build_model(thesis_layout())
        >>> ex = KinematicExecutor(model, mujoco.MjData(model), ids.qpos_adr, ids.qvel_adr)
        >>> ex.reset(0.0, 0.0, 1.0, 0.0)
        >>> out = ex.execute((0.25, 0.0, 0.0, 0.0), np.random.default_rng(0), (2.5, 0, 1), 0.2)
        >>> out.crashed, round(ex.pose()[0], 2)
        (False, 0.25)
    """

    def __init__(
        self,
        model,
        data,
        qpos_adr: int,
        qvel_adr: int,
        position_noise_std: float = 0.0,
        yaw_noise_std_deg: float = 0.0,
        max_substep_m: float = 0.04,
        max_substep_deg: float = 5.0,
    ):
        super().__init__(model, data, qpos_adr, qvel_adr)
        self.position_noise_std = float(position_noise_std)
        self.yaw_noise_std = math.radians(float(yaw_noise_std_deg))
        self.max_substep_m = float(max_substep_m)
        self.max_substep_rad = math.radians(float(max_substep_deg))

    def noisy_delta(self, delta, rng: np.random.Generator) -> tuple:
        """``delta`` with this executor's move noise drawn from ``rng``: Gaussian
        (``position_noise_std``) along the moved axes only, and
        (``yaw_noise_std_deg``) on a turn. Noise-free options return ``delta``.

        Example:
            >>> import numpy as np
            >>> ex = KinematicExecutor(None, None, 0, 0, position_noise_std=0.05)
            >>> d = ex.noisy_delta((0.25, 0.0, 0.0, 0.0), np.random.default_rng(0))
            >>> d[0] != 0.25 and d[1:] == (0.0, 0.0, 0.0)
            True
        """
        fwd, left, up, dyaw_deg = delta
        if self.position_noise_std > 0.0:
            n = rng.normal(0.0, self.position_noise_std, size=3)
            fwd += n[0] if fwd else 0.0
            left += n[1] if left else 0.0
            up += n[2] if up else 0.0
        if self.yaw_noise_std > 0.0 and dyaw_deg:
            dyaw_deg += math.degrees(float(rng.normal(0.0, self.yaw_noise_std)))
        return (float(fwd), float(left), float(up), float(dyaw_deg))

    def execute(self, delta, rng: np.random.Generator | None, goal_point, reach_radius: float,
                check_collisions: bool = True) -> StepOutcome:
        """Executes ``delta = (forward, left, up, yaw_deg)`` from the current pose.

        ``rng``: the move noise is drawn from it (:meth:`noisy_delta`); ``None``
        executes ``delta`` as given (a caller that drew the noise already, e.g.
        the Tello emulator once per command). ``check_collisions=False`` skips
        the swept collision test (the same end pose and reach test otherwise):
        only for a caller that knows the swept volume is free, e.g.
        :class:`~torchrl_causal.envs.ShortestPathPlanner` far from every obstacle.
        """
        if rng is not None:
            delta = self.noisy_delta(delta, rng)
        fwd, left, up, dyaw_deg = delta
        dyaw = math.radians(dyaw_deg)
        x0, y0, z0, yaw0 = self.pose()
        c, s = math.cos(yaw0), math.sin(yaw0)
        dx, dy = c * fwd - s * left, s * fwd + c * left
        dist = math.sqrt(fwd * fwd + left * left + up * up)
        n = max(1, math.ceil(dist / self.max_substep_m), math.ceil(abs(dyaw) / self.max_substep_rad))
        gx, gy, gz = float(goal_point[0]), float(goal_point[1]), float(goal_point[2])
        r2 = reach_radius * reach_radius
        reached = False
        last = (x0, y0, z0, yaw0)
        for k in range(1, n + 1):
            f = k / n
            p = (x0 + f * dx, y0 + f * dy, z0 + f * up, yaw0 + f * dyaw)
            if check_collisions:
                self.set_pose(*p)
                if self.in_collision():
                    self.set_pose(*last)
                    mujoco.mj_kinematics(self.model, self.data)
                    return StepOutcome(crashed=True, reached=False)
            last = p
            if (p[0] - gx) ** 2 + (p[1] - gy) ** 2 + (p[2] - gz) ** 2 <= r2:
                reached = True
        if not check_collisions:
            self.set_pose(*last)
        return StepOutcome(crashed=False, reached=reached)


class CascadedPID:
    """Cascaded PID for a quadrotor on four thrust actuators.

    Outer loop (world frame): position and velocity errors (plus the
    reference's acceleration as feed-forward) give a desired acceleration,
    with a small integral term on altitude. It maps to a collective thrust and
    roll/pitch set-points (small-angle, in the heading frame). Inner loop:
    attitude PD on roll, pitch and yaw gives body torques. A mixer inverts the
    rotor geometry to the four thrusts (clipped to the actuator range).

    Args:
        mass: drone mass (kg).
        inertia: principal inertia ``(Ixx, Iyy, Izz)`` (kg m^2).
        pos_omega: outer-loop natural frequency (rad/s).
        att_omega: attitude-loop natural frequency (rad/s).
        yaw_omega: yaw-loop natural frequency (rad/s).
        damping: damping ratio of every loop.
        max_tilt_deg: roll/pitch set-point limit.

    Example:
        >>> pid = CascadedPID(0.5, (0.003, 0.003, 0.005))
        >>> f = pid.thrusts((0, 0, 1), (0, 0, 0), (0, 0, 0), 0.0, (0, 0, 1), (0, 0, 0), (0, 0, 0), 0.0, 0.0, 0.01)
        >>> round(sum(f), 3) == round(0.5 * 9.81, 3)
        True
    """

    def __init__(
        self,
        mass: float,
        inertia,
        pos_omega: float = 6.0,
        att_omega: float = 30.0,
        yaw_omega: float = 12.0,
        damping: float = 0.8,
        max_tilt_deg: float = 30.0,
        max_thrust: float = ROTOR_MAX_THRUST,
    ):
        self.mass = float(mass)
        self.inertia = tuple(float(v) for v in inertia)
        self.kp = pos_omega**2
        self.kd = 2 * damping * pos_omega
        self.ki_z = 0.5 * pos_omega
        self.kp_att = att_omega**2
        self.kd_att = 2 * damping * att_omega
        self.kp_yaw = yaw_omega**2
        self.kd_yaw = 2 * damping * yaw_omega
        self.max_tilt = math.radians(max_tilt_deg)
        self.max_thrust = float(max_thrust)
        # rows: total thrust, tau_x, tau_y, tau_z
        A = np.array(
            [
                [1.0] * 4,
                [y for _, y in ROTOR_XY],
                [-x for x, _ in ROTOR_XY],
                [ROTOR_TORQUE_COEF * s for s in ROTOR_SPIN],
            ]
        )
        self._mix = np.linalg.inv(A).tolist()
        self.reset()

    def reset(self):
        """Clears the integral state."""
        self._iz = 0.0

    def thrusts(self, p, v, euler, yaw, p_ref, v_ref, a_ref, yaw_ref, yaw_rate_ref, dt, omega=(0.0, 0.0, 0.0)):
        """Four rotor thrusts (N) for the current state and reference.

        ``euler`` is ``(roll, pitch, yaw)`` (rad), ``omega`` the body angular
        velocity (rad/s).
        """
        ex, ey, ez = p_ref[0] - p[0], p_ref[1] - p[1], p_ref[2] - p[2]
        self._iz = max(-0.5, min(0.5, self._iz + ez * dt))
        ax = self.kp * ex + self.kd * (v_ref[0] - v[0]) + a_ref[0]
        ay = self.kp * ey + self.kd * (v_ref[1] - v[1]) + a_ref[1]
        az = self.kp * ez + self.kd * (v_ref[2] - v[2]) + a_ref[2] + self.ki_z * self._iz
        az = max(-0.6 * GRAVITY, min(0.8 * GRAVITY, az))
        c, s = math.cos(yaw), math.sin(yaw)
        a_fwd = c * ax + s * ay
        a_left = -s * ax + c * ay
        lim = self.max_tilt
        pitch_d = max(-lim, min(lim, math.atan2(a_fwd, GRAVITY + az)))
        roll_d = max(-lim, min(lim, -math.atan2(a_left, GRAVITY + az)))
        roll, pitch, _ = euler
        tilt = max(0.5, math.cos(roll) * math.cos(pitch))
        T = self.mass * (GRAVITY + az) / tilt
        Ix, Iy, Iz = self.inertia
        wx, wy, wz = omega
        tx = Ix * (self.kp_att * (roll_d - roll) - self.kd_att * wx)
        ty = Iy * (self.kp_att * (pitch_d - pitch) - self.kd_att * wy)
        tz = Iz * (self.kp_yaw * _wrap(yaw_ref - yaw) + self.kd_yaw * (yaw_rate_ref - wz))
        u = (T, tx, ty, tz)
        m = self._mix
        hi = self.max_thrust
        return [
            max(0.0, min(hi, m[i][0] * u[0] + m[i][1] * u[1] + m[i][2] * u[2] + m[i][3] * u[3]))
            for i in range(4)
        ]


def _min_jerk(t: float) -> tuple[float, float, float]:
    """Position, velocity, acceleration profiles of a unit minimum-jerk move, ``t`` in [0, 1]."""
    if t >= 1.0:
        return 1.0, 0.0, 0.0
    t2 = t * t
    t3 = t2 * t
    return (
        10 * t3 - 15 * t2 * t2 + 6 * t3 * t2,
        30 * t2 - 60 * t3 + 30 * t2 * t2,
        60 * t - 180 * t2 + 120 * t3,
    )


class PhysicsExecutor(_Executor):
    """Flies the move with the thrust actuators under a :class:`CascadedPID`.

    Args:
        model: the compiled scene.
        data: its ``MjData``.
        qpos_adr: address of the drone's free joint in ``qpos``.
        qvel_adr: address in ``qvel``.
        drone_body: body id of the drone (for its inertia).
        action_duration: simulated seconds per action.
        control_every: physics steps per controller update.
        move_fraction: fraction of ``action_duration`` the reference takes to
            reach the set-point.

    Example:
        >>> import mujoco, numpy as np
        >>> from torchrl_causal.envs.layouts import thesis_layout
        >>> from torchrl_causal.envs.scene import build_model
        >>> model, ids = build_model(thesis_layout())
        >>> ex = PhysicsExecutor(model, mujoco.MjData(model), ids.qpos_adr, ids.qvel_adr, ids.drone_body)
        >>> ex.reset(0.0, 0.0, 1.0, 0.0)
        >>> out = ex.execute((0.0, 0.0, 0.25, 0.0), np.random.default_rng(0), (2.5, 0, 1), 0.2)
        >>> out.crashed, abs(ex.pose()[2] - 1.25) < 0.03
        (False, True)
    """

    def __init__(
        self,
        model,
        data,
        qpos_adr: int,
        qvel_adr: int,
        drone_body: int,
        action_duration: float = 1.0,
        control_every: int = 1,
        move_fraction: float = 0.5,
    ):
        super().__init__(model, data, qpos_adr, qvel_adr)
        inertia = tuple(float(v) for v in model.body_inertia[drone_body])
        mass = float(model.body_subtreemass[drone_body]) or DRONE_MASS
        self.pid = CascadedPID(mass, inertia)
        self.control_every = int(control_every)
        self.dt = float(model.opt.timestep) * self.control_every
        self.n_ticks = max(1, int(round(action_duration / self.dt)))
        self.move_ticks = max(1, int(round(move_fraction * self.n_ticks)))
        self._hover = [mass * GRAVITY / 4.0] * 4

    def reset(self, x, y, z, yaw):
        super().reset(x, y, z, yaw)
        self.pid.reset()
        self.data.ctrl[:] = self._hover
        self._sp = (float(x), float(y), float(z), float(yaw))

    def execute(self, delta, rng: np.random.Generator, goal_point, reach_radius: float) -> StepOutcome:
        """Flies ``delta = (forward, left, up, yaw_deg)`` from the current pose."""
        m, d = self.model, self.data
        fwd, left, up, dyaw_deg = delta
        # moves are relative to the previous set-point (not the measured pose),
        # so tracking errors do not accumulate over an episode
        x0, y0, z0, yaw0 = self._sp
        c, s = math.cos(yaw0), math.sin(yaw0)
        dx, dy, dz = c * fwd - s * left, s * fwd + c * left, up
        dyaw = math.radians(dyaw_deg)
        T = self.move_ticks * self.dt
        gx, gy, gz = float(goal_point[0]), float(goal_point[1]), float(goal_point[2])
        r2 = reach_radius * reach_radius
        qa, va = self.qa, self.va
        qpos, qvel = d.qpos, d.qvel
        pid = self.pid
        reached = False
        self._sp = (x0 + dx, y0 + dy, z0 + dz, yaw0 + dyaw)
        for k in range(1, self.n_ticks + 1):
            sp, sv, sa = _min_jerk(k / self.move_ticks)
            sv /= T
            sa /= T * T
            q = qpos[qa : qa + 7].tolist()
            v = qvel[va : va + 6].tolist()
            w, qx, qy, qz = q[3:7]
            roll = math.atan2(2.0 * (w * qx + qy * qz), 1.0 - 2.0 * (qx * qx + qy * qy))
            pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * qy - qz * qx))))
            yaw = math.atan2(2.0 * (w * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
            f = pid.thrusts(
                q, v, (roll, pitch, yaw), yaw,
                (x0 + sp * dx, y0 + sp * dy, z0 + sp * dz),
                (sv * dx, sv * dy, sv * dz),
                (sa * dx, sa * dy, sa * dz),
                yaw0 + sp * dyaw, sv * dyaw, self.dt, omega=v[3:6],
            )
            d.ctrl[:] = f
            mujoco.mj_step(m, d, self.control_every)
            if d.ncon > 0:
                return StepOutcome(crashed=True, reached=False)
            px, py, pz = qpos[qa], qpos[qa + 1], qpos[qa + 2]
            if (px - gx) ** 2 + (py - gy) ** 2 + (pz - gz) ** 2 <= r2:
                reached = True
        if self.in_collision():
            return StepOutcome(crashed=True, reached=False)
        return StepOutcome(crashed=False, reached=reached)
