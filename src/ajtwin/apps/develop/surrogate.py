"""The ink's line after the tests: the physics ensemble and a data-driven residual, updated.

Each output k (L_w, L_o, and Q_m when a record gave it) is modelled in logarithms,
f_k = ln(y_k + c_k) (c = 1 µm for the line, 0 for Q_m: an ink's levels and gains act as
factors, and the ensemble is then nearly Gaussian), at inputs z as

    f_k(z) = μ_k(z) + a_k(z)ᵀ w + r_k(z),        w ~ N(0, I_N),  r_k ~ GP(0, κ_k),

with μ_k the prior ensemble's mean, a_k(z) = (F_k(z) − μ_k(z))/√N its N draws centred
(:class:`ajtwin.apps.develop.prior.LineEnsemble`): the physics part, one weight vector w
shared by every output, so a test's L_w also teaches L_o and Q_m through the ink they share.
r_k is the data-driven part, a Gaussian process with a squared-exponential kernel over the
scaled inputs, κ_k(z, z') = s_k² exp(−|z − z'|²/2ℓ²), its amplitude s_k a relative share of
the line (``data/ink_prior.toml [residual]``) times a multiplier λ_k ∈ {1, 2.5, 6} and ℓ one
of two lengthscales, chosen by the tests' marginal likelihood with a prior that favours
λ = 1 (Rasmussen & Williams 2006, §5.4): a line that follows another law than the model's
makes the data-driven part larger, the physics part then learning less. A test reads
y = f_k(z) + ε, ε ~ N(0, σ²) with σ² the reading's own variance plus the line's
repeatability (in logarithms: relative). The posterior is Gaussian (Rasmussen & Williams
2006, eq. 2.25–2.26, with the kernel A Aᵀ + K_r):

    mean_k(z) = μ_k(z) + q(z)ᵀ C⁻¹ (y − μ_o),    var_k(z) = |a_k(z)|² + s_k(z)² − q(z)ᵀ C⁻¹ q(z),
    C = A_o A_oᵀ + K_r(o, o) + diag(σ²),        q(z) = A_o a_k(z) + K_r(o, z).

Examples
--------
>>> from ajtwin.apps.develop.prior import InkPrior, InputBox
>>> prior = InkPrior.load()
>>> box = InputBox.from_limits(None, speed_mm_s=2.0)
>>> tests = Observations.empty()
>>> post = LinePosterior(prior, box, tests)
>>> p = post.predict(box.inputs(np.array([[0.5, 0.4, 0.4]])))
>>> bool(p.linewidth_sd[0] > 0.2)   # the prior alone: wide (σ of ln L_w: > 20 %)
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ajtwin.apps.develop.prior import INK_VALUES

#: Output kinds of a test observation.
LINEWIDTH, OVERSPRAY, MATERIAL_FLOW = 0, 1, 2
#: c_k of f_k = ln(y_k + c_k) [µm, µm, mL/s]
LOG_OFFSET = np.array([1.0, 1.0, 0.0])
#: the residual's multipliers λ and lengthscale factors tried, with their prior weights
RESIDUAL_MULTIPLIERS = ((1.0, 0.6), (2.5, 0.25), (6.0, 0.15))
LENGTHSCALE_FACTORS = ((1.0, 0.7), (0.55, 0.3))


def to_log(values, kinds) -> np.ndarray:
    """ln(y + c_k) of values of the given output kinds."""
    return np.log(np.maximum(np.asarray(values, float) + LOG_OFFSET[kinds], 1e-30))


@dataclass
class Observations:
    """Observations of the ink: (n,) kinds, (n, 4) inputs, (n,) values and their σ."""

    kinds: np.ndarray
    inputs: np.ndarray
    values: np.ndarray
    sd: np.ndarray

    @classmethod
    def empty(cls) -> Observations:
        """No tests yet."""
        return cls(np.zeros(0, int), np.zeros((0, 4)), np.zeros(0), np.zeros(0))

    def __len__(self) -> int:
        return len(self.values)


@dataclass
class Prediction:
    """The posterior at M inputs, in logarithms: means and σ of ln(L_w + 1 µm),
    ln(L_o + 1 µm), ln Q_m, and the line's sensitivities ∂L_w/∂ln d_a, ∂L_w/∂ln φ_A [µm]
    (posterior means). :meth:`in_units` gives a value and its 2σ half-width in µm."""

    linewidth: np.ndarray
    linewidth_sd: np.ndarray
    overspray: np.ndarray
    overspray_sd: np.ndarray
    material_flow: np.ndarray
    material_flow_sd: np.ndarray
    droplet_sensitivity: np.ndarray
    aerosol_sensitivity: np.ndarray

    def in_units(self, kind: int, index) -> tuple[float, float]:
        """(median, half-width of the ±2σ band) of output ``kind`` at a point, display units."""
        mean, sd = [
            (self.linewidth, self.linewidth_sd),
            (self.overspray, self.overspray_sd),
            (self.material_flow, self.material_flow_sd),
        ][kind]
        m, s = float(mean[index]), float(sd[index])
        low, high = np.exp(m - 2 * s), np.exp(m + 2 * s)
        return float(np.exp(m) - LOG_OFFSET[kind]), float((high - low) / 2)


class LinePosterior:
    """The ink's settled line given the tests (module docstring).

    Parameters
    ----------
    prior : InkPrior
    box : InputBox
        Scales the inputs for the residual's kernel.
    tests : Observations
    """

    def __init__(self, prior, box, tests: Observations):
        self.prior, self.box, self.tests = prior, box, tests
        residual = prior.settings["residual"]
        self.base_lengthscale = float(residual["lengthscale"])
        self.base_shares = np.array(
            [residual["linewidth_sd_relative"], residual["overspray_sd_relative"], 0.15]
        )
        self.lengthscale, self.shares = self.base_lengthscale, self.base_shares.copy()
        self.multipliers = (1.0, 1.0)
        self._fit()

    def _fields(self, ensemble):
        """Per output kind: (mean (M,), centred draws / √N (N, M))."""
        n = ensemble.linewidth.shape[0]
        out = []
        fields = (ensemble.linewidth, ensemble.overspray, ensemble.material_flow)
        for kind, field in enumerate(fields):
            field = to_log(field, kind)
            mean = field.mean(axis=0)
            out.append((mean, (field - mean) / np.sqrt(n)))
        return out

    def _fit(self) -> None:
        t = self.tests
        if len(t) == 0:
            self._alpha = None
            return
        fields = self._fields(self.prior.ensemble(t.inputs))
        idx = np.arange(len(t))
        self._mean_o = np.array([fields[k][0][i] for k, i in zip(t.kinds, idx)])
        self._a_o = np.stack([fields[k][1][:, i] for k, i in zip(t.kinds, idx)])  # (n, N)
        self._z_o = self.box.scaled(t.inputs)
        self._y = to_log(t.values, t.kinds)
        # a reading's σ in logarithms: relative to the line (plus its offset)
        self._noise = t.sd / (t.values + LOG_OFFSET[t.kinds])
        best = None
        for lw, p_lw in RESIDUAL_MULTIPLIERS:
            for lo, p_lo in RESIDUAL_MULTIPLIERS:
                for ls, p_ls in LENGTHSCALE_FACTORS:
                    shares = self.base_shares * np.array([lw, lo, 1.0])
                    fit = self._factor(shares, self.base_lengthscale * ls)
                    score = fit[2] + np.log(p_lw * p_lo * p_ls)
                    if best is None or score > best[0]:
                        best = (score, shares, self.base_lengthscale * ls, fit, (lw, lo))
        _, self.shares, self.lengthscale, (self._cov, self._alpha, _), self.multipliers = best
        # the weights' posterior mean E[w | tests] = A_oᵀ C⁻¹ (y − μ_o)
        self._weights = self._a_o.T @ self._alpha

    def _factor(self, shares, lengthscale):
        """(C, C⁻¹(y − μ_o), log marginal likelihood) for residual amplitudes
        ``shares`` (per kind, log units) and a lengthscale."""
        kinds = self.tests.kinds
        scale = shares[kinds]
        same = kinds[:, None] == kinds[None, :]
        k_r = self._kernel(self._z_o, self._z_o, lengthscale) * np.outer(scale, scale) * same
        c = self._a_o @ self._a_o.T + k_r + np.diag(self._noise**2)
        c = c + 1e-10 * np.mean(np.diag(c)) * np.eye(len(c))
        r = self._y - self._mean_o
        alpha = np.linalg.solve(c, r)
        log_ml = -0.5 * (r @ alpha + np.linalg.slogdet(c)[1] + len(r) * np.log(2 * np.pi))
        return c, alpha, log_ml

    def _kernel(self, z1, z2, lengthscale=None) -> np.ndarray:
        d2 = ((z1[:, None, :] - z2[None, :, :]) ** 2).sum(axis=-1)
        return np.exp(-0.5 * d2 / (lengthscale or self.lengthscale) ** 2)

    def predict(self, inputs) -> Prediction:
        """The posterior at inputs (M, 4) [mA, sccm, sccm, mm/s]."""
        ensemble = self.prior.ensemble(inputs)
        fields = self._fields(ensemble)
        z = self.box.scaled(inputs)
        moments = []
        for kind, (mean, a) in enumerate(fields):
            scale = np.full_like(mean, self.shares[kind])
            var = (a**2).sum(axis=0) + scale**2
            if self._alpha is not None:
                same = self.tests.kinds == kind
                obs_scale = self.shares[self.tests.kinds] * same
                q = self._a_o @ a + self._kernel(self._z_o, z) * np.outer(obs_scale, scale)
                mean = mean + q.T @ self._alpha
                var = var - (q * np.linalg.solve(self._cov, q)).sum(axis=0)
            moments += [mean, np.sqrt(np.maximum(var, 1e-12))]
        sensitivities = []
        for field in (ensemble.droplet_sensitivity, ensemble.aerosol_sensitivity):
            mean = field.mean(axis=0)
            if self._alpha is not None:
                centred = (field - mean) / np.sqrt(field.shape[0])
                mean = mean + centred.T @ self._weights
            sensitivities.append(mean)
        return Prediction(*moments, *sensitivities)

    def fitted_ink(self) -> dict:
        """The ink's drawn values at the weights' posterior mean (a linearisation: each value
        moved as the ensemble's combination moves the line)."""
        draws = self.prior.draws
        mean = draws.mean(axis=0)
        if self._alpha is None:
            return dict(zip(INK_VALUES, mean.tolist()))
        centred = (draws - mean) / np.sqrt(len(draws))
        return dict(zip(INK_VALUES, (mean + centred.T @ self._weights).tolist()))
