"""The virtual printer's true dynamics: a pure JAX core over pre-drawn processes.

The truth is the model's physics (:func:`ajtwin.model.transition_rates`, θ = 0)
*plus* what the twin does not know, all supplied per second as arrays:

* the droplet size d_a is an external process (drift, wander, lagged response to
  the inputs) — the twin knows only dd_a/dt = θ_da d_a;
* the droplet generation is H·m(t), m = (1 + systematic offset)(1 + slow wander)
  × (atomizer dropout), H clipped at 0 (a generation cannot be negative);
* the tube/nozzle deposition rates are the model's times factors (the clog fault
  raises the nozzle factor from its onset);
* the vial may lose solvent by evaporation, which the twin's vial model lacks;
* the gas that reaches vial, tube and nozzle is the MFC's true (jittery) flow, less
  any leak.

The states are integrated with RK4 sub-steps (the twin uses Euler at 1 s), and a
sixth carried quantity, the ink that reached the substrate, closes the ink balance
V_l(0) − V_l(t) − evaporated = tube deposit + nozzle deposit + substrate.
"""

from __future__ import annotations

import numpy as np

from ajtwin import units
from ajtwin._jax import jax, jnp
from ajtwin.model.atomizer import net_droplet_generation
from ajtwin.model.names import N_STATES
from ajtwin.model.system import output_function, transition_rates


def true_generation(flow_input, vial_volume_ml, generation_multiplier, params):
    """True net droplet generation [mL/s]: max(H, 0) times the truth multiplier."""
    generation = net_droplet_generation(
        flow_input[..., 1], vial_volume_ml, flow_input[..., 0], params.generation_fit
    )
    return jnp.maximum(generation, 0.0) * generation_multiplier


def truth_rates(x, flow_input, drivers, params):
    """Per-second rates of the true states (display units), d_a held (rate 0).

    Parameters
    ----------
    x : array (5,)
        True state [d_a µm, V_l mL, ΔR_T µm, ΔR_N µm, φ_A].
    flow_input : array (3,)
        What really reaches the head: [I_A mA, Q_c sccm (after any leak), Q_s sccm].
    drivers : array (4,)
        [generation multiplier, tube deposition factor, nozzle deposition factor,
        vial evaporation mL/s].
    params : PhysicalParameters

    Returns
    -------
    (array (5,), float)
        State rates and the rate of ink onto the substrate [mL/s].
    """
    generation_multiplier, tube_factor, nozzle_factor, evaporation = (drivers[i] for i in range(4))
    nominal = transition_rates(x, flow_input, jnp.zeros(N_STATES), params)
    vial_ml, aerosol = x[1], x[4]
    headspace = units.m3_to_ml(params.vial_volume) - vial_ml
    # The model's dφ_A/dt contains H/(V_v − V_l); swap in the true generation, and
    # add the head-space growth by evaporation to its φ_A dV_l/dt dilution term.
    nominal_generation = net_droplet_generation(
        flow_input[1], vial_ml, flow_input[0], params.generation_fit
    )
    generation = true_generation(flow_input, vial_ml, generation_multiplier, params)
    d_aerosol = nominal[4] + (generation - nominal_generation - aerosol * evaporation) / headspace
    d_vial = nominal[1] - evaporation
    d_tube = tube_factor * nominal[2]
    d_nozzle = nozzle_factor * nominal[3]
    # Ink volume flows [mL/s]: out of the vial, into the two annular deposits.
    out_of_vial = aerosol * units.sccm_to_ml_per_s(flow_input[1])
    tube_radius = params.tube_radius - units.um_to_m(x[2])
    nozzle_radius = params.nozzle_radius - units.um_to_m(x[3])
    into_tube = units.m3_to_ml(
        2 * jnp.pi * tube_radius * params.tube_length * units.um_to_m(d_tube)
    )
    into_nozzle = units.m3_to_ml(
        2 * jnp.pi * nozzle_radius * params.nozzle_length * units.um_to_m(d_nozzle)
    )
    rates = jnp.stack([jnp.zeros(()), d_vial, d_tube, d_nozzle, d_aerosol])
    return rates, out_of_vial - into_tube - into_nozzle


