"""The simulator driven by a measured trial: the measured perturbation torque and grip force.

``simulate_trial`` runs :class:`hardware.sim.world.World` (the same compiled kernel as
``steerlab simulate``) at the trial's sample rate on the measured perturbation torque.
Everything random is switched off: no remnant (unless one is given), no sensor noise, no
quantisation; the model's prediction is the deterministic response to the measured
perturbation in its periodic steady state, where the perturbation is periodic
(:mod:`analysis.diagnosis.steady_state`): a linear model's is computed bin by bin there,
any other model's simulated from that steady state. Elsewhere the world starts from rest at
the trial's first sample.

The world draws its exogenous signals (remnant, sensor noise, grip force) from a noise-block
object; :class:`ReplayBlocks` stands in for it and replays measured or given signals instead,
so the grip-scheduled stiffness follows the grip force that was actually measured. This uses
the world's ``noise`` attribute and the block protocol of ``hardware.sim.world.NoiseBlocks``
(``block`` samples per ``next_block()`` call, the same keys); a test guards that contract.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from steerlab.analysis.diagnosis import steady_state
from steerlab.analysis.diagnosis.data import TrialData, measurement_spectra
from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.hardware.sim.physiology import ArmParams, ConditionBehaviour
from steerlab.hardware.sim.world import NOISELESS_SENSORS as NOISELESS
from steerlab.hardware.sim.world import World, WorldConfig


class ReplayBlocks:
    """Duck-typed ``NoiseBlocks``: replays given remnant and grip force, zero sensor noise.

    ``block``: samples per block (default one second, as the world's own). The diagnosis
    replays a whole trial as one block: the world runs one compiled call per block, and with
    one-second blocks the Python work around those calls took as long as the calls themselves
    (profile of a small study: 1.09 million blocks for 21 778 simulations)."""

    def __init__(
        self,
        fs_hz: float,
        grip: np.ndarray,
        remnant: np.ndarray | None = None,
        block: int | None = None,
    ):
        self.block = int(block) if block else int(round(fs_hz))
        self.grip = np.asarray(grip, dtype=float)
        self.remnant = None if remnant is None else np.asarray(remnant, dtype=float)
        self.i = 0

    def _slice(self, x: np.ndarray) -> np.ndarray:
        y = x[self.i : self.i + self.block]
        if len(y) < self.block:
            fill = y[-1] if len(y) else 0.0
            y = np.concatenate([y, np.full(self.block - len(y), fill)])
        return y

    def next_block(self) -> dict[str, np.ndarray]:
        z = np.zeros(self.block)
        g = self._slice(self.grip)
        rem = z if self.remnant is None else self._slice(self.remnant)
        self.i += self.block
        return {
            "remnant_Nm": rem,
            "velocity_noise": z,
            "torque_noise": z,
            "grip_true_N": g,
            "grip_force_left_N": 0.5 * g,
            "grip_force_right_N": 0.5 * g,
        }


def behaviour_for(trial: TrialData, arm: ArmParams) -> ConditionBehaviour:
    # The grip-scheduled stiffness is relative to the grip's mean: the trial's own mean.
    mean, sd = trial.grip_stats
    return ConditionBehaviour(arm, mean, sd, 0.0)


def trial_world(trial: TrialData, mechanisms: Mechanisms) -> World:
    """The noiseless world at the trial's rate, with the trial's wheel (nominal or measured)
    and the recording rig's command limits (``TrialData.safety``)."""
    cfg = WorldConfig(
        fs_hz=trial.fs_hz,
        wheel_inertia_kgm2=trial.wheel.inertia_kgm2,
        sensors=NOISELESS,
        mechanisms=mechanisms,
        wheel_rendering=trial.wheel_rendering,
    )
    return World(cfg, wheel=trial.wheel, safety=trial.safety)


def simulate_trial(
    trial: TrialData,
    arm: ArmParams,
    mechanisms: Mechanisms,
    remnant: np.ndarray | None = None,
    start: SteadyStart | None = None,
) -> dict[str, np.ndarray]:
    """The simulated wheel angle and driver torque (``wheel_angle_rad``,
    ``driver_torque_Nm``) for the trial's first ``n_sim`` samples, as the world gives them.

    Where the trial's perturbation is periodic (:func:`steady_state.perturbation`), the world
    starts where it becomes so, with every state at the periodic steady state of the model's
    linear part (its dry friction, stiffening, grip coupling and imbalance taken out); the
    samples before are NaN. Elsewhere, and where that linear part is unstable, it starts
    from rest at the first sample (:func:`steady_start`). ``start``: :func:`steady_start` of
    the same trial, arm and mechanisms, computed once for several runs."""
    world = trial_world(trial, mechanisms)
    world.begin_trial(behaviour_for(trial, arm), 0.5, seed=0)
    start = steady_start(trial, arm, mechanisms) if start is None else start
    m0 = 0
    if start.steady is not None:
        pert, lp, ss = start.steady
        m0 = pert.periodic_from
        steady_state.set_initial_state(world, lp, ss, pert)
    n = trial.n_sim
    world.noise = ReplayBlocks(
        trial.fs_hz, trial.grip[m0:n], None if remnant is None else remnant[m0:n], block=n - m0
    )
    out = world.run(trial.tp[m0:n])
    channels = {}
    for name in ("wheel_angle_rad", "driver_torque_Nm"):
        x = np.empty(n)
        x[:m0] = np.nan
        x[m0:] = out[name]
        channels[name] = x
    return channels


@dataclass(frozen=True)
class SteadyStart:
    """Where a simulation of a trial starts: (perturbation, loop, steady state) of the
    model's linear part, or None (from rest)."""

    steady: tuple[steady_state.Perturbation, steady_state.Loop, steady_state.SteadyState] | None


def steady_start(
    trial: TrialData, arm: ArmParams, mechanisms: Mechanisms, before: int = 0
) -> SteadyStart:
    """From the steady state of the model's linear part, where the trial's perturbation is
    periodic from at least ``before`` samples before the segment; from rest elsewhere, and
    where that linear part is unstable: its periodic orbit would be one the loop never
    leaves in a simulation (rounding is all that would seed its growing mode), and the fit
    must see an unstable model diverge (or run into the rig's limits) as it does from rest."""
    pert = steady_state.perturbation(trial)
    if pert is None or trial.start - pert.periodic_from < before:
        return SteadyStart(None)
    lp = steady_state.loop(trial, arm, steady_state.linear_part(mechanisms))
    if not steady_state.is_stable(lp):
        return SteadyStart(None)
    return SteadyStart((pert, lp, steady_state.steady_state(lp, pert)))


def _split(mechanisms: Mechanisms) -> tuple[Mechanisms, float]:
    """The mechanisms the world runs, and the driver-torque reading delay applied afterwards.

    The sensor delay is applied in the frequency domain (e^{−jωτ}): exactly the world's
    ring-buffer delay for a whole number of samples in the periodic steady state, and a smooth
    interpolation in between, so the delay can be fitted as a continuous parameter. Drift acts
    between trials (through each trial's arm parameters), never inside the world.
    """
    tau = float(mechanisms.sensor_delay.delay_s)
    world_mech = replace(
        mechanisms,
        sensor_delay=type(mechanisms.sensor_delay)(),
        drift=type(mechanisms.drift)(),
    )
    return world_mech, tau


NONLINEAR = ("coulomb_friction", "stiffness_nonlinearity")


def needs_remnant(mechanisms: Mechanisms) -> bool:
    """Whether the model's response to the perturbation depends on the remnant's motion."""
    return any(getattr(mechanisms, n).active for n in NONLINEAR)


def _spectra(trial: TrialData, out: dict[str, np.ndarray]) -> np.ndarray:
    # A diverged simulation (an unstable candidate) gives non-finite spectra; the fit treats
    # them as infinitely bad, no need for warnings.
    with np.errstate(all="ignore"):
        return measurement_spectra(
            out["wheel_angle_rad"], out["driver_torque_Nm"], trial.start, trial.stop, trial.bins
        )


def simulated_spectra(trial: TrialData, arm: ArmParams, mechanisms: Mechanisms) -> np.ndarray:
    """Complex (5, n_bins): the model's θ and Td on the trial's bins, given the perturbation
    (ramp removed, then raw, as :func:`analysis.diagnosis.data.measurement_spectra`), and
    the factor e^{jωτ} that undoes the model's torque-reading delay τ.

    A linear model's response to the perturbation does not depend on the remnant, and is
    simulated without it. Friction and a cubic stiffness respond to the total motion: the
    remnant's slow wander changes how they act on the perturbation's response (noise-free
    simulation under-estimated a 0.2 N·m friction by 30 %). For those the prediction is the
    mean of two runs with the trial's remnant estimate added and subtracted
    (``trial.remnant``, see :func:`reconstruct_remnant`): the remnant's own linear response
    cancels, its effect on the nonlinearity stays.
    """
    mech, tau = _split(mechanisms)
    rems = trial.remnant
    Y = _steady_spectra(trial, arm, mech)
    if Y is None and rems and needs_remnant(mech):
        start = steady_start(trial, arm, mech)
        # The spectra are linear in the series: the mean run's spectra, one transform.
        runs = [
            simulate_trial(trial, arm, mech, sign * r, start) for r in rems for sign in (1.0, -1.0)
        ]
        with np.errstate(all="ignore"):  # a diverged run: non-finite, as in _spectra
            mean = {k: np.mean([o[k] for o in runs], axis=0) for k in runs[0]}
        Y = _spectra(trial, mean)
    elif Y is None:
        Y = _spectra(trial, simulate_trial(trial, arm, mech))
    # Row 4: the factor that undoes the reading delay in the wheel-equation channel (see
    # analysis.diagnosis.fit.raw_vectors); 1 without a delay.
    undo = np.ones(len(trial.bins), dtype=complex)
    if tau:
        shift = np.exp(-2j * np.pi * trial.freqs_hz * tau)
        Y = np.asarray(Y)
        Y[1] = Y[1] * shift
        Y[3] = Y[3] * shift
        undo = 1.0 / shift
    return np.vstack([Y, undo[None, :]])


def _steady_spectra(trial: TrialData, arm: ArmParams, mech: Mechanisms) -> np.ndarray | None:
    """The model's spectra from its periodic steady state, bin by bin, where that route
    applies (:mod:`analysis.diagnosis.steady_state`: a linear, time-invariant, stable model
    clear of the rig's limits, on a periodic perturbation); else None."""
    pert = steady_state.perturbation(trial)
    if pert is None or not steady_state.is_linear_time_invariant(mech):
        return None
    lp = steady_state.loop(trial, arm, mech)
    if not steady_state.is_stable(lp):
        return None
    ss = steady_state.steady_state(lp, pert)
    if not steady_state.within_linear_range(trial, lp, ss, pert):
        return None
    return steady_state.spectra(trial, ss, pert)


def _remnant_spectrum(trial: TrialData, arm: ArmParams) -> tuple[np.ndarray, np.ndarray]:
    """(frequencies, spectrum of the driver's own torque n) over the analysed segment, with
    θ_h = θ − Td/(b_c s + k_c) and n = (I_i s² + b_i s + k_i) θ_h − Td."""
    P = trial.stop - trial.start
    th = np.fft.rfft(trial.theta)
    td = np.fft.rfft(trial.td)
    f = np.fft.rfftfreq(P, 1.0 / trial.fs_hz)
    s = 2j * np.pi * f
    n_hat = (arm.I_i * s**2 + arm.b_i * s + arm.k_i) * (th - td / (arm.b_c * s + arm.k_c)) - td
    return f, n_hat


def reconstruct_remnant(
    trial: TrialData, arm: ArmParams, f_max_hz: float = 3.0, seed: int = 0
) -> np.ndarray:
    """A remnant torque series for the trial (N·m, ``n_sim`` samples): the hand torque that the
    arm model needs to produce the measured θ and Td at the unexcited bins below ``f_max_hz``.

    With θ_h = θ − Td/(b_c s + k_c) and n = (I_i s² + b_i s + k_i) θ_h − Td; excited bins are
    not used (there the perturbation dominates and the model's error would leak in), and high
    frequencies neither (there the inverse arm amplifies sensor noise, and the remnant has no
    power). The analysed segment's series is extended periodically over the run-in.
    """
    P = trial.stop - trial.start
    f, n_hat = _remnant_spectrum(trial, arm)
    band = (f > 0) & (f <= f_max_hz)
    excited = np.zeros(len(f), dtype=bool)
    excited[trial.bins[trial.excited]] = True
    # At excited bins the remnant is hidden under the perturbation's response; leaving those
    # bins empty would take up to half of the remnant's power below 0.7 Hz (two bins of every
    # four are excited there). They get the power of their unexcited neighbours, with phases
    # from a fixed generator (only the remnant's amplitude matters to the nonlinearity).
    quiet = np.flatnonzero(band & ~excited)
    fill = np.flatnonzero(band & excited)
    rng = np.random.default_rng(P + seed)
    for k in fill:
        near = quiet[np.argsort(np.abs(quiet - k))[:4]]
        power = np.mean(np.abs(n_hat[near]) ** 2) if len(near) else 0.0
        n_hat[k] = np.sqrt(power) * np.exp(2j * np.pi * rng.random())
    n_hat[~band] = 0.0
    seg = np.fft.irfft(n_hat, P)
    # Sample i of the simulation is sample (i − start) mod P of the periodic segment.
    idx = (np.arange(trial.n_sim) - trial.start) % P
    return seg[idx]


def simulated_segment(
    trial: TrialData, arm: ArmParams, mechanisms: Mechanisms
) -> tuple[np.ndarray, np.ndarray]:
    """The model's (θ, Td) over the analysed segment, mean-free, for time-domain comparisons
    (averaged over the remnant realisations exactly as :func:`simulated_spectra`)."""
    mech, tau = _split(mechanisms)
    # The reading delay's interpolation reads τ·fs samples before the segment.
    start = steady_start(trial, arm, mech, before=int(np.ceil(tau * trial.fs_hz)) + 2)
    runs = (
        [
            simulate_trial(trial, arm, mech, sign * r, start)
            for r in trial.remnant
            for sign in (1.0, -1.0)
        ]
        if trial.remnant and needs_remnant(mech)
        else [simulate_trial(trial, arm, mech, None, start)]
    )
    th = np.asarray(sum(o["wheel_angle_rad"] for o in runs)) / len(runs)
    td = np.asarray(sum(o["driver_torque_Nm"] for o in runs)) / len(runs)
    if tau:
        n = np.arange(len(td), dtype=float)
        td = np.interp(n - tau * trial.fs_hz, n, td)
    th = th[trial.start : trial.stop]
    td = td[trial.start : trial.stop]
    return th - th.mean(), td - td.mean()


def remnant_spectrum_fit(
    trial: TrialData, arm: ArmParams, f_max_hz: float = 3.0
) -> tuple[float, float]:
    """(SD in N·m, corner in Hz) of a first-order (AR(1)) remnant, the simulator's model,
    fitted by maximum likelihood to the remnant torque reconstructed at the unexcited bins
    below ``f_max_hz`` (see :func:`reconstruct_remnant`)."""
    P = trial.stop - trial.start
    fs = trial.fs_hz
    f, n_hat = _remnant_spectrum(trial, arm)
    use = (f > 0) & (f <= f_max_hz)
    use[trial.bins[trial.excited]] = False
    k = np.flatnonzero(use)
    if len(k) < 5:
        return float("nan"), float("nan")
    power = np.abs(n_hat[k]) ** 2
    w = 2 * np.pi * f[k] / fs

    def m2ll(z: np.ndarray) -> float:
        sd, a = np.exp(z[0]), 1.0 / (1.0 + np.exp(-z[1]))
        m = P * sd**2 * (1 - a * a) / np.abs(1 - a * np.exp(-1j * w)) ** 2
        return float(np.sum(np.log(m) + power / m))

    from scipy.optimize import minimize

    a0 = np.exp(-2 * np.pi * 0.4 / fs)
    z0 = np.array([np.log(max(np.sqrt(np.mean(power) / P), 1e-6)), np.log(a0 / (1 - a0))])
    z = minimize(m2ll, z0, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-9}).x
    sd, a = float(np.exp(z[0])), float(1.0 / (1.0 + np.exp(-z[1])))
    return sd, float(-np.log(a) * fs / (2 * np.pi))


