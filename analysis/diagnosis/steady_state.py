"""The loop's periodic steady state on a trial's perturbation, bin by bin.

Why
    A fit simulates its model on every trial thousands of times (a reflex's forms: about
    15 000 simulations of 3 ms). For a linear, time-invariant model (the baseline, a reflex,
    an actuator lag in any form, viscous friction; not dry friction, stiffening, grip
    coupling or an unbalanced wheel) and a perturbation that is periodic over the analysed
    segment, the response at the segment's bins is H(z_k)·Tp_k, with H the loop's transfer
    function at z_k = e^{j2πk/P}: a 4 × 4 solve at each bin the perturbation drives (the
    multisine's 62 lines of 2 250 bins; zero elsewhere) instead of a simulation. Measured on
    the independent world's trials (250 Hz, 94 s): 0.24–0.44 ms against 3.3 ms.

Equations (those of :func:`hardware.sim.world._advance`, z-transformed; x = (θ, ω, θ_h, ω_h)
is the state before a sample's step, Ad, Bd its exact discretisation, inputs (T_m, T_hand,
T_wheel))::

    cmd  = Tp − b_sw ω − k_sw θ                         the loop's command (nothing clipped)
    T_m  = La(z) cmd                                     actuator lag (first, second order, delay):
                                                         its mean over the sample
    T_h  = R(z) z^{−n_r} (k_p θ_h + k_v ω_h)             reflex: delay, activation dynamics
    T_w  = −b_v ω                                        viscous friction
    z x  = Ad x + Bd (T_m, T_h, T_w)

solved per bin for x; θ = x_0 and Td = k_c (θ − θ_h) + b_c (ω − ω_h), read before the step.

The prediction is the trial in its periodic steady state
    The perturbation is periodic from some sample on (the recording's fade-in before it,
    :func:`perturbation`). Every model, this route and the simulated one alike, predicts the
    loop as if the periodic perturbation had always run: a simulation starts at that sample
    from the steady state's values of every state of the world (:func:`set_initial_state`),
    so that for a linear model both routes agree to rounding (a test holds them to it), a
    fit may pass from one to the other, and a nonlinear candidate is judged against the same
    baseline as a linear one. The measured start-up transient stays in the data, where the
    transient projection (:func:`analysis.diagnosis.data.transient_projector`) takes its
    smooth part; simulated from rest, the prediction differed from this one by at most 0.3
    units of cost per trial after that projection (the reflex study of the independent
    world, 2026-11-27).

When this route is not taken
    A trial whose perturbation is not periodic over the segment, or has power outside the
    analysed bins, or does not become periodic 0.2 s before the segment: every model
    is simulated from rest there, as before. A model that is not linear and time-invariant,
    or whose command could reach the rig's torque or slew limits or whose angle the soft
    limit's fade (:func:`within_linear_range`): simulated, from the steady state where the
    trial allows it. A loop that is unstable (spectral radius of its closed-loop matrix ≥ 1)
    is simulated from rest (``simulate.steady_start``): it grows until the rig's limits hold
    it, and the fit sees that; on its periodic orbit it would stay, rounding being all that
    seeds the growing mode.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np
import scipy.fft
from numba import njit

from steerlab.hardware.sim import world as W
from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.hardware.sim.physiology import ArmParams, ConditionBehaviour

# The perturbation counts as periodic where it repeats to this fraction of its peak, and as
# within the bins where this fraction of its power is outside them (CSV rounding: ~1e-12).
PERIODIC_TOL = 1e-7
OUT_OF_BIN_POWER_TOL = 1e-9
# A simulation from the steady state starts at least this long before the segment (the
# reading delay's interpolation in simulate.simulated_segment reads samples before it).
START_MARGIN_S = 0.2
# Slack on the command limits (relative).
LIMIT_MARGIN = 0.999
# Bins whose perturbation phasor is below this fraction of the largest are not driven (a
# multisine's unexcited bins: 1.7e-10 after the interchange format's rounding); the steady
# state is zero there.
DRIVEN_TOL = 1e-8


@dataclass(frozen=True)
class Perturbation:
    """The trial's perturbation as the steady state needs it: amplitude-scaled phasors U_k
    at the bins it drives (Tp(m) = Re Σ U_k z_k^{m − start}), the sample from which it is
    periodic, and its peak and largest step over a period."""

    driven: np.ndarray  # indices into the trial's bins
    n_bins: int
    phasors: np.ndarray
    periodic_from: int
    peak: float
    peak_step: float
    z: np.ndarray  # e^{j2πk/P} at the driven bins
    z_from: np.ndarray  # z^{periodic_from − start}
    ramp: np.ndarray  # (2/P)/(1 − e^{−j2πk/P}) at every bin: a unit ramp's spectrum, negated
    # [(fb, |cmd| max, |step| max)]: the last command checked over a period
    # (within_linear_range), its feedback phasors and the largest command and step it
    # reached; at first the perturbation's own. Replaced whole: a thread sees one or the other.
    checked: list = field(default_factory=list)


def perturbation(trial) -> Perturbation | None:
    """The trial's :class:`Perturbation` (computed once per trial), or None when the steady
    state does not apply (module docstring)."""
    cached = trial._perturbation
    if cached is not None:
        return cached or None
    out = _perturbation(trial)
    trial._perturbation = out if out is not None else False
    return out


def _perturbation(trial) -> Perturbation | None:
    start, stop, P = trial.start, trial.stop, trial.stop - trial.start
    tp = np.asarray(trial.tp[: trial.n_sim], dtype=float)
    seg = tp[start:stop]
    peak = float(np.max(np.abs(seg))) if len(seg) else 0.0
    if P < 4 or peak == 0.0 or not np.all(np.isfinite(tp)):
        return None
    F = np.fft.rfft(seg)
    power = np.abs(F) ** 2
    total = float(np.sum(power[1:]) * 2 + power[0])
    inside = float(np.sum(power[trial.bins]) * 2)
    if total - inside > OUT_OF_BIN_POWER_TOL * total:
        return None
    # The periodic extension up to the segment's end; where the recording matches it. (What
    # comes after, the sample after the segment, moves nothing the segment's spectra read:
    # the world's outputs at a sample are read before its step.)
    ext = seg[(np.arange(stop) - start) % P]
    off = np.flatnonzero(np.abs(tp[:stop] - ext) > PERIODIC_TOL * peak)
    if len(off) and off[-1] >= start - START_MARGIN_S * trial.fs_hz:
        return None
    first = int(off[-1]) + 1 if len(off) else 0
    steps = np.abs(np.diff(np.concatenate([seg, seg[:1]])))
    U = F[trial.bins] * (2.0 / P)
    driven = np.flatnonzero(np.abs(U) > DRIVEN_TOL * np.max(np.abs(U)))
    k = trial.bins[driven]
    z = np.exp(2j * np.pi * k / P)
    z_from = np.exp(2j * np.pi * k * ((first - start) % P) / P)
    ramp = (2.0 / P) / (1.0 - np.exp(-2j * np.pi * trial.bins / P))
    pert = Perturbation(
        driven, len(trial.bins), U[driven], first, peak, float(np.max(steps)), z, z_from, ramp
    )
    pert.checked.append((np.zeros(len(driven), dtype=complex), peak, pert.peak_step))
    return pert


# The parts of the mechanisms that are not linear and time-invariant: these two functions
# name the same ones (the sensor delay and drift are applied outside the world, see
# ``simulate._split``).
def is_linear_time_invariant(mech: Mechanisms) -> bool:
    """Whether the world's loop with these mechanisms is linear and time-invariant."""
    return not (
        mech.coulomb_friction.torque_nm != 0.0
        or mech.stiffness_nonlinearity.active
        or mech.grip_scheduled_stiffness.active
        or mech.wheel_imbalance.active
    )


