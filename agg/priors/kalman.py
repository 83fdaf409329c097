"""Multi-object tracking of 3D points with one constant-velocity Kalman filter per track (filterpy).

The functional core of the agent tracklets (``agg/priors/tracklets.py``): it knows nothing about images. Input is,
per step, the measured 3D positions (world frame) and their covariances; output is, per track, which measurement
it took at each step and its RTS-smoothed state. Rules (documented in docs/PRIORS.md, "Agent tracklets"):

* State ``[x, y, z, vx, vy, vz]`` (world, velocity per frame); transition over ``dt`` frames ``x += v dt``; process
  noise ``Q_discrete_white_noise`` (piecewise-constant white acceleration) of variance ``accel_var`` per axis.
* Gating: the squared Mahalanobis distance ``y^T S^-1 y`` of the innovation ``y = z - H x`` with ``S = H P H^T + R``
  must be below ``gate`` (a chi-square quantile, 3 degrees of freedom), and an optional ``extra_gate`` of the
  caller (the image-space gate of the tracklets) must accept the pair.
* Assignment: Hungarian (``scipy.optimize.linear_sum_assignment``) on the gated squared distances plus
  ``log det S`` (the negative log-likelihood up to a constant, so a coasted track with a wide ``S`` does not win
  every contest by its large gate), plus, when appearance descriptors are given (normalised colour histograms),
  ``appearance_weight * (1 - BC)`` with BC the Bhattacharyya coefficient between the track's descriptor (an
  exponential moving average of its detections', keeping ``appearance_memory``) and the measurement's.
* A track that misses a step is coasted (predicted only); after more than ``max_missed`` consecutive misses it ends.
  Unmatched measurements start new tracks with zero velocity and velocity variance ``init_vel_var``.
* After the last step each track's filtered states from its first to its last hit are smoothed with
  ``KalmanFilter.rts_smoother``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy.optimize import linear_sum_assignment

_H = np.hstack([np.eye(3), np.zeros((3, 3))])  # [3, 6] measurement matrix: position only


def transition(dt: float) -> np.ndarray:
    """[6, 6] constant-velocity transition over ``dt`` frames."""
    f = np.eye(6)
    f[:3, 3:] = dt * np.eye(3)
    return f


def process_noise(dt: float, accel_var: float) -> np.ndarray:
    """[6, 6] white-acceleration process noise, state order (x, y, z, vx, vy, vz)."""
    return Q_discrete_white_noise(dim=2, dt=float(dt), var=float(accel_var), block_size=3, order_by_dim=False)


def new_filter(z: np.ndarray, R: np.ndarray, init_vel_var: float) -> KalmanFilter:
    """A filter started at measurement z [3] with covariance R [3, 3], velocity 0 +- sqrt(init_vel_var)."""
    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.x = np.concatenate([z, np.zeros(3)])
    kf.P = np.zeros((6, 6))
    kf.P[:3, :3] = R
    kf.P[3:, 3:] = init_vel_var * np.eye(3)
    kf.H = _H.copy()
    kf.R = R.copy()
    return kf


@dataclass
class _Track:
    kf: KalmanFilter
    start: int  # step of the first hit
    feat: np.ndarray | None = None  # [F] appearance descriptor (moving average)
    hits: int = 1
    misses: int = 0  # consecutive
    ended: bool = False
    assoc: dict = field(default_factory=dict)  # step -> measurement index
    xs: list = field(default_factory=list)  # filtered states [6], one per step from start
    ps: list = field(default_factory=list)  # [6, 6]
    fs: list = field(default_factory=list)  # transition into each step
    qs: list = field(default_factory=list)


@dataclass
class TrackHistory:
    """One track: the measurement it took at each step (-1: none) and its smoothed state (NaN outside its life)."""

    assoc: np.ndarray  # [T] int, measurement index per step, -1 where missed / outside the track
    state: np.ndarray  # [T, 6] RTS-smoothed (x, y, z, vx, vy, vz), NaN outside [first hit, last hit]
    cov: np.ndarray  # [T, 6, 6] smoothed covariance, NaN outside
    hits: int


def _mahalanobis_sq(kf: KalmanFilter, z: np.ndarray, R: np.ndarray) -> tuple[float, float]:
    """Squared Mahalanobis distance of z from the predicted measurement, and log det S."""
    S = _H @ kf.P @ _H.T + R  # [3, 3]
    y = z - _H @ kf.x
    sign, logdet = np.linalg.slogdet(S)
    return float(y @ np.linalg.solve(S, y)), float(logdet)


def associate(tracks: list[_Track], z: np.ndarray, R: np.ndarray, gate: float, feats: np.ndarray | None = None,
              appearance_weight: float = 0.0, extra_gate: Callable[[np.ndarray], np.ndarray] | None = None
              ) -> list[tuple[int, int]]:
    """Gated Hungarian assignment of measurements z [N, 3] (covariances R [N, 3, 3], descriptors feats [N, F] or
    None) to the predicted tracks. extra_gate(predicted position [3]) -> [N] bool: a further gate (image space)."""
    if not tracks or len(z) == 0:
        return []
    big = 1e12
    cost = np.full((len(tracks), len(z)), big)
    for a, tr in enumerate(tracks):
        allowed = np.ones(len(z), bool) if extra_gate is None else extra_gate(tr.kf.x[:3].copy())
        for b in range(len(z)):
            d2, logdet = _mahalanobis_sq(tr.kf, z[b], R[b])
            if d2 <= gate and allowed[b]:
                cost[a, b] = d2 + logdet
                if feats is not None and tr.feat is not None and appearance_weight > 0:
                    cost[a, b] += appearance_weight * (1.0 - float(np.sqrt(tr.feat * feats[b]).sum()))
    # shift so every gated cost is >= 0: the assignment stays optimal and "big" stays the only infeasible value
    ok = cost < big
    if ok.any():
        cost[ok] -= cost[ok].min()
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c)) for r, c in zip(rows, cols) if cost[r, c] < big]


def track_points(z_steps: list[np.ndarray], r_steps: list[np.ndarray], dt: np.ndarray, *, accel_var: float,
                 init_vel_var: float, gate: float, max_missed: int, feat_steps: list[np.ndarray] | None = None,
                 appearance_weight: float = 0.0, appearance_memory: float = 0.7,
                 extra_gate: Callable[[int, np.ndarray], np.ndarray] | None = None,
                 observed: np.ndarray | None = None) -> list[TrackHistory]:
    """Track 3D measurements over T steps.

    z_steps[i]: [N_i, 3] world positions measured at step i; r_steps[i]: [N_i, 3, 3] their covariances;
    dt: [T] frames elapsed since the previous step (dt[0] unused); feat_steps[i]: [N_i, F] appearance descriptors
    (non-negative, summing to 1) or None; extra_gate(step, predicted position [3]) -> [N_i] bool or None;
    observed: [T] bool, False at steps that could not measure anything (a held-out frame): a track coasts through
    them without counting a miss (None: every step observed).
    Returns every track ever started (also the one-hit ones; the caller filters by ``hits``), in order of creation.
    """
    n_steps = len(z_steps)
    live: list[_Track] = []
    done: list[_Track] = []
    for i in range(n_steps):
        z, R = np.asarray(z_steps[i], float).reshape(-1, 3), np.asarray(r_steps[i], float).reshape(-1, 3, 3)
        if i > 0:
            F, Q = transition(dt[i]), process_noise(dt[i], accel_var)
            for tr in live:
                tr.kf.predict(F=F, Q=Q)
                tr.fs.append(F)
                tr.qs.append(Q)
        f = None if feat_steps is None or len(z) == 0 else np.asarray(feat_steps[i], float).reshape(len(z), -1)
        gate_i = None if extra_gate is None else (lambda x, i=i: extra_gate(i, x))
        pairs = associate(live, z, R, gate, f, appearance_weight, gate_i)
        taken = {b for _, b in pairs}
        matched = {a for a, _ in pairs}
        for a, b in pairs:
            tr = live[a]
            tr.kf.update(z[b], R=R[b])
            tr.hits += 1
            tr.misses = 0
            tr.assoc[i] = b
            if f is not None:
                tr.feat = appearance_memory * tr.feat + (1.0 - appearance_memory) * f[b]
        for a, tr in enumerate(live):
            if a not in matched and (observed is None or observed[i]):
                tr.misses += 1
            tr.xs.append(tr.kf.x.copy())
            tr.ps.append(tr.kf.P.copy())
        for tr in live:
            if tr.misses > max_missed:
                tr.ended = True
        done += [tr for tr in live if tr.ended]
        live = [tr for tr in live if not tr.ended]
        for b in range(len(z)):
            if b not in taken:
                tr = _Track(new_filter(z[b], R[b], init_vel_var), start=i, assoc={i: b},
                            feat=None if f is None else f[b].copy())
                tr.xs.append(tr.kf.x.copy())
                tr.ps.append(tr.kf.P.copy())
                tr.fs.append(np.eye(6))
                tr.qs.append(np.zeros((6, 6)))
                live.append(tr)
    done += live
    done.sort(key=lambda t: (t.start, t.assoc[t.start]))
    return [_history(tr, n_steps) for tr in done]


def _history(tr: _Track, n_steps: int) -> TrackHistory:
    last = max(tr.assoc)  # step of the last hit
    n = last - tr.start + 1
    xs, ps = np.array(tr.xs[:n]), np.array(tr.ps[:n])  # [n, 6], [n, 6, 6]
    if n > 1:
        xs, ps, _, _ = tr.kf.rts_smoother(xs, ps, Fs=tr.fs[:n], Qs=tr.qs[:n])
    assoc = np.full(n_steps, -1, dtype=np.int64)
    for step, b in tr.assoc.items():
        assoc[step] = b
    state = np.full((n_steps, 6), np.nan)
    cov = np.full((n_steps, 6, 6), np.nan)
    state[tr.start:last + 1] = xs
    cov[tr.start:last + 1] = ps
    return TrackHistory(assoc=assoc, state=state, cov=cov, hits=tr.hits)


def smooth_sequence(z: np.ndarray, R: np.ndarray, *, accel_var: float, init_vel_var: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """RTS-smoothed constant-velocity states of one already-associated track.

    z: [T, 3] positions, NaN rows where missing (coasted); R: [T, 3, 3] their covariances. Returns state [T, 6]
    and covariance [T, 6, 6], NaN outside [first, last] present row."""
    present = np.nonzero(~np.isnan(z).any(1))[0]
    n_steps = len(z)
    state, cov = np.full((n_steps, 6), np.nan), np.full((n_steps, 6, 6), np.nan)
    if len(present) == 0:
        return state, cov
    first, last = int(present[0]), int(present[-1])
    kf = new_filter(z[first], R[first], init_vel_var)
    xs, ps, fs, qs = [kf.x.copy()], [kf.P.copy()], [np.eye(6)], [np.zeros((6, 6))]
    F, Q = transition(1.0), process_noise(1.0, accel_var)
    for i in range(first + 1, last + 1):
        kf.predict(F=F, Q=Q)
        if not np.isnan(z[i]).any():
            kf.update(z[i], R=R[i])
        xs.append(kf.x.copy())
        ps.append(kf.P.copy())
        fs.append(F)
        qs.append(Q)
    xs, ps = np.array(xs), np.array(ps)
    if len(xs) > 1:
        xs, ps, _, _ = kf.rts_smoother(xs, ps, Fs=fs, Qs=qs)
    state[first:last + 1], cov[first:last + 1] = xs, ps
    return state, cov


def relink(histories: list[TrackHistory], *, max_gap: int, gate: float, accel_var: float,
           extra_gate: Callable[[int, np.ndarray], np.ndarray] | None = None) -> list[TrackHistory]:
    """Join tracks broken by a gap longer than the tracker's ``max_missed`` (an agent lost for a few frames).

    A track B that starts ``g`` steps (1 <= g <= ``max_gap``) after a track A ended, with no step in common, is the
    same agent when A's smoothed last state, propagated over the gap with the constant-velocity model (covariance
    grown by the process noise), meets B's smoothed first position within the chi-square ``gate`` on the squared
    Mahalanobis distance (covariance: propagated A plus B's) and, with ``extra_gate`` (step, predicted position [3])
    -> [N] bool as in ``track_points``, that gate accepts B's first measurement for A's propagated position. Pairs
    are joined greedily, closest first; each track joins at most one successor and one predecessor. The joined track
    keeps A's start (its id order), both tracks' measurements and states, and NaN states in the gap (coasted,
    invalid there).
    """
    if max_gap < 2 or len(histories) < 2:
        return list(histories)
    spans = []
    for h in histories:
        steps = np.flatnonzero(h.assoc >= 0)
        spans.append((int(steps[0]), int(steps[-1])) if len(steps) else None)  # None: no measurement left
    pairs = []
    for a, ha in enumerate(histories):
        for b, hb in enumerate(histories):
            if a == b or spans[a] is None or spans[b] is None:
                continue
            gap = spans[b][0] - spans[a][1]
            if not 1 <= gap <= max_gap:
                continue
            x, p = ha.state[spans[a][1]], ha.cov[spans[a][1]]  # [6], [6, 6]
            f, q = transition(float(gap)), process_noise(float(gap), accel_var)
            x, p = f @ x, f @ p @ f.T + q
            s = p[:3, :3] + hb.cov[spans[b][0], :3, :3]
            y = hb.state[spans[b][0], :3] - x[:3]
            d2 = float(y @ np.linalg.solve(s, y))
            if d2 <= gate and (extra_gate is None or extra_gate(spans[b][0], x[:3])[hb.assoc[spans[b][0]]]):
                pairs.append((d2, a, b))
    nxt: dict[int, int] = {}
    prv: dict[int, int] = {}
    for _, a, b in sorted(pairs):
        if a not in nxt and b not in prv:
            nxt[a], prv[b] = b, a
    out = []
    for a in range(len(histories)):
        if a in prv:
            continue  # joined into its predecessor's chain
        h = histories[a]
        assoc, state, cov, hits = h.assoc.copy(), h.state.copy(), h.cov.copy(), h.hits
        while a in nxt:
            a = nxt[a]
            hb, (s0, s1) = histories[a], spans[a]
            assoc[s0:s1 + 1] = hb.assoc[s0:s1 + 1]
            state[s0:s1 + 1], cov[s0:s1 + 1] = hb.state[s0:s1 + 1], hb.cov[s0:s1 + 1]
            hits += hb.hits
        out.append(TrackHistory(assoc=assoc, state=state, cov=cov, hits=hits))
    return out