def _rk4(x, substrate, flow_input, drivers, params, dt):
    def f(state):
        return truth_rates(state, flow_input, drivers, params)

    k1, s1 = f(x)
    k2, s2 = f(x + 0.5 * dt * k1)
    k3, s3 = f(x + 0.5 * dt * k2)
    k4, s4 = f(x + dt * k3)
    x_next = x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    substrate_next = substrate + dt / 6.0 * (s1 + 2 * s2 + 2 * s3 + s4)
    return x_next, substrate_next


def _scan_seconds(
    carry, droplet_um, droplet_next_um, flow_inputs, drivers, params, coefficients, substeps
):
    """``lax.scan`` over seconds; carry = (state, substrate ink). Pure and jit-able.

    Emits per second the state, the substrate ink, the noise-free true outputs and the
    true generation, so nothing downstream compiles per print length.
    """
    dt = 1.0 / substeps

    def body(carry, per_second):
        x, substrate = carry
        d_a, flow_input, driver, d_a_next = per_second
        x = x.at[0].set(d_a)
        state_k, substrate_k = x, substrate
        outputs_k = output_function(x, flow_input, params, coefficients)
        generation_k = true_generation(flow_input, x[1], driver[0], params)

        def sub(c, _):
            return _rk4(c[0], c[1], flow_input, driver, params, dt), None

        (x, substrate), _ = jax.lax.scan(sub, (x, substrate), None, length=substeps)
        x = x.at[0].set(d_a_next)
        return (x, substrate), (state_k, substrate_k, outputs_k, generation_k)

    return jax.lax.scan(body, carry, (droplet_um, flow_inputs, drivers, droplet_next_um))


#: The truth over a run of seconds, compiled; shared by the whole-print integration
#: and the stepper (a print second by second).
scan_truth_seconds = jax.jit(_scan_seconds, static_argnames=("substeps",))

#: Seconds per compiled scan chunk: every print length reuses one compiled chunk.
CHUNK_S = 600


def integrate_truth(x0, droplet_um, flow_inputs, drivers, params, coefficients, substeps=1):
    """True state trajectory over T seconds.

    A ``lax.scan`` over fixed chunks of :data:`CHUNK_S` seconds (the last one padded and
    trimmed), so prints of any length share one compilation.

    Parameters
    ----------
    x0 : array (5,)
        True state at t = 0 (its d_a is replaced by ``droplet_um[0]``).
    droplet_um : array (T,)
        The external droplet-size process d_a(t_k) [µm].
    flow_inputs : array (T, 3)
        [I_A mA, Q_c sccm, Q_s sccm] reaching the head in second k.
    drivers : array (T, 4)
        See :func:`truth_rates`.
    params : PhysicalParameters
    coefficients : array (2, 8)
        The true line-output coefficients.
    substeps : int
        RK4 steps per second.

    Returns
    -------
    dict of numpy arrays
        ``states`` (T, 5) at t_k = k s, ``substrate_ink_mL`` (T,) cumulative ink on the
        substrate, ``outputs`` (T, 5) noise-free true outputs, ``generation_ml_s`` (T,).
    """
    droplet_um = np.asarray(droplet_um, dtype=float)
    flow_inputs = np.asarray(flow_inputs, dtype=float)
    drivers = np.asarray(drivers, dtype=float)
    n = len(droplet_um)
    droplet_next = np.concatenate([droplet_um[1:], droplet_um[-1:]])
    pad = (-n) % CHUNK_S

    def padded(a):
        return np.concatenate([a, np.repeat(a[-1:], pad, axis=0)]) if pad else a

    arrays = [padded(a) for a in (droplet_um, droplet_next, flow_inputs, drivers)]
    carry = (jnp.asarray(x0, dtype=float), jnp.zeros(()))
    coefficients = jnp.asarray(coefficients, dtype=float)
    pieces = []
    for start in range(0, n + pad, CHUNK_S):
        chunk = [a[start : start + CHUNK_S] for a in arrays]
        carry, emitted = scan_truth_seconds(
            carry, *chunk, params, coefficients, substeps=int(substeps)
        )
        pieces.append([np.asarray(e) for e in emitted])
    names = ("states", "substrate_ink_mL", "outputs", "generation_ml_s")
    return {name: np.concatenate([p[i] for p in pieces])[:n] for i, name in enumerate(names)}