def linear_part(mech: Mechanisms) -> Mechanisms:
    """The mechanisms without their nonlinear and time-varying parts (dry friction's
    Coulomb and Stribeck terms, stiffening, grip coupling, an unbalanced wheel)."""
    cf = mech.coulomb_friction
    return replace(
        mech,
        coulomb_friction=type(cf)(viscous_nms_per_rad=cf.viscous_nms_per_rad),
        stiffness_nonlinearity=type(mech.stiffness_nonlinearity)(),
        grip_scheduled_stiffness=type(mech.grip_scheduled_stiffness)(),
        wheel_imbalance=type(mech.wheel_imbalance)(),
    )


@dataclass(frozen=True)
class Loop:
    """The loop's per-sample equations for one trial, arm and set of mechanisms."""

    Ad: np.ndarray
    Bd: np.ndarray
    q: np.ndarray  # the compiled functions' scalars (:func:`_scalars`)
    n_reflex: int  # reflex delay, samples
    n_command: int  # length of the ring of past commands (the lag's delay form), 0: none

    @property
    def k_sw(self) -> float:
        return float(self.q[0])

    @property
    def b_sw(self) -> float:
        return float(self.q[1])


@lru_cache(maxsize=512)
def _discretised(
    I_w: float, arm: ArmParams, dt: float, b_w: float = 0.0, k_w: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    # A fit evaluates each arm with several mechanism parameters (its Jacobian's columns).
    Ad, Bd = W.discretise(I_w, arm, dt, b_w, k_w)
    Ad.flags.writeable = Bd.flags.writeable = False
    return Ad, Bd


def loop(trial, arm: ArmParams, mech: Mechanisms) -> Loop:
    fs = trial.fs_hz
    # A physical wheel's spring and damper are in the continuous dynamics; the loop renders none.
    (b_w, k_w), (b_sw, k_sw) = W.wheel_split(trial.wheel, trial.wheel_rendering)
    Ad, Bd = _discretised(float(trial.wheel.inertia_kgm2), arm, 1.0 / fs, b_w, k_w)
    p = np.zeros(W.N_PARAMS)
    p[W.P_DT] = 1.0 / fs
    mech.configure(p, ConditionBehaviour(arm, 0.0, 0.0, 0.0), fs)
    q = _scalars(p, k_sw, b_sw, arm)
    return Loop(Ad, Bd, q, mech.reflex_delay_samples(fs), mech.command_ring_samples(fs))


@njit(cache=True, inline="always")
def _power(x, n):  # pragma: no cover - compiled
    """x**n for a whole n ≥ 0 (complex ** in compiled code goes through exp and log)."""
    out = 1.0 + 0.0j
    for _ in range(n):
        out *= x
    return out


@njit(cache=True)
def _bins(z, U, Ad, Bd, q, n_reflex, out):  # pragma: no cover - compiled
    """Per bin, every phasor of the loop (rows of ``out``, :data:`_ROWS`), from
    (zI − Ad − Bd F(z)) x = Bd[:, 0] La(z) U (module docstring). ``q``: the scalars of
    :func:`_scalars`."""
    k_sw, b_sw, k_p, k_v, b_v, k_c, b_c = q[0], q[1], q[2], q[3], q[4], q[5], q[6]
    form, alpha, n_lag, frac = q[7], q[8], int(q[9]), q[10]
    f00, f01, f10, f11, g0, g1 = q[11], q[12], q[13], q[14], q[15], q[16]
    dt, w, ze = q[17], q[18], q[19]
    m0, m1, m2 = q[20], q[21], q[22]
    reflex = k_p != 0.0 or k_v != 0.0
    M = np.empty((4, 5), dtype=np.complex128)
    x = np.empty(4, dtype=np.complex128)
    for k in range(z.shape[0]):
        zk = z[k]
        zi = zk.conjugate()  # |z| = 1
        # The actuator's lag L = T_m / cmd (and the second order's rate, Ld), T_m at the
        # sample's end; La: the torque applied over the sample, the lag's mean over it.
        ld = 0.0j
        if form == 1.0:
            m00, m01, m10, m11 = 1.0 - f00 * zi, -f01 * zi, -f10 * zi, 1.0 - f11 * zi
            det = m00 * m11 - m01 * m10
            lk = (m11 * g0 - m01 * g1) / det
            ld = (m00 * g1 - m10 * g0) / det
            la = m2 + zi * (m0 * lk + m1 * ld)
        elif form == 2.0:
            zn = _power(zi, n_lag)
            lk = (1.0 - frac) * zn + frac * zn * zi
            la = lk
        else:
            lk = alpha / (1.0 - (1.0 - alpha) * zi)
            la = 1.0 - m0 + m0 * zi * lk
        # The reflex: delay and activation (semi-implicit Euler), T_h / drive.
        rk = 0.0j
        if reflex:
            qq = 1.0 - zi
            rk = -(dt * dt * w * w) / (qq * qq + 2.0 * ze * w * dt * zi * qq + dt * dt * w * w * zi)
            rk = rk * _power(zi, n_reflex)
        for a in range(4):
            for b in range(4):
                M[a, b] = -Ad[a, b]
            M[a, a] += zk
            # −Bd F: F's rows act on θ, ω (command), θ_h, ω_h (reflex), ω (viscous).
            M[a, 0] += Bd[a, 0] * la * k_sw
            M[a, 1] += Bd[a, 0] * la * b_sw + Bd[a, 2] * b_v
            M[a, 2] -= Bd[a, 1] * rk * k_p
            M[a, 3] -= Bd[a, 1] * rk * k_v
            M[a, 4] = Bd[a, 0] * la * U[k]
        # Gaussian elimination, partial pivoting (on |re| + |im|).
        for c in range(4):
            piv = c
            best = abs(M[c, c].real) + abs(M[c, c].imag)
            for r in range(c + 1, 4):
                m = abs(M[r, c].real) + abs(M[r, c].imag)
                if m > best:
                    piv, best = r, m
            if piv != c:
                for j in range(c, 5):
                    t = M[c, j]
                    M[c, j] = M[piv, j]
                    M[piv, j] = t
            inv = 1.0 / M[c, c]
            for r in range(c + 1, 4):
                f = M[r, c] * inv
                for j in range(c + 1, 5):
                    M[r, j] -= f * M[c, j]
        for c in range(3, -1, -1):
            acc = M[c, 4]
            for j in range(c + 1, 4):
                acc -= M[c, j] * x[j]
            x[c] = acc / M[c, c]
        cmd = U[k] - b_sw * x[1] - k_sw * x[0]
        drive = k_p * x[2] + k_v * x[3]
        ra = rk * drive
        for a in range(4):
            out[a, k] = x[a]
        out[4, k] = cmd
        out[5, k] = lk * cmd
        out[6, k] = ld * cmd
        out[7, k] = drive
        out[8, k] = ra
        out[9, k] = ra * (1.0 - zi) / dt
        out[10, k] = k_c * (x[0] - x[2]) + b_c * (x[1] - x[3])


def _scalars(p: np.ndarray, k_sw: float, b_sw: float, arm: ArmParams) -> np.ndarray:
    """What :func:`_bins` and :func:`_closed_loop` read, from the kernel's parameter vector
    ``p`` (hardware.sim.world P_*), the rendered wheel's spring and damper and the arm."""
    return np.concatenate([
        [k_sw, b_sw, p[W.P_RKP], p[W.P_RKV], p[W.P_VISC], arm.k_c, arm.b_c],
        [p[W.P_LAG_FORM], p[W.P_ACT_ALPHA], p[W.P_LAG_N], p[W.P_LAG_FRAC]],
        p[W.P_LAG2 : W.P_LAG2 + 6],
        [p[W.P_DT], p[W.P_RW], p[W.P_RZ]],
        p[W.P_LAG_MEAN : W.P_LAG_MEAN + 3],
    ])  # fmt: skip


@dataclass(frozen=True)
class SteadyState:
    """Amplitude-scaled phasors at the trial's bins of every signal of the loop: rows of
    ``rows``, named by :data:`ROWS`."""

    rows: np.ndarray

    @property
    def x(self) -> np.ndarray:
        """(4, nb) θ, ω, θ_h, ω_h."""
        return self.rows[:4]

    def __getattr__(self, name: str) -> np.ndarray:
        # Only the signals' names; anything else (``rows`` itself before it is set, as in
        # unpickling and copying) is not found, rather than looked up again.
        if name not in ROWS:
            raise AttributeError(name)
        return self.rows[ROWS.index(name)]


# cmd: the loop's command; tm, tmd: the lag's torque at the sample's end (applied over the next
# sample with the command: the kernel's P_LAG_MEAN) and (second-order lag) its rate;
# drive: k_p θ_h + k_v ω_h before its delay; ra, rad: the reflex's torque and its rate;
# td: the driver torque.
ROWS = ("theta", "omega", "theta_h", "omega_h", "cmd", "tm", "tmd", "drive", "ra", "rad", "td")


def steady_state(lp: Loop, pert: Perturbation) -> SteadyState:
    out = np.empty((len(ROWS), len(pert.z)), dtype=complex)
    _bins(pert.z, pert.phasors, lp.Ad, lp.Bd, lp.q, lp.n_reflex, out)
    return SteadyState(out)


def closed_loop_matrix(lp: Loop) -> np.ndarray:
    """The loop's state-transition matrix with the perturbation at zero. The state is x, then
    those of the kernel's states the model uses: the lag's torque (a first-order lag; and
    its rate, a second-order one), the reflex's activation and its rate and its last n_r
    drives, the last commands (the lag's delay form); the rings ordered by age."""
    return _closed_loop(lp.Ad, lp.Bd, lp.q, lp.n_reflex, max(lp.n_command - 1, 0))


@njit(cache=True)
def _closed_loop(Ad, Bd, q, nr, nc):  # pragma: no cover - compiled
    k_sw, b_sw, k_p, k_v, b_v = q[0], q[1], q[2], q[3], q[4]
    form, alpha, n_lag, frac = q[7], q[8], int(q[9]), q[10]
    f00, f01, f10, f11, g0, g1 = q[11], q[12], q[13], q[14], q[15], q[16]
    dt, w, ze = q[17], q[18], q[19]
    m0, m1, m2 = q[20], q[21], q[22]
    reflex = k_p != 0.0 or k_v != 0.0
    # A lag so short that alpha rounds to 1 still weighs the last sample's torque (m0 > 0).
    n_tm = 2 if form == 1.0 else (1 if form == 0.0 and (alpha != 1.0 or m0 != 0.0) else 0)
    if not reflex:
        nr = 0
    if form != 2.0:
        nc = 0
    i_tm = 4
    i_ra = i_tm + n_tm
    i_dr = i_ra + (2 if reflex else 0)
    i_cm = i_dr + nr
    n = i_cm + nc
    # Each of the sample's quantities as a row over the state (its coefficients).
    cmd = np.zeros(n)
    cmd[0], cmd[1] = -k_sw, -b_sw
    tm = np.zeros(n)
    tmd = np.zeros(n)
    if form == 1.0:
        tm[:] = g0 * cmd
        tm[i_tm] += f00
        tm[i_tm + 1] += f01
        tmd[:] = g1 * cmd
        tmd[i_tm] += f10
        tmd[i_tm + 1] += f11
    elif form == 2.0:
        # cmd_{n−m}: this sample's command for m = 0, else the ring's entry m − 1.
        for m, c in ((n_lag, 1.0 - frac), (n_lag + 1, frac)):
            if c == 0.0:
                continue
            if m == 0:
                tm += c * cmd
            else:
                tm[i_cm + m - 1] += c
    else:
        tm[:] = alpha * cmd
        if n_tm:
            tm[i_tm] += 1.0 - alpha
    # The torque applied over the sample: the lag's mean over it (tm is its value at the end).
    applied = tm.copy()
    if form == 1.0:
        applied[:] = m2 * cmd
        applied[i_tm] += m0
        applied[i_tm + 1] += m1
    elif form == 0.0:
        applied[:] = (1.0 - m0) * cmd
        if n_tm:
            applied[i_tm] += m0
    drive = np.zeros(n)
    drive[2], drive[3] = k_p, k_v
    ra = np.zeros(n)
    rad = np.zeros(n)
    if reflex:
        delayed = np.zeros(n)
        if nr:
            delayed[i_dr + nr - 1] = 1.0
        else:
            delayed[:] = drive
        rad[i_ra + 1] = 1.0 - dt * 2.0 * ze * w
        rad[i_ra] = -dt * w * w
        rad -= dt * w * w * delayed
        ra[:] = dt * rad
        ra[i_ra] += 1.0
    A = np.zeros((n, n))
    for r in range(4):
        for c in range(4):
            A[r, c] = Ad[r, c]
        A[r, 1] -= Bd[r, 2] * b_v
        for c in range(n):
            A[r, c] += Bd[r, 0] * applied[c] + Bd[r, 1] * ra[c]
    if n_tm:
        A[i_tm] = tm
    if n_tm == 2:
        A[i_tm + 1] = tmd
    if reflex:
        A[i_ra] = ra
        A[i_ra + 1] = rad
    if nr:
        A[i_dr] = drive
        for j in range(1, nr):
            A[i_dr + j, i_dr + j - 1] = 1.0
    if nc:
        A[i_cm] = cmd
        for j in range(1, nc):
            A[i_cm + j, i_cm + j - 1] = 1.0
    return A


def is_stable(lp: Loop) -> bool:
    A = closed_loop_matrix(lp)
    return bool(np.all(np.isfinite(A))) and float(np.max(np.abs(np.linalg.eigvals(A)))) < 1.0


def within_linear_range(trial, lp: Loop, ss: SteadyState, pert: Perturbation) -> bool:
    """Whether the command's and the angle's steady state stay clear of every limit the loop
    applies (hardware.safety). The command is Tp − fb (fb = b_sw ω + k_sw θ); bounded from
    the last command checked over a period by the sum of the feedback's change at the bins,
    and checked over a period (one inverse FFT) where that bound does not settle it."""
    s = trial.safety.kernel_vector(trial.fs_hz)
    max_t, max_step, limit, zone = s[0] * LIMIT_MARGIN, s[1] * LIMIT_MARGIN, s[2], s[3]
    if not float(np.sum(np.abs(ss.x[0]))) < LIMIT_MARGIN * (limit - zone):
        return False
    fb = lp.b_sw * ss.x[1] + lp.k_sw * ss.x[0]
    fb0, top0, step0 = pert.checked[0]
    change = np.abs(fb - fb0)
    if (
        top0 + np.sum(change) < max_t
        and step0 + np.sum(change * np.abs(1.0 - pert.z.conj())) < max_step
    ):
        return True
    P = trial.stop - trial.start
    full = np.zeros(P // 2 + 1, dtype=complex)
    full[trial.bins[pert.driven]] = fb * (P / 2.0)
    cmd = trial.tp[trial.start : trial.stop] - scipy.fft.irfft(full, P)
    top = float(np.max(np.abs(cmd)))
    step = float(np.max(np.abs(np.diff(np.concatenate([cmd, cmd[:1]])))))
    pert.checked[0] = (fb, top, step)
    return top < max_t and step < max_step


def _at(S: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """Re Σ_k S_k·phase_k (phase = z_k^{m − start} for sample m); S (…, nb)."""
    return (S @ phase).real


def set_initial_state(world, lp: Loop, ss: SteadyState, pert: Perturbation) -> None:
    """Put every state of ``world`` (after ``begin_trial``) where the steady state has it
    before sample ``pert.periodic_from``: the rings at position 0, so that the kernel's first
    read is the oldest entry."""
    at0 = pert.z_from
    before = at0 * pert.z.conj()
    world.x[:] = _at(ss.x, at0)
    st = world.st
    st[W.S_TM] = _at(ss.tm, before)
    st[W.S_TMD] = _at(ss.tmd, before)
    st[W.S_RA] = _at(ss.ra, before)
    st[W.S_RAD] = _at(ss.rad, before)
    st[W.S_CMD] = _at(ss.cmd, before)
    st[W.S_RPOS] = st[W.S_SPOS] = st[W.S_CPOS] = 0.0
    nr = len(world.ring_r)
    if nr:
        # Entry i is read at sample m0 + i: the drive of n_r − i samples before m0.
        world.ring_r[:] = _at(ss.drive, _before(at0, pert.z, nr)[:, ::-1])
    ns = len(world.ring_s)
    if ns:
        # The torque reading's delay, likewise (the diagnosis applies it outside the world,
        # simulate._split; a caller may not).
        world.ring_s[:] = _at(ss.td, _before(at0, pert.z, ns)[:, ::-1])
    ring = st[W.N_STATE :]
    nc = len(ring)
    if nc:
        # Entry nc − j holds the command of j samples before m0 (entry 0 is written first).
        ring[1:] = _at(ss.cmd, _before(at0, pert.z, nc - 1)[:, ::-1])


def _before(at0: np.ndarray, z: np.ndarray, n: int) -> np.ndarray:
    """(nb, n): the phases of the n samples before m0, column j: j + 1 samples before."""
    steps = np.repeat(z.conj()[:, None], n, axis=1)
    return at0[:, None] * np.cumprod(steps, axis=1)


def spectra(trial, ss: SteadyState, pert: Perturbation) -> np.ndarray:
    """(4, nb) as :func:`analysis.diagnosis.data.measurement_spectra` gives them for the
    steady state: θ and Td with the ramp removed, then raw (zero at the bins the
    perturbation does not drive). The ramp is zero where the sample after the segment is
    simulated; where it is not, the ramp is taken from the last step extrapolated, as there.
    """
    out = np.zeros((4, pert.n_bins), dtype=complex)
    out[2, pert.driven] = ss.theta
    out[3, pert.driven] = ss.td
    if trial.stop < trial.n_sim:
        out[:2] = out[2:]
        return out
    # Samples start, stop − 2, stop − 1: z^0, z^{−2}, z^{−1} (z^P = 1).
    both = ss.rows[[ROWS.index("theta"), ROWS.index("td")]]
    zi = pert.z.conj()
    delta = 2.0 * _at(both, zi) - _at(both, zi * zi) - both.sum(axis=1).real
    out[:2] = out[2:] + delta[:, None] * pert.ramp
    return out
