"""Steerlab's tracker: grip force for speed, the perturbation response for truth.

An extended Kalman filter on the arm model, whose parameter states are *offsets from the LPV
model's prediction*:

    log p(t) = m(μ(t)) + δ(t),    p = (b_i, k_i, b_c, k_c)

- m(μ) is the grip-scheduled LPV model (:mod:`analysis.tracking.calibration`) evaluated at the
  grip force's *level* μ(t). When the driver grips harder the prior moves at once: the estimate
  reacts as fast as the grip does, as the paper's LPV model.
- The level is the mean of the measured grip *since the task last changed*: a running mean
  over n samples, μ += (g − μ)/n, n growing by one per sample up to ``level_max_s`` and cut
  back to ``level_min_s`` (50 ms) when the grip jumps: its relative distance from the level
  |g − μ|/μ above D_0 (25 %), or above D_1 (10 %) while its relative rate ρ = |g'|/g / ν
  (g the lightly smoothed grip) is above ρ_0. Within a task the grip wanders (SD 7.5–11 % in
  the simulated drivers, correlated over ~1 s) and the arm follows only the task, not the
  wander; the mean since the change estimates the task's grip better the longer the task
  lasts, *if* nothing restarts it. The wander itself does, now and then: with the simulated
  drivers' glove stream, 2–50 times a minute (most for the wide-boundary tasks, whose grip is
  low and wanders most), so in a steady task this level is about as noisy as a 1-s smoother's
  for those and better for the steadier grips. During a change it follows the grip (50 ms
  behind, plus the rate filters' lag); after a 0.2-s step it sits a few per cent short for a
  few seconds, because the mean starts while the grip still creeps up. Stricter restarts
  (fewer false ones) made the benchmark's steps slower to detect and scored no better. (The
  first version smoothed with a time constant scheduled on ρ and D, never averaging beyond
  ~1 s; docs/benchmarks.md, tracking, has what each change did.)
- δ(t) is what the measurements correct: whatever the LPV model gets wrong for this driver and
  this task (calibration error, RT vs BT18 at equal grip) is learnt from how the wheel actually
  moves under the measured torque, so the estimate is not biased by the grip → admittance
  relation the way the LPV model alone is.
- δ is scheduled on the same rate: δ_{k+1} = a_k δ_k + w_k with
  a_k = exp(−h (ρ − ρ_0)₊²/τ_reset) and var(w_k) = q_δ h + (1 − a_k²) P_δ0. A fast change
  of grip means a change of task, for which the offset learnt in the old task is no evidence:
  δ relaxes towards 0 (trust the LPV model's new prediction) and its variance towards the
  prior's, so the measurements then correct it quickly; while the grip is steady (ρ < ρ_0)
  a_k = 1 and δ is a slow random walk.
- The estimate shows δ shrunk by its evidence: p = exp(m + δ z²/(z² + c)), z = δ/SD(δ). An
  offset the data have not established (|z| ≲ 1) moves the estimate little, one they have (an
  RT driver taken for BT18 by grip, z ≫ 1) moves it fully. Without it the filter's own noise
  in δ pushed estimates out of a band the LPV prediction was in (``shrink``, c = 1).

The measurement model is the rig driven by the perturbation, the only signal the driver does
not shape: the wheel (the protocol's inertia, rendered damping and stiffness) in contact with the
arm model, perturbation torque in, wheel angle and driver torque out (docs/method.md):

    state  x = [θ, θ', θ_h, θ_h', d_θ, d_θ', d_T, d_T', δ_bi, δ_ki, δ_bc, δ_kc]
    I_w θ'' = T_m − T_d,  T_m = T_p − b_w θ' − k_w θ (held per sample, as the loop renders it)
    T_d = k_c (θ − θ_h) + b_c (θ' − θ_h')
    I_i θ_h'' = T_d − b_i θ_h' − k_i θ_h
    y = [θ + d_θ, T_d + d_T] + v

What the perturbation does not drive (the remnant's effect through the closed loop, slow drifts)
is modelled as two second-order (critically damped) Gauss–Markov disturbances d_θ, d_T on the
outputs, SDs and corners from the calibration (the remnant's effect is smooth: a low-passed
torque through the rig's own low-pass). Because T_p is independent of the remnant, this output-error
structure is unbiased in the closed loop. (A first version took the measured T_d as the arm's
input and the remnant as a state, the natural EKF; with the remnant present it converged to
k_c 17 % and k_i 10 % too high, the equation-error bias of a filter that re-reads the angle
every sample; see docs/benchmarks.md.)

Discretised per sample by the trapezoidal rule at the current parameters; the Jacobian exact
for the states, by central differences for the parameters. Everything per sample (grip
smoothing, LPV evaluation, the filter) is one compiled function, :func:`ekf_update`, used
sample by sample by :class:`analysis.tracking.online.OnlineTracker` and in a compiled loop
offline; both give the same numbers.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit
from scipy.linalg import expm

from steerlab.analysis.tracking.base import TrackedAdmittance, TrackingTrial, finish
from steerlab.analysis.tracking.calibration import CalibratedTracker, Calibration

# cfg vector
C_I, C_H, C_IW, C_BW, C_KW, C_R1, C_R2, C_QZ = 0, 1, 2, 3, 4, 5, 6, 7
C_QD = 8  # 8..11: δ random-walk variance per second, per parameter
C_NU, C_AG, C_AD, C_LO, C_HI, C_CEN, C_SCL = 12, 13, 14, 15, 16, 17, 18
C_NMIN, C_TR, C_USE_T, C_RT = 19, 20, 21, 22
C_P0 = 23  # 23..26: per parameter, the variance δ relaxes to at a change of task (0: kept)
C_DEV = 27
C_DEV1, C_NMAX, C_SHRINK = 28, 29, 30
N_CFG = 31
# mem vector (what the filter remembers between samples)
M_U, M_MU, M_DMU, M_INIT = 0, 1, 2, 3
M_M = 4  # 4..7: LPV prior (log parameters) of the previous sample
M_LEVEL = 8  # grip level
M_NEFF = 9  # samples the level averages over
N_MEM = 10
# out vector
O_P = 0  # 0..3: b_i, k_i, b_c, k_c
O_MU, O_PRIOR_KI, O_SD_LOG_KI, O_QSCALE = 4, 5, 6, 7
N_OUT = 8
# state: rig (θ, θ', θ_h, θ_h'), d_θ and its rate, d_T and its rate, δ (4)
X_DTH, X_DT, X_D = 4, 6, 8
N_X = 12


@dataclass(frozen=True)
class EKFConfig:
    """Tuning of :class:`GripInformedEKF` (chosen on subjects apart from the benchmark's)."""

    grip_tau_s: float = 0.1  # smoothing of the glove's total grip force (for its rate)
    grip_rate_tau_s: float = 0.1  # smoothing of its rate of change
    rate_ref_per_s: float = 0.3  # ν: relative grip rate that counts as "changing"
    level_jump: float = 0.25  # D_0: relative distance of grip from level that is a jump
    level_step: float = 0.10  # D_1: the same while the grip moves fast (ρ > ρ_0)
    level_min_s: float = 0.05  # the grip level's averaging while the grip jumps
    level_max_s: float = 20.0  # ... and at most, in a long steady task
    reset_threshold: float = 1.5  # ρ_0: ρ above which δ relaxes towards 0
    shrink: float = 1.0  # c: the estimate shows δ·z²/(z² + c), z = δ/SD(δ); 0: δ as it is
    delta_reset_s: float = 1.0  # τ_reset: how fast, per (ρ − threshold)²
    # Random walk of δ per second (log units², per b_i, k_i, b_c, k_c) while grip is steady.
    q_delta: tuple[float, float, float, float] = (1e-3, 4e-3, 1e-3, 4e-3)
    p0_delta: float = 0.3**2  # variance of δ at the start: the LPV model may be ~30 % off
    # Variance each δ relaxes to at a change of task (0: that δ is kept as it is). Small: right
    # after a change the LPV model is the better guess, the measurements then refine it over
    # seconds (a large value lets the k_i–k_c trade-off of the series springs run off).
    p_reset: tuple[float, float, float, float] = (0.05**2, 0.05**2, 0.05**2, 0.05**2)
    angle_sd_rad: float = 2e-5  # white measurement noise on θ (encoder, model error)
    # White measurement noise on T_d. Not the sensor's (~0.03 N·m): what the arm model misses
    # in the driver torque beyond the coloured d_T. At 0.03 the filter trusted the torque too
    # much and k_i came out +5 to +7 % biased on the tuning subjects; at 0.3 (the order of the
    # remnant torque's own SD) +2.5 %, with lower RMS error (docs/benchmarks.md, tracking).
    torque_sd_Nm: float = 0.3
    use_torque: bool = True  # also correct from the measured driver torque
    state_sd: float = 1e-7  # white process noise on the rig's states (model error)


@njit(cache=True)
def _prior(mu, cfg, coef, m):
    x = (min(max(mu, cfg[C_LO]), cfg[C_HI]) - cfg[C_CEN]) / cfg[C_SCL]
    for i in range(4):
        v = 0.0
        for c in coef[i]:
            v = v * x + c
        m[i] = math.log(max(v, 1e-3))


@njit(cache=True)
def _rig(z, u, p, cfg, Minv, N):
    """One step of the rig at parameters p = (b_i, k_i, b_c, k_c), as the loop runs it: the
    motor torque (perturbation u, rendered damping and stiffness of the wheel from the state
    at the step's start) held over the step, wheel and arm by the trapezoidal rule.
    Fills Minv and N with z+ = Minv (N z + g u), N holding the rendering; returns z+."""
    bi, ki, bc, kc = p[0], p[1], p[2], p[3]
    I, Iw, bw, kw, h = cfg[C_I], cfg[C_IW], cfg[C_BW], cfg[C_KW], cfg[C_H]
    A = np.zeros((4, 4))
    A[0, 1] = 1.0
    A[1, 0] = -kc / Iw
    A[1, 1] = -bc / Iw
    A[1, 2] = kc / Iw
    A[1, 3] = bc / Iw
    A[2, 3] = 1.0
    A[3, 0] = kc / I
    A[3, 1] = bc / I
    A[3, 2] = -(kc + ki) / I
    A[3, 3] = -(bc + bi) / I
    Minv[:, :] = np.linalg.inv(np.eye(4) - 0.5 * h * A)
    N[:, :] = np.eye(4) + 0.5 * h * A
    N[1, 0] -= h * kw / Iw
    N[1, 1] -= h * bw / Iw
    rhs = N @ z
    rhs[1] += h * u / Iw
    return Minv @ rhs


@njit(cache=True)
def ekf_update(x, P, cfg, coef, dphi, dq, mem, tp, td, theta, grip, out):
    """One loop sample: (perturbation, driver torque, angle, grip) → estimate in ``out``.

    ``dphi``/``dq`` (2, 2, 2): per output (θ, T_d) the disturbance's discrete transition and
    process-noise matrices.
    """
    h = cfg[C_H]
    m_now = np.empty(4)
    changing = False
    if mem[M_INIT] == 0.0:
        mem[M_MU] = grip
        mem[M_DMU] = 0.0
        mem[M_LEVEL] = grip
        mem[M_NEFF] = cfg[C_NMIN]
        mem[M_INIT] = 1.0
        _prior(grip, cfg, coef, m_now)
        out[O_QSCALE] = 1.0
    else:
        mu_old = mem[M_MU]
        mem[M_MU] += cfg[C_AG] * (grip - mem[M_MU])
        mem[M_DMU] += cfg[C_AD] * ((mem[M_MU] - mu_old) / h - mem[M_DMU])
        rate = abs(mem[M_DMU]) / max(mem[M_MU], 1.0) / cfg[C_NU]
        qscale = 1.0 + rate * rate
        out[O_QSCALE] = qscale
        # Grip level: the mean since the grip last jumped (module docstring). A big jump
        # shows in the distance from the level before the smoothed rate has risen.
        dev = abs(grip - mem[M_LEVEL]) / max(mem[M_LEVEL], 1.0)
        if dev > cfg[C_DEV] or (rate > cfg[C_RT] and dev > cfg[C_DEV1]):
            mem[M_NEFF] = cfg[C_NMIN]  # n never falls below it: this restarts the mean
        else:
            mem[M_NEFF] = min(mem[M_NEFF] + 1.0, cfg[C_NMAX])
        mem[M_LEVEL] += (grip - mem[M_LEVEL]) / mem[M_NEFF]
        _prior(mem[M_LEVEL], cfg, coef, m_now)
        # Above a threshold only: in a steady task the rate's noise (glove frames, the grip's
        # own wander) keeps ρ below 1.4–2.0 (99th percentile, simulated drivers); a change of
        # task gives 2.4–10.
        over = max(0.0, rate - cfg[C_RT])
        a = math.exp(-h * over * over / cfg[C_TR])
        changing = over > 0.0
        # Time update from the previous sample, with the previous sample's prior.
        p = np.empty(4)
        for i in range(4):
            p[i] = math.exp(mem[M_M + i] + x[X_D + i])
        Minv = np.empty((4, 4))
        N = np.empty((4, 4))
        z = x[:4].copy()
        zn = _rig(z, mem[M_U], p, cfg, Minv, N)
        F = np.zeros((N_X, N_X))
        F[:4, :4] = Minv @ N
        # Sensitivity to δ_i (log parameter): central differences of the rig step.
        Mt = np.empty((4, 4))
        Nt = np.empty((4, 4))
        for i in range(4):
            e = 1e-6
            pp = p.copy()
            pp[i] = p[i] * math.exp(e)
            zp = _rig(z, mem[M_U], pp, cfg, Mt, Nt)
            pp[i] = p[i] * math.exp(-e)
            zm = _rig(z, mem[M_U], pp, cfg, Mt, Nt)
            for r in range(4):
                F[r, X_D + i] = (zp[r] - zm[r]) / (2.0 * e)
        for o in range(2):
            k0 = X_DTH + 2 * o
            F[k0 : k0 + 2, k0 : k0 + 2] = dphi[o]
        for i in range(4):
            F[X_D + i, X_D + i] = a if cfg[C_P0 + i] > 0.0 else 1.0
        xn = F @ x
        xn[:4] = zn  # the rig's own step (F[:4, X_D:] is only its linearisation)
        for i in range(N_X):
            x[i] = xn[i]
        Pn = F @ P @ F.T
        for i in range(4):
            Pn[i, i] += cfg[C_QZ]
        for o in range(2):
            k0 = X_DTH + 2 * o
            Pn[k0 : k0 + 2, k0 : k0 + 2] += dq[o]
        for i in range(4):
            ai = F[X_D + i, X_D + i]
            Pn[X_D + i, X_D + i] += cfg[C_QD + i] * h + (1.0 - ai * ai) * cfg[C_P0 + i]
        for i in range(N_X):
            for j in range(N_X):
                P[i, j] = 0.5 * (Pn[i, j] + Pn[j, i])
    # Measurement update: θ = rig θ + d_θ; T_d = contact torque of the rig + d_T.
    bc = math.exp(m_now[2] + x[X_D + 2])
    kc = math.exp(m_now[3] + x[X_D + 3])
    defl, rate_defl = x[0] - x[2], x[1] - x[3]
    n_y = 2 if cfg[C_USE_T] != 0.0 else 1
    H = np.zeros((n_y, N_X))
    innov = np.empty(n_y)
    Rm = np.zeros((n_y, n_y))
    H[0, 0] = 1.0
    H[0, X_DTH] = 1.0
    innov[0] = theta - (x[0] + x[X_DTH])
    Rm[0, 0] = cfg[C_R1]
    if n_y == 2:
        H[1, 0], H[1, 1], H[1, 2], H[1, 3] = kc, bc, -kc, -bc
        H[1, X_DT] = 1.0
        H[1, X_D + 2] = bc * rate_defl
        H[1, X_D + 3] = kc * defl
        innov[1] = td - (kc * defl + bc * rate_defl + x[X_DT])
        Rm[1, 1] = cfg[C_R2]
    PHt = P @ H.T
    S = H @ PHt + Rm
    K = PHt @ np.linalg.inv(S)
    if changing:
        # While the task changes, the LPV prediction and the arm move on slightly different
        # time courses (grip smoothing, the arm's own response): what the measurements show
        # then is the transition, not an offset of the new task. δ waits (its variance keeps
        # relaxing towards p_reset) and learns once the grip has settled.
        K[X_D:, :] = 0.0
    x += K @ innov
    IKH = np.eye(N_X) - K @ H
    # Joseph form: keeps P symmetric and positive with the very small R of the encoder.
    Pn = IKH @ P @ IKH.T + K @ Rm @ K.T
    for i in range(N_X):
        for j in range(N_X):
            P[i, j] = 0.5 * (Pn[i, j] + Pn[j, i])
    mem[M_U] = tp
    for i in range(4):
        mem[M_M + i] = m_now[i]
        d = x[X_D + i]
        if cfg[C_SHRINK] > 0.0:
            z2 = d * d / max(P[X_D + i, X_D + i], 1e-12)
            d *= z2 / (z2 + cfg[C_SHRINK])
        out[O_P + i] = math.exp(m_now[i] + d)
    out[O_MU] = mem[M_LEVEL]
    out[O_PRIOR_KI] = math.exp(m_now[1])
    out[O_SD_LOG_KI] = math.sqrt(max(P[X_D + 1, X_D + 1], 0.0))


@njit(cache=True)
def _run(x, P, cfg, coef, dphi, dq, mem, tp, td, th, grip, outs):
    one = np.empty(N_OUT)
    for k in range(len(td)):
        ekf_update(x, P, cfg, coef, dphi, dq, mem, tp[k], td[k], th[k], grip[k], one)
        outs[k] = one


def _gm2(sd: float, corner_hz: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Discrete transition and noise of a critically damped 2nd-order Gauss–Markov process
    with SD ``sd`` and corner ``corner_hz`` (Van Loan's method)."""
    w = 2 * math.pi * max(corner_hz, 1e-3)
    A = np.array([[0.0, 1.0], [-w * w, -2.0 * w]])
    q = 4.0 * w**3 * sd**2  # white-noise intensity giving variance sd² (ζ = 1)
    G = np.array([[0.0], [1.0]])
    M = np.block([[-A, G @ G.T * q], [np.zeros((2, 2)), A.T]]) * h
    E = expm(M)
    phi = E[2:, 2:].T
    Q = phi @ E[:2, 2:]
    return phi, 0.5 * (Q + Q.T)


class KalmanCore:
    """The filter's arrays for one run; shared by the offline tracker and the online one."""

    def __init__(self, calibration: Calibration, fs_hz: float, config: EKFConfig) -> None:
        prior = calibration.prior
        h = 1.0 / fs_hz
        c, d, w = config, calibration.disturbance, calibration.wheel
        cfg = np.zeros(N_CFG)
        cfg[C_I], cfg[C_H] = calibration.I_i, h
        cfg[C_IW], cfg[C_BW], cfg[C_KW] = (
            w.inertia_kgm2,
            w.damping_nms_per_rad,
            w.stiffness_nm_per_rad,
        )
        self.dphi = np.empty((2, 2, 2))
        self.dq = np.empty((2, 2, 2))
        for o, (sd, fc) in enumerate(
            ((d.angle_sd_rad, d.angle_corner_hz), (d.torque_sd_Nm, d.torque_corner_hz))
        ):
            self.dphi[o], self.dq[o] = _gm2(sd, fc, h)
        cfg[C_R1], cfg[C_R2] = c.angle_sd_rad**2, c.torque_sd_Nm**2
        cfg[C_QZ] = c.state_sd**2
        cfg[C_QD : C_QD + 4] = c.q_delta
        cfg[C_NU] = c.rate_ref_per_s
        cfg[C_AG] = 1.0 - math.exp(-h / c.grip_tau_s) if c.grip_tau_s > 0 else 1.0
        cfg[C_AD] = 1.0 - math.exp(-h / c.grip_rate_tau_s) if c.grip_rate_tau_s > 0 else 1.0
        cfg[C_LO], cfg[C_HI], cfg[C_CEN], cfg[C_SCL] = prior.lo, prior.hi, prior.centre, prior.scale
        cfg[C_TR] = c.delta_reset_s
        cfg[C_NMIN] = max(1.0, c.level_min_s * fs_hz)
        cfg[C_NMAX] = max(1.0, c.level_max_s * fs_hz)
        cfg[C_DEV1] = c.level_step
        cfg[C_SHRINK] = c.shrink
        cfg[C_P0 : C_P0 + 4] = c.p_reset
        cfg[C_USE_T] = 1.0 if c.use_torque else 0.0
        cfg[C_RT] = c.reset_threshold
        cfg[C_DEV] = c.level_jump
        order = max(len(cf) for cf in prior.coeffs)
        coef = np.zeros((4, order))
        for i, cf in enumerate(prior.coeffs):
            coef[i, order - len(cf) :] = cf  # leading zeros leave Horner's rule unchanged
        self.cfg, self.coef = cfg, coef
        self.x = np.zeros(N_X)
        # The rig starts at rest (the perturbation fades in); a tracker started mid-trial
        # converges within the rig's settling time (about a second).
        wa, wt = 2 * math.pi * d.angle_corner_hz, 2 * math.pi * d.torque_corner_hz
        self.P = np.diag(
            [1e-4, 1e-3, 1e-4, 1e-3]
            + [d.angle_sd_rad**2, (wa * d.angle_sd_rad) ** 2]
            + [d.torque_sd_Nm**2, (wt * d.torque_sd_Nm) ** 2]
            + [config.p0_delta] * 4
        ).astype(float)
        self.mem = np.zeros(N_MEM)
        self.out = np.zeros(N_OUT)

    def run(self, trial: TrackingTrial) -> np.ndarray:
        return self.run_arrays(
            trial.perturbation_Nm, trial.driver_torque_Nm, trial.angle_rad, trial.grip_N
        )

    def run_arrays(self, tp, td, theta, grip) -> np.ndarray:
        """Samples in (perturbation N·m, driver torque N·m, angle rad, grip N), one compiled
        call; (n, N_OUT) out, the filter's state carried on."""
        tp, td, theta, grip = (np.ascontiguousarray(v, dtype=float) for v in (tp, td, theta, grip))
        outs = np.empty((len(tp), N_OUT))
        _run(self.x, self.P, self.cfg, self.coef, self.dphi, self.dq, self.mem, tp, td, theta, grip,
             outs)  # fmt: skip
        return outs

    def update(self, tp: float, td: float, theta: float, grip: float) -> np.ndarray:
        ekf_update(
            self.x, self.P, self.cfg, self.coef, self.dphi, self.dq, self.mem,
            tp, td, theta, grip, self.out,
        )  # fmt: skip
        return self.out


class GripInformedEKF(CalibratedTracker):
    """Grip-scheduled LPV prior + Kalman correction from the perturbation response (ours)."""

    name = "grip_ekf"
    causal = True

    def __init__(self, config: EKFConfig | None = None) -> None:
        self.config = config or EKFConfig()

    def core(self, fs_hz: float) -> KalmanCore:
        return KalmanCore(self.calibrated(), fs_hz, self.config)

    def track(self, trial: TrackingTrial) -> TrackedAdmittance:
        t0 = time.perf_counter()
        core = self.core(trial.fs_hz)
        outs = core.run(trial)
        return finish(
            self.name, trial, outs[:, O_P : O_P + 4], np.ones(trial.n, dtype=bool),
            self.calibrated().I_i, self.causal, t0,
            {"config": asdict(self.config), "sd_log_k_i": outs[:, O_SD_LOG_KI],
             "prior_k_i": outs[:, O_PRIOR_KI], "q_scale": outs[:, O_QSCALE]},
        )  # fmt: skip
