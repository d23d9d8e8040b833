"""The simulated physical world: wheel, driver's arm, sensors.

Bodies (angles in rad, positive counter-clockwise seen by the driver):

    I_w θ''  = T_motor − T_d + T_wheel_extra                  (wheel, physical inertia)
    T_d      = k_c (θ − θ_h) + b_c (θ' − θ_h')               (torque the wheel exerts on the hands)
    I_i θ_h'' = T_d − b_i θ_h' − k_i θ_h + T_hand_extra        (arm, intrinsic dynamics)

so that θ/T_d = 1/(b_c s + k_c) + 1/(I_i s² + b_i s + k_i), the paper's admittance.
T_hand_extra carries the remnant and the torques of added mechanisms (reflexes, stiffening,
time-varying parameters); T_wheel_extra carries wheel-side mechanisms (dry friction, the
gravity torque of an unbalanced wheel).

Time-varying trials (a :class:`hardware.sim.schedule.BehaviourSchedule`) move the arm parameters
sample by sample through the same per-sample deltas (``dpar``) relative to the trial's base
behaviour, and the grip force's mean with them; the true values are returned as extra channels
(:data:`TRUTH_CHANNELS`).

The linear part is discretised exactly (zero-order hold, matrix exponential); the extra
torques are held over one sample. One compiled kernel, ``_advance``, runs both a whole block
(batch: the loop's command, rendering and safety limits, computed inside) and a single sample
(live: the command comes from outside, through the drive interface); both draw noise from the
same seeded 1-second blocks, so the two paths give the same signals.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Protocol

import numpy as np
from numba import njit
from scipy.linalg import expm

from steerlab.hardware.safety import SafetyLimits, inputs_finite, loop_command
from steerlab.hardware.sim.filters import first_order_lfilter
from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.hardware.sim.physiology import ConditionBehaviour
from steerlab.hardware.sim.schedule import ARM_COLUMNS, BehaviourSchedule
from steerlab.protocols.protocol import VirtualWheel

# Indices into the kernel's parameter vector.
P_KSW, P_BSW, P_QANG, P_TRES, P_KC, P_BC = 0, 1, 2, 3, 4, 5
P_K3, P_COUL, P_COUL_EPS, P_ACT_ALPHA = 6, 7, 8, 9
P_RKP, P_RKV, P_RW, P_RZ, P_DT, P_HAS_DPAR = 10, 11, 12, 13, 14, 15
P_DPAR_HALF = 16  # dt/2 for scheduled trials (see World._scheduled_deltas), else 0
P_GRAV = 17  # wheel imbalance m·g·r, N·m (torque −m·g·r·sin θ on the wheel)
# Forms of the mechanism families (hardware.sim.mechanisms); all 0 in their default forms.
P_KI = 18  # the trial's intrinsic stiffness k_i (the exponential and piecewise stiffening)
P_STIFF_FORM, P_RISE, P_THETA_S = 19, 20, 21  # 1 exponential (θ_0), 2 piecewise (θ_s)
P_STRIB, P_STRIB_V, P_VISC = 22, 23, 24  # F_s − F_c, v_s; viscous b_v
P_LAG_FORM = 25  # 0 first order (P_ACT_ALPHA), 1 second order (P_LAG2..+6), 2 delay
P_LAG2 = 26  # Φ00, Φ01, Φ10, Φ11, Γ0, Γ1 of the second-order lag
P_LAG_N, P_LAG_FRAC = 32, 33  # the delay form: whole samples, fraction
# The torque applied over a sample: the lag's mean over it, from its state at the sample's
# start and the held command. First order: cmd + m (T − cmd), in P_LAG_MEAN alone (0: no lag);
# second order: m0 T + m1 T' + m2 cmd.
P_LAG_MEAN = 34
N_PARAMS = 37
# Indices into the kernel's state vector (beyond the 4 mechanical states).
S_TM, S_RA, S_RAD, S_RPOS, S_SPOS, S_CMD = 4, 5, 6, 7, 8, 9
S_NONFINITE = 10  # cycles whose command had a non-finite input (zero torque applied instead)
S_TMD = 11  # the second-order lag's rate of torque
S_CPOS = 12  # write position in the ring of past commands (the lag's delay form)
N_STATE = 13  # the ring of past commands, when there is one, follows at st[N_STATE:]


@dataclass(frozen=True)
class SensorSpec:
    """Sensor resolution and noise of the simulated rig."""

    encoder_counts_per_rev: int = 131072  # 17-bit absolute encoder
    velocity_noise_sd: float = 0.002  # rad/s, the drive's velocity estimate
    torque_noise_sd: float = 0.02  # N·m, column torque sensor
    torque_resolution: float = 0.001  # N·m per LSB
    glove_rate_hz: float = 100.0
    glove_noise_sd_n: float = 0.8  # N per hand


#: Ideal sensors: no quantisation, no noise (the glove still samples at its rate). For checks
#: against analytic responses and for the diagnosis's noise-free replays.
NOISELESS_SENSORS = SensorSpec(
    encoder_counts_per_rev=0,
    velocity_noise_sd=0.0,
    torque_noise_sd=0.0,
    torque_resolution=0.0,
    glove_noise_sd_n=0.0,
)


@dataclass(frozen=True)
class WorldConfig:
    fs_hz: float = 1000.0
    wheel_inertia_kgm2: float = 0.3  # physical; the loop renders Table 1's b and k
    sensors: SensorSpec = field(default_factory=SensorSpec)
    mechanisms: Mechanisms = field(default_factory=Mechanisms)
    grip_corner_hz: float = 0.15  # bandwidth of the slow grip-force fluctuation
    # How the wheel's damping and spring act: "sampled" (Steerlab's rig: the loop renders them
    # from the angle and velocity it reads, through the held motor command) or "continuous"
    # (a physical spring and damper, or a drive rendering them in its own fast loop: part of
    # the continuous dynamics, and the loop commands the perturbation alone).
    wheel_rendering: str = "sampled"

    def to_dict(self) -> dict:
        return asdict(self)


OUTPUTS = (
    "wheel_angle_rad",
    "wheel_velocity_rad_s",
    "driver_torque_Nm",
    "motor_command_Nm",
    "motor_torque_Nm",
)
# The simulated driver's true admittance parameters and grip mean, per sample: time-varying
# trials only (the parameters that act from this sample to the next).
TRUTH_CHANNELS = (
    "true_b_i_Nms_per_rad",
    "true_k_i_Nm_per_rad",
    "true_b_c_Nms_per_rad",
    "true_k_c_Nm_per_rad",
    "true_grip_mean_N",
)


def wheel_split(
    wheel: VirtualWheel, rendering: str
) -> tuple[tuple[float, float], tuple[float, float]]:
    """The wheel's (damping, stiffness) as ((physical), (rendered by the loop)) for a
    ``WorldConfig.wheel_rendering``: all physical for "continuous", all rendered otherwise."""
    bk = (float(wheel.damping_nms_per_rad), float(wheel.stiffness_nm_per_rad))
    return (bk, (0.0, 0.0)) if rendering == "continuous" else ((0.0, 0.0), bk)


def discretise(
    I_w: float, arm, dt: float, b_w: float = 0.0, k_w: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH discretisation of the wheel–contact–arm system; inputs [T_m, T_hand, T_wheel].
    ``b_w``, ``k_w``: the wheel's physical damping and spring (0: rendered by the loop)."""
    kc, bc, Ii, bi, ki = arm.k_c, arm.b_c, arm.I_i, arm.b_i, arm.k_i
    A = np.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [-(kc + k_w) / I_w, -(bc + b_w) / I_w, kc / I_w, bc / I_w],
            [0.0, 0.0, 0.0, 1.0],
            [kc / Ii, bc / Ii, -(kc + ki) / Ii, -(bc + bi) / Ii],
        ]
    )
    B = np.array(
        [
            [0.0, 0.0, 0.0],
            [1.0 / I_w, 0.0, 1.0 / I_w],
            [0.0, 0.0, 0.0],
            [0.0, 1.0 / Ii, 0.0],
        ]
    )
    M = np.zeros((7, 7))
    M[:4, :4] = A * dt
    M[:4, 4:] = B * dt
    E = expm(M)
    return E[:4, :4].copy(), E[:4, 4:].copy()


