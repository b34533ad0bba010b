"""Consistency of a pose solve with its own error model: the χ² gate and the prior–measurement test.

Specification: spc-algorithms.md §10.3 (the weighted least-squares pose with its a-priori term, L15
§2.2 Eq. 2.8–2.19); the tests are the standard ones of linear-Gaussian estimation (Bar-Shalom, Li &
Kirubarajan 2001, *Estimation with Applications to Tracking and Navigation*, §5.4: the normalised
innovation squared and the χ² test of the minimised cost).

**χ² gate.**  With measurement weights Wᵢ that are the inverse covariances of the pixel errors and an
honest prior, the minimised cost J = Σᵢ rᵢᵀWᵢrᵢ + ‖P₀^(−1/2)(χ̂ − χ₀)‖² is χ²-distributed with
dof = 2·M + (prior equations) − 6 degrees of freedom.  J above its ``quantile`` (99.9 %) says the
error model is wrong — the residuals are larger than the weights claim (model error, a wrong
landmark, a bad maplet) — and the pose is *inconsistent*: never ``ok``.  The landmarks with the largest
weighted residuals ρᵢ² = rᵢᵀWᵢrᵢ are named with their share of the measurement χ².  (The covariance
is then reported scaled by J/dof, :mod:`spctool.stages.pose`.)

**Prior–measurement test.**  For a linear problem with honest prior covariance P₀ and a-posteriori
covariance P, the change of the estimate from the a-priori state, d = χ̂ − χ₀, has covariance
P₀ − P (the information the measurements add is exactly what shrinks P₀ to P), so

    q = dᵀ (P₀ − P)⁺ d  ~  χ²ₖ,

the normalised innovation squared, k the number of directions in which the measurements reduce the prior
variance at all (eigenvalues of S⁻¹(P₀ − P)S⁻¹ = I − S⁻¹PS⁻¹ above ``min_gain``, S = diag(σ₀):
directions the measurements do not inform carry no test). When the measurements' own residuals say their
noise is s > 1 times what the weights claim (s = χ²_meas / (2M − 6 + tr(BP)), B = P₀⁻¹), the change also
carries the extra measurement noise: with d = P·A·δ, A = P⁻¹ − B the measurement information, Cov(d) =
P(A·P₀·A + s·A)P = (P₀ − P) + (s − 1)(P − P·B·P), which is used instead — so an inconsistent set of
measurements (bad maplets) is not mistaken for a wrong prior. Only components with a prior enter (the
limit of an infinite σ₀ for the others). q above its 99.9 % quantile says the a-priori pose is further
from the measurements' pose than SIGMA_VSO / SIGMA_PTG allow: the prior is *contradicted*. Also
reported: the prior's share of J and the change per component in a-priori σ units, dⱼ/σ₀ⱼ.

**Model error.**  With per-landmark covariances Cᵢ (the correlation peaks'), residuals larger than
they allow are read as an isotropic model error τ common to the landmarks of the fit:
Σᵢ rᵢᵀ(Cᵢ + τ²I)⁻¹rᵢ = dof (method of moments, :func:`model_error`), estimated only when the χ² with
τ = 0 exceeds its ``quantile`` (0.9: honest covariances are left alone but for chance) and at most a
``cap`` — a larger misfit is the χ² gate's to report.

**Prior scale.**  If σ₀ understates the a-priori error by a factor s, q ≈ k·s² when the measurements
dominate; :func:`prior_scale_step` gives the factor √(q/k) by which to widen σ₀ (the pose module
iterates it until the test passes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "ChiSquareGate",
    "PriorTest",
    "chi2_quantile",
    "chi2_gate",
    "model_error",
    "prior_test",
    "prior_scale_step",
]

#: eigenvalues of I − S⁻¹PS⁻¹ below this (the measurements remove < 0.1 % of the prior variance in that
#: direction) carry no test of the prior
MIN_GAIN = 1e-3


def _gamma_pq(a: float, x: float) -> tuple[float, float]:
    """(P, Q): the regularised lower and upper incomplete gamma functions at (a, x), x > 0 (the series
    of P below x = a + 1, the continued fraction of Q above: Press et al., Numerical Recipes §6.2)."""
    lead = math.exp(a * math.log(x) - x - math.lgamma(a))
    if x < a + 1.0:
        term = total = 1.0 / a
        n = a
        while abs(term) > abs(total) * 1e-17:
            n += 1.0
            term *= x / n
            total += term
        p = total * lead
        return p, 1.0 - p
    tiny = 1e-300
    b = x + 1.0 - a
    c = 1.0 / tiny
    d = 1.0 / b
    h = d
    i = 0
    while True:  # modified Lentz
        i += 1
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = d if abs(d) > tiny else tiny
        c = b + an / c
        c = c if abs(c) > tiny else tiny
        d = 1.0 / d
        step = d * c
        h *= step
        if abs(step - 1.0) < 1e-16 or i > 10_000:
            break
    q = lead * h
    return 1.0 - q, q


def chi2_quantile(dof: float, p: float) -> float:
    """The p-quantile of χ² with ``dof`` degrees of freedom (2·P⁻¹(dof/2, p), the inverse regularised
    lower incomplete gamma function; 0 < p < 1); NaN for dof ≤ 0.  Newton's method on P (or on Q
    above the median, where 1 − P would lose digits) from the Wilson–Hilferty approximation, kept
    inside a bisection bracket, to full double precision (tests: equal to scipy's to 1e-10); in plain
    Python, as importing scipy.special cost 0.37 s of every navigate."""
    if not dof > 0:
        return math.nan
    a = 0.5 * float(dof)
    p = float(p)
    if not 0.0 < p < 1.0:
        return 0.0 if p == 0.0 else (math.inf if p == 1.0 else math.nan)
    # Wilson–Hilferty start: χ²_k ≈ k (1 − 2/(9k) + z √(2/(9k)))³, z the normal quantile
    z = math.sqrt(2.0) * _erfinv(2.0 * p - 1.0)
    k = float(dof)
    base = 1.0 - 2.0 / (9.0 * k) + z * math.sqrt(2.0 / (9.0 * k))
    # the lower tail: P(a, x) ≈ x^a / Γ(a + 1) for small x
    small = math.exp((math.log(p) + math.lgamma(a + 1.0)) / a)
    x = small if base <= 0.0 or (p < 0.5 and small < 0.5 * k * base**3) else 0.5 * k * base**3
    lo, hi = 0.0, math.inf
    upper = p > 0.5
    for _ in range(200):
        pp, qq = _gamma_pq(a, x)
        f = (1.0 - p) - qq if upper else pp - p  # increasing in x either way
        if f > 0.0:
            hi = min(hi, x)
        else:
            lo = max(lo, x)
        if f == 0.0:
            break
        dens = math.exp((a - 1.0) * math.log(x) - x - math.lgamma(a))
        new = x - f / dens if dens > 0.0 else math.nan
        new = min(max(new, 1e-3 * x), 1e3 * x)  # NaN → x/1000: at most a factor of 1000 per step
        if not lo < new < hi:  # outside the bracket: bisect it (geometrically while it spans decades)
            if hi == math.inf:
                new = 10.0 * x
            elif lo > 0.0 and hi > 4.0 * lo:
                new = math.sqrt(lo * hi)
            else:
                new = 0.5 * (lo + hi)
        if abs(new - x) <= 4e-16 * x:
            x = new
            break
        x = new
    return 2.0 * x


def _erfinv(y: float) -> float:
    """Inverse error function for |y| < 1 (Giles 2010's single-precision fit, refined by two Newton
    steps on math.erf): only a starting point for :func:`chi2_quantile`."""
    w = -math.log((1.0 - y) * (1.0 + y))
    if w < 5.0:
        w -= 2.5
        c = (2.81022636e-08, 3.43273939e-07, -3.5233877e-06, -4.39150654e-06, 0.00021858087,
             -0.00125372503, -0.00417768164, 0.246640727, 1.50140941)  # fmt: skip
    else:
        w = math.sqrt(w) - 3.0
        c = (-0.000200214257, 0.000100950558, 0.00134934322, -0.00367342844, 0.00573950773,
             -0.0076224613, 0.00943887047, 1.00167406, 2.83297682)  # fmt: skip
    r = c[0]
    for ci in c[1:]:
        r = r * w + ci
    x = r * y
    for _ in range(2):
        err = math.erf(x) - y
        x -= err / (2.0 / math.sqrt(math.pi) * math.exp(-x * x))
    return x


@dataclass
class ChiSquareGate:
    """The χ² test of a pose's minimised cost (module docstring)."""

    cost: float
    dof: int
    quantile: float
    limit: float  # χ²_dof quantile
    worst: list = field(default_factory=list)  # [(name, ρ², share of the measurement χ²)], worst first

    @property
    def consistent(self) -> bool:
        return not (self.dof > 0 and self.cost > self.limit)

    def reason(self) -> str:
        """One line (empty when consistent): the figure, the worst landmarks and the remedy."""
        if self.consistent:
            return ""
        red = self.cost / self.dof
        worst = ", ".join(f"{n} ({100 * s:.0f} %)" for n, _, s in self.worst)
        return (
            f"chi2 {self.cost:.4g} > {self.limit:.4g} ({100 * self.quantile:g} % quantile, {self.dof} dof;"
            f" cost/dof {red:.3g}: residuals ~{math.sqrt(red):.2g}x their sigmas); worst landmarks {worst};"
            " the covariance is scaled by cost/dof — check those landmarks' maplets or give larger sigmas"
        )

    def as_dict(self) -> dict:
        return {
            "consistent": self.consistent,
            "cost": self.cost,
            "dof": self.dof,
            "quantile": self.quantile,
            "limit": self.limit,
            "worst": [{"name": n, "rho2": r, "share": s} for n, r, s in self.worst],
        }


def chi2_gate(cost, dof, rho2, names, quantile: float = 0.999, n_worst: int = 3) -> ChiSquareGate:
    """:class:`ChiSquareGate` of the minimised ``cost`` with ``dof`` degrees of freedom; ``rho2`` (M,)
    the weighted residuals rᵢᵀWᵢrᵢ of the used landmarks ``names`` (the worst ``n_worst`` are named)."""
    rho2 = np.asarray(rho2, dtype=np.float64)
    total = float(np.sum(rho2))
    order = np.argsort(-rho2, kind="stable")[: int(n_worst)]
    worst = [
        (str(names[i]), float(rho2[i]), float(rho2[i]) / total if total > 0 else math.nan) for i in order
    ]
    return ChiSquareGate(float(cost), int(dof), float(quantile), chi2_quantile(dof, quantile), worst)


@dataclass
class PriorTest:
    """The prior–measurement test of a pose solve (module docstring)."""

    nis: float  # q = dᵀ(P₀ − P)⁺d
    dof: int  # k: directions the measurements inform
    quantile: float
    limit: float
    share: float  # prior term / total cost
    change_sigma: np.ndarray  # (6,) dⱼ/σ₀ⱼ (NaN without a prior on j)
    scale: float = 1.0  # factor applied to the given prior sigmas

    @property
    def contradicted(self) -> bool:
        return self.dof > 0 and self.nis > self.limit

    @property
    def understatement(self) -> float:
        """√(q/k): by about how much the prior sigmas understate the a-priori error."""
        return math.sqrt(self.nis / self.dof) if self.dof > 0 else math.nan

    def reason(self) -> str:
        """One line (empty when the prior agrees): the figure and the remedy."""
        if not self.contradicted:
            return ""
        j = int(np.nanargmax(np.abs(self.change_sigma)))
        comp = ("dx", "dy", "dz", "tx", "ty", "tz")[j]
        return (
            f"the measurements contradict the a-priori pose: change {abs(self.change_sigma[j]):.3g} sigma"
            f" ({comp}), normalised change {self.nis:.4g} > {self.limit:.4g} ({100 * self.quantile:g} %"
            f" quantile, {self.dof} dof), prior {100 * self.share:.0f} % of chi2 — SIGMA_VSO/SIGMA_PTG"
            f" understate the a-priori error ~{self.understatement:.2g}x"
            + (f" (already widened x{self.scale:.3g})" if self.scale != 1.0 else "")
            + "; solve with --no-prior or --prior-scale auto"
        )

    def as_dict(self) -> dict:
        return {
            "contradicted": self.contradicted,
            "normalised_change": self.nis,
            "dof": self.dof,
            "quantile": self.quantile,
            "limit": self.limit,
            "prior_share": self.share,
            "change_sigma": [None if not math.isfinite(x) else float(x) for x in self.change_sigma],
            "understatement": self.understatement,
            "prior_scale": self.scale,
        }


def prior_test(
    change,
    info,
    covariance,
    prior_term,
    cost,
    quantile: float = 0.999,
    scale: float = 1.0,
    min_gain: float = MIN_GAIN,
    noise_scale: float = 1.0,
) -> PriorTest:
    """:class:`PriorTest` of the solved change ``change`` = χ̂ − χ₀ (6,) against the prior ``info``
    (6,) inverse variances (0 = no prior on that component), with the formal a-posteriori
    ``covariance`` P (6 × 6, not scaled by cost/dof); ``prior_term`` and ``cost`` give the prior's
    share of the cost; ``scale`` is reported (the factor already applied to the prior sigmas);
    ``noise_scale`` s ≥ 1: the measurements' noise relative to their weights (module docstring)."""
    d = np.asarray(change, dtype=np.float64)
    info = np.asarray(info, dtype=np.float64)
    p = np.asarray(covariance, dtype=np.float64)
    on = info > 0
    sig0 = np.where(on, 1.0 / np.sqrt(np.where(on, info, 1.0)), np.nan)
    change_sigma = np.where(on, d / np.where(on, sig0, 1.0), np.nan)
    share = float(prior_term) / float(cost) if cost > 0 else math.nan
    idx = np.flatnonzero(on)
    if idx.size == 0:
        return PriorTest(math.nan, 0, quantile, math.nan, share, change_sigma, scale)
    s = sig0[idx]
    c = -p  # Cov(d) − P₀ = −P + (s − 1)(P − P·B·P)
    extra = max(1.0, float(noise_scale)) - 1.0
    if extra > 0:
        c = c + extra * (p - (p * info[None, :]) @ p)
    m = np.eye(idx.size) + c[np.ix_(idx, idx)] / np.outer(s, s)  # S⁻¹·Cov(d)·S⁻¹
    m = 0.5 * (m + m.T)
    lam, vec = np.linalg.eigh(m)
    keep = lam > float(min_gain)
    z = vec[:, keep].T @ (d[idx] / s)
    nis = float(np.sum(z * z / lam[keep]))
    k = int(np.count_nonzero(keep))
    return PriorTest(nis, k, quantile, chi2_quantile(k, quantile), share, change_sigma, scale)


def prior_scale_step(test: PriorTest) -> float:
    """The factor (≥ 1) by which to widen the prior sigmas so that the test's statistic would fall to
    its degrees of freedom when the measurements dominate: √(q/k) (module docstring)."""
    if not test.contradicted:
        return 1.0
    return max(1.0, test.understatement)


def model_error(residuals, covariances, dof: int, cap: float, quantile: float = 0.9) -> float:
    """τ (px, module docstring "Model error"): ``residuals`` (M, 2) px, ``covariances`` (M, 2, 2) px²,
    ``dof`` of the fit; 0 when χ²(τ = 0) is within its ``quantile`` or dof ≤ 0, ``cap`` when even
    χ²(cap) exceeds dof, else the root of χ²(τ²) = dof by bisection on log τ² (χ² decreases with τ²)."""
    r = np.asarray(residuals, dtype=np.float64)
    c = np.asarray(covariances, dtype=np.float64)
    if dof <= 0:
        return 0.0

    def chi2(t2):
        return float(np.einsum("mi,mij,mj->", r, np.linalg.inv(c + t2 * np.eye(2)), r))

    if chi2(0.0) <= chi2_quantile(dof, quantile):  # no evidence of model error
        return 0.0
    if chi2(cap * cap) >= dof:
        return float(cap)
    hi = cap * cap
    lo = hi * 1e-12
    for _ in range(60):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if chi2(mid) > dof else (lo, mid)
        if hi <= lo * (1.0 + 1e-6):
            break
    return float(math.sqrt(hi))
