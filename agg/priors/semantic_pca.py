"""Per-scene PCA of raw descriptors and the choice of the channel subsets C_bg / C_ag (paper Sec. 3).

Pure numpy / scikit-learn functions used by ``agg.priors.features.build_semantics``; the rules are documented in
docs/PRIORS.md ("Semantic features").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SubsetChoice:
    """Channel subsets and the sign of every PCA channel (multiply basis column c by signs[c])."""

    C_bg: list[int]
    C_ag: list[int]
    signs: np.ndarray  # [C] +1 / -1
    corr_ag: float  # correlation of sum(F[C_ag]) with the agent labels (after the flips)
    corr_bg: float  # correlation of sum(F[C_bg]) with the background labels
    rule: str


def fit_pca(x: np.ndarray, n_components: int, standardize: bool) -> tuple[np.ndarray, np.ndarray]:
    """(mean [D], basis [D, C]) with F_low = (x - mean) @ basis, fitted on samples x [N, D].

    C = min(n_components, D, N - 1). standardize: the PCA runs on z-scores (x - mean) / s with
    s = max(std, 1e-2 median(std), 1e-6) per descriptor, folded into the basis (basis = V / s[:, None]).
    Components come from scikit-learn's covariance eigendecomposition (deterministic, signs fixed by sklearn).
    """
    from sklearn.decomposition import PCA

    x = np.asarray(x, dtype=np.float64)
    n, d = x.shape
    c = int(min(n_components, d, n - 1))
    if c < 1:
        raise ValueError(f"PCA needs at least 2 samples, got {n}")
    mean = x.mean(0)
    scale = np.ones(d)
    if standardize:
        std = x.std(0)
        scale = np.maximum(std, max(1e-2 * float(np.median(std)), 1e-6))
    pca = PCA(n_components=c, svd_solver="covariance_eigh").fit((x - mean) / scale)
    basis = pca.components_.T / scale[:, None]  # [D, C]
    return mean, basis


def _corr(s: np.ndarray, y: np.ndarray) -> float:
    sd = s.std()
    return float(((s - s.mean()) * (y - y.mean())).mean() / (sd * y.std())) if sd > 0 else 0.0


class _Greedy:
    """Forward selection of channels maximising corr(sum_c sign_c f[:, c], y), one channel per ``step``."""

    def __init__(self, f: np.ndarray, y: np.ndarray, signs: np.ndarray, k_max: int, min_gain: float):
        self.fs = (f - f.mean(0)) * signs  # [N, C] centred, signed
        self.yc = y - y.mean()
        self.y_sd = max(float(y.std()), 1e-12)
        self.cov_y = self.fs.T @ self.yc / len(y)  # [C]
        self.var_c = (self.fs * self.fs).mean(0)  # [C]
        self.s = np.zeros(len(y))  # the running sum
        self.chosen: list[int] = []
        self.best = -np.inf
        self.k_max, self.min_gain, self.done = k_max, min_gain, False

    def step(self, available: set[int]) -> int | None:
        """Add the best available channel (returned) or stop (None) when full or the gain is < min_gain."""
        if self.done or len(self.chosen) >= self.k_max or not available:
            self.done = True
            return None
        cand = np.array(sorted(available))
        n = len(self.s)
        var = (self.s * self.s).mean() + self.var_c[cand] + 2 * (self.fs[:, cand].T @ self.s) / n
        cov = (self.s * self.yc).mean() + self.cov_y[cand]
        score = cov / np.sqrt(np.maximum(var, 1e-30)) / self.y_sd  # corr(S + F_c, y) per candidate
        j = int(np.argmax(score))
        if self.chosen and score[j] - self.best < self.min_gain:
            self.done = True
            return None
        self.best = float(score[j])
        self.chosen.append(int(cand[j]))
        self.s = self.s + self.fs[:, cand[j]]
        return int(cand[j])


def select_channel_subsets(f: np.ndarray, agent: np.ndarray | None, max_ag: int = 16, max_bg: int = 16,
                           min_gain: float = 0.005) -> SubsetChoice:
    """Choose C_ag and C_bg (disjoint) and the channel signs from labelled F_low samples.

    f [N, C] PCA features, agent [N] bool (True = agent cell) or None. Rule: r_c = corr(F_c, agent); each channel
    is oriented so that it rises on its subset's class (sign(r_c) for C_ag, -sign(r_c) for C_bg). The two subsets
    grow in turns (C_ag first) by greedy forward selection: each turn adds the still-unused channel that most
    increases corr(sum_{C_i} F_c, labels_i) (labels_ag = agent, labels_bg = not agent), until max_ag / max_bg
    channels or a gain < min_gain. Because M_i is an affine map of sum_{C_i} F_c (global latent normalisation),
    that correlation is the point-biserial correlation of the attention map with the labels. Without labels
    (None, or one class only): C_bg = the first min(max_bg, C // 2) channels, C_ag = the next ones, no flips.
    """
    f = np.asarray(f, dtype=np.float64)
    c = f.shape[1]
    if agent is None or agent.all() or not agent.any() or c < 2:
        k_bg = max(1, min(max_bg, c // 2))
        k_ag = max(0, min(max_ag, c - k_bg))
        return SubsetChoice(list(range(k_bg)), list(range(k_bg, k_bg + k_ag)), np.ones(c), float("nan"),
                            float("nan"), "fallback: no labels (first channels for C_bg, next for C_ag)")
    y = np.asarray(agent, dtype=np.float64)
    fc = f - f.mean(0)
    r = fc.T @ (y - y.mean()) / (len(y) * np.maximum(fc.std(0), 1e-12) * y.std())  # [C]
    signs = np.where(r >= 0, 1.0, -1.0)
    ag, bg = _Greedy(f, y, signs, max_ag, min_gain), _Greedy(f, 1.0 - y, -signs, max_bg, min_gain)
    available = set(range(c))
    while not (ag.done and bg.done):
        for g in (ag, bg):
            available.discard(g.step(available))
    out = np.ones(c)
    out[ag.chosen] = signs[ag.chosen]
    out[bg.chosen] = -signs[bg.chosen]
    return SubsetChoice(sorted(bg.chosen), sorted(ag.chosen), out, ag.best, bg.best,
                        "correlation with agent labels (greedy, in turns)")