@njit(cache=True)
def _sensors(th, om, thh, omh, st, ring_s, q, tres, kc, bc, vel_noise_k, td_noise_k, dkc, dbc):
    """(angle, velocity, driver torque) as the sensors report them for the state (θ, θ', θ_h,
    θ_h'), given the angle's quantum ``q``, the torque's resolution ``tres`` and the contact's
    ``kc``, ``bc`` (0: none); ``dkc``, ``dbc``: this sample's contact deltas (dpar), so the
    column sensor reads the contact torque the arm actually exerts when they vary."""
    ang = np.round(th / q) * q if q > 0.0 else th
    vel = om + vel_noise_k
    if ring_s.shape[0] > 0:
        td = ring_s[int(st[S_SPOS])]
    else:
        td = kc * (th - thh) + bc * (om - omh)
        td = td + dkc * (th - thh) + dbc * (om - omh)
    td = td + td_noise_k
    if tres > 0.0:
        td = np.round(td / tres) * tres
    return ang, vel, td


@njit(cache=True)
def _measure(x, st, p, ring_s, vel_noise_k, td_noise_k, dkc=0.0, dbc=0.0):
    """(angle, velocity, driver torque) as the sensors report them for the current state
    (:func:`_sensors` with the parameter vector's sensors and contact)."""
    return _sensors(
        x[0], x[1], x[2], x[3], st, ring_s, p[P_QANG], p[P_TRES], p[P_KC], p[P_BC],
        vel_noise_k, td_noise_k, dkc, dbc,
    )  # fmt: skip


