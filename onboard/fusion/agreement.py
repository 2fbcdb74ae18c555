"""The fused tracker's outlier check against the other tracker, with the
reference distribution of a statistic whose scale is estimated.

The second tracker's motion, once the first one has updated the filter, is
off by both trackers' errors: d^2 = y^T S^-1 y (k = 3 dof). If S were right,
d^2 ~ chi2(k) and a fixed bound (`outlier_chi2`, 12: 99.3 %) would leave out
0.7 % of honest frames. But S is only known up to a scale: the trackers'
quality signals see the noise of a match, not what real data adds, and the
agreement scale that corrects them (fused._adapt) is itself estimated from
the disagreements seen so far (`tum_fr1_rpy`: from 1 at the start to ~6).
With the variance scale lambda unknown and estimated from the nu dof of the
disagreements seen, lambda_hat = sum(d_i^2) / nu, the new one is distributed
as d^2 / lambda_hat ~ k F(k, nu) (the predictive distribution of a Gaussian
with an estimated variance; Hotelling's T^2 with a known shape). That is very
wide while nu is small (nu = 6: the 99.3 % point is 33, not 12) and tends to
chi2(k) as nu grows, so early honest disagreement is not taken for an
outlier, while a wild pose (hundreds) still is, and once a few dozen frames
have been seen the bound is the chi-square one again.

The estimate (the conjugate scaled-inverse-chi2 one of a normal variance,
Gelman et al., Bayesian Data Analysis, ch. 2-3) starts from the trackers'
own covariances, worth `outlier_prior_dof` dof (scale 1), and forgets at the
agreement scale's own rate (`noise_adapt_gain`), since S is rescaled at that
rate and older disagreements say less about it. A frame beyond the bound
adds only the bound (clipped, winsorised): a wild pose widens the check no more than an
honest frame at the bound would (counted at its d^2, a frame a thousand
times off would open it for the next wild one).
"""

from __future__ import annotations

import math

from scipy.special import chdtrc, fdtri


class OutlierCheck:
    """Outlier bound on d^2 of the second tracker against the first one's update."""

    def __init__(self, chi2_bound: float, prior_dof: float, forget: float, k: int = 3) -> None:
        self.k = k
        self.tail = float(chdtrc(k, chi2_bound))  # the chi-square bound's tail: kept for every nu
        self.forget = forget
        self.sum = float(prior_dof)  # sum of d^2 seen (the prior: its dof at scale 1)
        self.dof = float(prior_dof)

    @property
    def scale(self) -> float:
        """lambda_hat: how far the d^2 seen are above what S says (1: as
        claimed), never below 1: the trackers' own figures are a floor, as
        for the agreement scale (a quality signal sees a match's noise, real
        data only adds to it). So the bound is never tighter than chi2(k)'s:
        this check only lets through what the fixed bound took for an outlier."""
        return max(1.0, self.sum / self.dof) if self.dof > 0.0 else 1.0

    def bound(self) -> float:
        """d^2 beyond which a frame is an outlier: lambda_hat k F^-1(1 - tail; k, nu)."""
        if self.dof <= 0.0:
            return float("inf")  # nothing known of the scale yet: no test
        return self.scale * self.k * float(fdtri(self.k, self.dof, 1.0 - self.tail))

    def check(self, d2: float) -> bool:
        """Whether d2 is an outlier; the frame then counts towards the scale
        with the bound (clipped), otherwise with d2."""
        b = self.bound()
        if math.isnan(d2):  # NaN: no test, nothing learnt (as fused._adapt)
            return False
        out = d2 > b
        g = self.forget
        self.sum = (1.0 - g) * self.sum + min(d2, b)
        self.dof = (1.0 - g) * self.dof + self.k
        return out