def kernel_wheel_impedance(
    trial: TrialData, arm: ArmParams, mechanisms: Mechanisms, duration_s: float = 20.0
) -> np.ndarray:
    """−Td/θ at the trial's bins for a torque applied at the hands, as the world computes it.

    For any input on the arm's side (remnant, reflexes) the wheel ties θ and Td together by the
    wheel's impedance. The analytic I s² + b s + k is off by 1–2 % at a 200 Hz loop (the
    rendered spring and damper act on sampled, held values), which left a structured trace of
    the remnant in the wheel-equation channel; this is the kernel's own relation, from the
    impulse response to a hand-torque impulse (DTFT at the bins).
    """
    mech, _ = _split(mechanisms)
    # Dry friction has no impedance: linearised at rest (the impulse response) it is a damping
    # F_c/ε, 15 N·m·s/rad for a measured 0.15 N·m, which no motion of the remnant's size sees.
    mech = replace(mech, coulomb_friction=type(mech.coulomb_friction)())
    fs = trial.fs_hz
    n = int(round(duration_s * fs))
    world = trial_world(trial, mech)
    world.begin_trial(behaviour_for(trial, arm), 0.5, seed=0)
    impulse = np.zeros(n)
    impulse[0] = 1.0
    world.noise = ReplayBlocks(fs, np.full(n, float(np.mean(trial.grip))), impulse, block=n)
    out = world.run(np.zeros(n))
    # The bins are k/P of the sample rate: an FFT of length P (impulse response zero-padded,
    # it has decayed long before) evaluates the DTFT exactly there.
    P = trial.stop - trial.start
    m = min(n, P)
    num = np.fft.rfft(out["driver_torque_Nm"][:m], P)[trial.bins]
    den = np.fft.rfft(out["wheel_angle_rad"][:m], P)[trial.bins]
    return -num / den