@njit(cache=True)
def _stiffening(form, rise, theta_s, th):
    """The stiffening's torque beyond k_i θ, per unit k_i (hardware.sim.mechanisms)."""
    if form == 1.0:  # θ_0 sinh(θ/θ_0) − θ; its series where the difference cancels
        x = th / theta_s
        if abs(x) < 1e-2:
            x2 = x * x
            return theta_s * x * x2 * (1.0 / 6.0 + x2 / 120.0)
        return theta_s * np.sinh(x) - th
    excess = abs(th) - theta_s
    if excess <= 0.0:
        return 0.0
    return rise * excess if th > 0.0 else -rise * excess


@njit(cache=True)
def _tanh(z):
    """tanh(z) from one exponential, within 3 ulp of libm's (which took 40 % of the kernel's time
    on a trial with dry friction; ``exp`` is an LLVM intrinsic, ``tanh`` a library call); libm's
    itself below |z| = 0.5, where 1 − e^{−2|z|} would lose digits."""
    a = abs(z)
    if not a >= 0.5:  # (NaN too: libm's NaN, not the formula's)
        return np.tanh(z)
    e = np.exp(-2.0 * a)
    t = (1.0 - e) / (1.0 + e)
    return t if z > 0.0 else -t


@njit(cache=True)
def _row(Ad, Bd, a, th, om, thh, omh, applied, h, w):
    """Row ``a`` of the discretised linear part's update: Ad x + Bd u, x = (θ, θ', θ_h, θ_h'),
    u = (applied motor torque, hand-side torque, wheel-side torque)."""
    acc = 0.0
    acc += Ad[a, 0] * th
    acc += Ad[a, 1] * om
    acc += Ad[a, 2] * thh
    acc += Ad[a, 3] * omh
    acc += Bd[a, 0] * applied
    acc += Bd[a, 1] * h
    acc += Bd[a, 2] * w
    return acc


@njit(cache=True)
def _delayed_command(st, p, cmd):
    """The command of ``P_LAG_N`` (+ ``P_LAG_FRAC``) samples ago, from the ring at
    st[N_STATE:], after storing this cycle's ``cmd`` there."""
    ring = st[N_STATE:]
    nr = ring.shape[0]
    pos = int(st[S_CPOS])
    ring[pos] = cmd
    st[S_CPOS] = (pos + 1) % nr
    n = int(p[P_LAG_N])
    a = ring[(pos - n) % nr]
    f = p[P_LAG_FRAC]
    if f == 0.0:
        return a
    return (1.0 - f) * a + f * ring[(pos - n - 1) % nr]


@njit(cache=True)
def _advance(
    x,
    st,
    p,
    Ad,
    Bd,
    ring_r,
    ring_s,
    tp,
    cmd_ext,
    internal,
    hand_ext,
    vel_noise,
    td_noise,
    dpar,
    out,
    i0,
    n,
    safety,
):
    """Advance n samples from noise index i0; write outputs (len(OUTPUTS) rows) at [:, 0..n).

    The parameters and the mechanical state are read into locals once: the compiler cannot
    tell that the writes to ``st``, the rings and ``out`` leave ``p`` and ``x`` alone, and
    re-read them every sample otherwise (40 % of a linear trial's time)."""
    has_dpar = p[P_HAS_DPAR] != 0.0
    q, tres, kc, bc = p[P_QANG], p[P_TRES], p[P_KC], p[P_BC]
    ksw, bsw = p[P_KSW], p[P_BSW]
    lag_form, alpha = p[P_LAG_FORM], p[P_ACT_ALPHA]
    m0, m1, m2 = p[P_LAG_MEAN], p[P_LAG_MEAN + 1], p[P_LAG_MEAN + 2]
    f00, f01, f10, f11, g0, g1 = (
        p[P_LAG2], p[P_LAG2 + 1], p[P_LAG2 + 2], p[P_LAG2 + 3], p[P_LAG2 + 4], p[P_LAG2 + 5]
    )  # fmt: skip
    k3, stiff_form, rise, theta_s, k_i = (
        p[P_K3], p[P_STIFF_FORM], p[P_RISE], p[P_THETA_S], p[P_KI]
    )  # fmt: skip
    half = p[P_DPAR_HALF]
    coul, coul_eps, strib, strib_v = p[P_COUL], p[P_COUL_EPS], p[P_STRIB], p[P_STRIB_V]
    visc, grav = p[P_VISC], p[P_GRAV]
    rkp, rkv, wa, za, dt = p[P_RKP], p[P_RKV], p[P_RW], p[P_RZ], p[P_DT]
    reflex = rkp != 0.0 or rkv != 0.0
    nr, ns = ring_r.shape[0], ring_s.shape[0]
    th, om, thh, omh = x[0], x[1], x[2], x[3]
    for j in range(n):
        k = i0 + j
        dkc = dpar[k, 3] if has_dpar else 0.0
        dbc = dpar[k, 2] if has_dpar else 0.0
        ang, vel, tdm = _sensors(
            th, om, thh, omh, st, ring_s, q, tres, kc, bc, vel_noise[k], td_noise[k], dkc, dbc
        )
        # What the drive reports as torque actual at this cycle: the lag's torque now (the
        # delay form's: last cycle's applied torque).
        tm_reported = st[S_TM]
        if internal:
            cmd = loop_command(tp[j], ang, vel, st[S_CMD], ksw, bsw, safety)
            if cmd == 0.0 and not inputs_finite(tp[j], ang, vel, st[S_CMD], ksw, bsw):
                st[S_NONFINITE] += 1
        else:
            cmd = cmd_ext[j]
            if not np.isfinite(cmd):  # no non-finite value reaches the motor
                cmd = 0.0
                st[S_NONFINITE] += 1
        st[S_CMD] = cmd
        if lag_form == 0.0:
            applied = cmd + m0 * (st[S_TM] - cmd)
            st[S_TM] += alpha * (cmd - st[S_TM])
        elif lag_form == 1.0:
            y, yd = st[S_TM], st[S_TMD]
            applied = m0 * y + m1 * yd + m2 * cmd
            st[S_TM] = f00 * y + f01 * yd + g0 * cmd
            st[S_TMD] = f10 * y + f11 * yd + g1 * cmd
        else:
            st[S_TM] = _delayed_command(st, p, cmd)
            applied = st[S_TM]
        contact = kc * (th - thh) + bc * (om - omh)
        # Torques of added mechanisms, held over the sample.
        h = hand_ext[k]
        w = 0.0
        if k3 != 0.0:
            h -= k3 * thh * thh * thh
        if stiff_form != 0.0:
            ki = k_i + dpar[k, 1] if has_dpar else k_i
            h -= ki * _stiffening(stiff_form, rise, theta_s, thh)
        if has_dpar:
            # The delta torques are held over the sample, i.e. half a sample late: a spring Δk
            # then acts as Δk − s·Δk·dt/2, a negative damping. Scheduled trials add Δk·dt/2 to
            # the matching damping (P_DPAR_HALF), so the arm moves with the logged parameters.
            dcon_true = dkc * (th - thh) + dbc * (om - omh)
            dcon = dcon_true + half * dkc * (om - omh)
            h += dcon - (dpar[k, 0] + half * dpar[k, 1]) * omh - dpar[k, 1] * thh
            w -= dcon
            contact += dcon_true
        if coul != 0.0:
            if strib != 0.0:
                v = om / strib_v
                w -= (coul + strib * np.exp(-v * v)) * _tanh(om / coul_eps)
            else:
                w -= coul * _tanh(om / coul_eps)
        if visc != 0.0:
            w -= visc * om
        if grav != 0.0:
            w -= grav * np.sin(th)
        if reflex:
            drive = rkp * thh + rkv * omh
            if nr > 0:
                pos = int(st[S_RPOS])
                delayed = ring_r[pos]
                ring_r[pos] = drive
                st[S_RPOS] = (pos + 1) % nr
            else:
                delayed = drive
            # Activation dynamics: 2nd-order low-pass, semi-implicit Euler.
            st[S_RAD] += dt * (wa * wa * (-delayed - st[S_RA]) - 2.0 * za * wa * st[S_RAD])
            st[S_RA] += dt * st[S_RAD]
            h += st[S_RA]
        if ns > 0:
            pos = int(st[S_SPOS])
            ring_s[pos] = contact
            st[S_SPOS] = (pos + 1) % ns
        th, om, thh, omh = (
            _row(Ad, Bd, 0, th, om, thh, omh, applied, h, w),
            _row(Ad, Bd, 1, th, om, thh, omh, applied, h, w),
            _row(Ad, Bd, 2, th, om, thh, omh, applied, h, w),
            _row(Ad, Bd, 3, th, om, thh, omh, applied, h, w),
        )
        out[0, j] = ang
        out[1, j] = vel
        out[2, j] = tdm
        out[3, j] = cmd
        out[4, j] = tm_reported
    x[0], x[1], x[2], x[3] = th, om, thh, omh


class NoiseSource(Protocol):
    """What a world draws its exogenous signals from, a block of ``block`` samples at a time
    (:class:`NoiseBlocks`; the diagnosis replays recorded ones)."""

    block: int

    def next_block(self) -> dict[str, np.ndarray]: ...


class NoiseBlocks:
    """Seeded exogenous signals, produced in 1-second blocks with filter states carried over.

    Drawing block by block makes the stream independent of how callers slice it.
    """

    def __init__(
        self,
        cfg: WorldConfig,
        behaviour: ConditionBehaviour,
        left_share: float,
        seed,
        schedule: BehaviourSchedule | None = None,
    ):
        self.cfg, self.b, self.left_share = cfg, behaviour, left_share
        # No random draws of its own: a schedule leaves the noise stream as it is.
        self.schedule = None if schedule is None else schedule.response(cfg.fs_hz)
        self.rng = np.random.default_rng(seed)
        self.block = int(round(cfg.fs_hz))
        fs = cfg.fs_hz
        self.a_rem = np.exp(-2 * np.pi * behaviour.remnant_corner_hz / fs)
        self.a_grip = np.exp(-2 * np.pi * cfg.grip_corner_hz / fs)
        self.zi_rem = np.zeros(1)
        # Start the grip fluctuation in its stationary distribution.
        self.zi_grip = np.array([self.rng.standard_normal() * self.a_grip])
        self.glove_every = max(1, int(round(fs / cfg.sensors.glove_rate_hz)))
        self.glove_phase = 0
        self.glove_hold: tuple[float, float] | None = None  # the last glove frame (left, right)

    def _ar1(self, a: float, e: np.ndarray, zi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # y[k] = a y[k−1] + sqrt(1−a²) e[k]: unit variance when stationary.
        y, zf = first_order_lfilter(np.sqrt(1 - a * a), -a, e, zi[0])
        return y, zf

    def next_block(self) -> dict[str, np.ndarray]:
        n, s, b = self.block, self.cfg.sensors, self.b
        e = self.rng.standard_normal((5, n))
        rem, self.zi_rem = self._ar1(self.a_rem, e[0], self.zi_rem)
        g, self.zi_grip = self._ar1(self.a_grip, e[1], self.zi_grip)
        tv = None if self.schedule is None else self.schedule.next_block(n)
        grip_mean: float | np.ndarray  # per sample when the driver is scheduled
        grip_sd: float | np.ndarray
        remnant_sd: float | np.ndarray
        if tv is None:
            grip_mean, grip_sd, remnant_sd = b.grip_mean_n, b.grip_sd_n, b.remnant_sd_nm
        else:
            grip_mean, grip_sd, remnant_sd = (
                tv["grip_mean_true_N"],
                tv["grip_sd_N"],
                tv["remnant_sd_Nm"],
            )
        grip_true = np.maximum(grip_mean + grip_sd * g, 0.0)
        # The glove unit samples both hands at its own rate; the loop holds the latest frame.
        left = grip_true * self.left_share + s.glove_noise_sd_n * e[2]
        right = grip_true * (1 - self.left_share) + s.glove_noise_sd_n * e[3]
        idx = np.arange(n) + self.glove_phase
        frame_start = (idx % self.glove_every) == 0
        hold_left, hold_right = np.empty(n), np.empty(n)
        last = self.glove_hold if self.glove_hold is not None else (left[0], right[0])
        starts = np.flatnonzero(frame_start)
        sel = np.maximum.accumulate(np.where(frame_start, np.arange(n), -1))
        has = sel >= 0
        hold_left[has], hold_right[has] = left[sel[has]], right[sel[has]]
        hold_left[~has], hold_right[~has] = last
        if len(starts):
            self.glove_hold = (hold_left[-1], hold_right[-1])
        self.glove_phase = (self.glove_phase + n) % self.glove_every
        out = {
            "remnant_Nm": remnant_sd * rem,
            "velocity_noise": s.velocity_noise_sd * e[4],
            "torque_noise": s.torque_noise_sd * self.rng.standard_normal(n),
            "grip_true_N": grip_true,
            "grip_force_left_N": np.maximum(hold_left, 0.0),
            "grip_force_right_N": np.maximum(hold_right, 0.0),
        }
        if tv is not None:
            out["true_arm"] = tv["true_arm"]
            out["grip_mean_true_N"] = tv["grip_mean_true_N"]
        return out


class World:
    """Wheel + simulated driver + sensors for one trial at a time.

    ``run(tp)`` advances a block with the loop's rendering computed inside (batch);
    ``read()``/``step(cmd)`` advance one sample with the command from outside (live).
    """

    def __init__(
        self,
        cfg: WorldConfig | None = None,
        wheel: VirtualWheel | None = None,
        safety: SafetyLimits | None = None,
    ):
        self.cfg = cfg or WorldConfig()
        self.wheel = wheel or VirtualWheel()
        self.safety = safety or SafetyLimits()
        self._trial = False

    # -- trial set-up -------------------------------------------------------------------
    @property
    def _physical(self) -> tuple[float, float]:
        """The wheel's physical (b, k) for :func:`discretise`: zero where the loop renders them."""
        return wheel_split(self.wheel, self.cfg.wheel_rendering)[0]

    def begin_trial(
        self,
        behaviour: ConditionBehaviour,
        left_share: float,
        seed,
        schedule: BehaviourSchedule | None = None,
    ) -> None:
        """``behaviour`` is the trial's base (for a time-varying trial: its first segment's)."""
        cfg, s, m = self.cfg, self.cfg.sensors, self.cfg.mechanisms
        self.behaviour = behaviour
        dt = 1.0 / cfg.fs_hz
        self.Ad, self.Bd = discretise(cfg.wheel_inertia_kgm2, behaviour.arm, dt, *self._physical)
        p = np.zeros(N_PARAMS)
        p[P_BSW], p[P_KSW] = wheel_split(self.wheel, cfg.wheel_rendering)[1]
        p[P_QANG] = 2 * np.pi / s.encoder_counts_per_rev if s.encoder_counts_per_rev else 0.0
        p[P_TRES] = s.torque_resolution
        p[P_KC], p[P_BC] = behaviour.arm.k_c, behaviour.arm.b_c
        p[P_DT] = dt
        m.configure(p, behaviour, cfg.fs_hz)
        self.p = p
        self.safety_vec = self.safety.kernel_vector(cfg.fs_hz)
        self.ring_r = np.zeros(m.reflex_delay_samples(cfg.fs_hz))
        self.ring_s = np.zeros(m.sensor_delay_samples(cfg.fs_hz))
        self.x = np.zeros(4)
        self.st = np.zeros(N_STATE + m.command_ring_samples(cfg.fs_hz))
        self.noise: NoiseSource = NoiseBlocks(cfg, behaviour, left_share, seed, schedule)
        self._blk: dict[str, np.ndarray] | None = None
        self._dpar = np.zeros((0, 4))
        self._truth: np.ndarray | None = None  # (block, len(TRUTH_CHANNELS)) when scheduled
        self._k = 0  # index within the current noise block
        self._n = 0  # samples advanced in this trial
        self._out1 = np.zeros((len(OUTPUTS), 1))
        self._cmd1 = np.zeros(1)
        self._trial = True

    def _ensure_block(self) -> dict[str, np.ndarray]:
        """The current noise block, drawing the next one when this one is used up."""
        if self._blk is None or self._k >= self.noise.block:
            self._blk = self.noise.next_block()
            self._k = 0
            dp = self.cfg.mechanisms.parameter_deltas(self._blk, self.behaviour)
            if "true_arm" in self._blk:
                dp = self._scheduled_deltas(self._blk, dp)
            self._dpar = dp if dp is not None else np.zeros((0, 4))
            self.p[P_HAS_DPAR] = 1.0 if dp is not None else 0.0
        return self._blk

    def _scheduled_deltas(self, blk: dict[str, np.ndarray], dp: np.ndarray | None) -> np.ndarray:
        """Deltas for a scheduled block; records the truth. Adds to any mechanism's deltas.

        The linear part is re-discretised exactly at the block's last parameters, so a block
        where the driver has settled runs exactly (zero deltas) and only the samples of a
        change go through the held deltas. Both paths do this at the same block boundaries.
        """
        arm = blk["true_arm"]
        truth = np.empty((len(arm), len(TRUTH_CHANNELS)))
        truth[:, :4] = arm if dp is None else arm + dp
        truth[:, 4] = blk["grip_mean_true_N"]
        self._truth = truth
        base = replace(self.behaviour.arm, **dict(zip(ARM_COLUMNS, arm[-1].tolist(), strict=True)))
        self.Ad, self.Bd = discretise(
            self.cfg.wheel_inertia_kgm2, base, self.p[P_DT], *self._physical
        )
        self.p[P_KC], self.p[P_BC] = base.k_c, base.b_c
        self.p[P_KI] = base.k_i
        self.p[P_DPAR_HALF] = 0.5 * self.p[P_DT]
        d = arm - arm[-1]
        return d if dp is None else d + dp

    # -- batch --------------------------------------------------------------------------
    def run(self, tp: np.ndarray) -> dict[str, np.ndarray]:
        """Advance len(tp) samples, rendering Table 1 inside the loop; returns all channels."""

        def advance(b: dict, tp_block: np.ndarray, out_block: np.ndarray, m: int) -> None:
            _advance(
                self.x,
                self.st,
                self.p,
                self.Ad,
                self.Bd,
                self.ring_r,
                self.ring_s,
                tp_block,
                self._cmd1,
                True,
                b["remnant_Nm"],
                b["velocity_noise"],
                b["torque_noise"],
                self._dpar,
                out_block,
                self._k,
                m,
                self.safety_vec,
            )

        return self._run_blocks(tp, advance, with_truth=self.scheduled)

    def _run_blocks(self, tp, advance, *, with_truth: bool) -> dict[str, np.ndarray]:
        """Run ``advance(block, tp_block, out_block, m)`` over the noise blocks that len(tp)
        samples span (a batch kernel per block, ``self._k`` at the block's first sample), and
        collect every channel."""
        if not self._trial:
            raise RuntimeError("World.run before begin_trial")
        tp = np.ascontiguousarray(tp, dtype=float)
        n = len(tp)
        out = np.empty((len(OUTPUTS), n))
        extra = {k: np.empty(n) for k in ("grip_force_left_N", "grip_force_right_N", "grip_true_N")}
        truth = np.empty((n, len(TRUTH_CHANNELS))) if with_truth else None
        done = 0
        while done < n:
            b = self._ensure_block()
            m = min(n - done, self.noise.block - self._k)
            advance(b, tp[done : done + m], out[:, done : done + m], m)
            for key in extra:
                extra[key][done : done + m] = b[key][self._k : self._k + m]
            if truth is not None and self._truth is not None:
                truth[done : done + m] = self._truth[self._k : self._k + m]
            self._k += m
            done += m
        self._n += n
        res = {name: out[i] for i, name in enumerate(OUTPUTS)}
        res.update(extra)
        if truth is not None:
            res.update({c: truth[:, i] for i, c in enumerate(TRUTH_CHANNELS)})
        return res

    # -- live, one sample at a time --------------------------------------------------------
    def read(self) -> dict[str, float]:
        """What the sensors report now (before the next step)."""
        b, k = self._ensure_block(), self._k
        dkc = dbc = 0.0
        if self.p[P_HAS_DPAR] != 0.0:
            dkc, dbc = self._dpar[k, 3], self._dpar[k, 2]
        ang, vel, td = _measure(
            self.x,
            self.st,
            self.p,
            self.ring_s,
            b["velocity_noise"][k],
            b["torque_noise"][k],
            dkc,
            dbc,
        )
        return {
            "wheel_angle_rad": ang,
            "wheel_velocity_rad_s": vel,
            "driver_torque_Nm": td,
            "motor_torque_Nm": self.st[S_TM],
            "grip_force_left_N": b["grip_force_left_N"][k],
            "grip_force_right_N": b["grip_force_right_N"][k],
            "grip_true_N": b["grip_true_N"][k],
        }

    def truth(self) -> dict[str, float]:
        """The driver's true parameters now (time-varying trials; else empty)."""
        if not self.scheduled:
            return {}
        self._ensure_block()
        row = self._truth[self._k] if self._truth is not None else None
        if row is None:
            return {}
        return {c: float(row[i]) for i, c in enumerate(TRUTH_CHANNELS)}

    def step(self, motor_command_nm: float) -> None:
        """Apply one sample of motor command (N·m) and advance one sample."""
        b = self._ensure_block()
        self._cmd1[0] = motor_command_nm
        _advance(
            self.x,
            self.st,
            self.p,
            self.Ad,
            self.Bd,
            self.ring_r,
            self.ring_s,
            self._cmd1,
            self._cmd1,
            False,
            b["remnant_Nm"],
            b["velocity_noise"],
            b["torque_noise"],
            self._dpar,
            self._out1,
            self._k,
            1,
            self.safety_vec,
        )
        self._k += 1
        self._n += 1

    def warm_up(self, behaviour: ConditionBehaviour) -> None:
        """Compile both kernel paths now, so the first live cycle is not a compile."""
        self.begin_trial(behaviour, 0.5, seed=0)
        self.run(np.zeros(2))
        self.read()
        self.step(0.0)
        self._trial = False

    @property
    def scheduled(self) -> bool:
        """Whether this trial is time-varying (a stand-in noise source has no schedule)."""
        return getattr(self.noise, "schedule", None) is not None

    @property
    def nonfinite_commands(self) -> int:
        """Cycles of this trial whose motor command had a non-finite input (zero applied)."""
        return int(self.st[S_NONFINITE])

    @property
    def samples_done(self) -> int:
        return self._n
