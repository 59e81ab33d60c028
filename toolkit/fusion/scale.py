"""Per-frame scale (and shift) of a monocular prediction from lidar/prediction pairs.

Pairs are (l_j, d_j): lidar z-depth and predicted value at the same pixel. For depth kinds
the model is ``l = s * d``. For ``relative_disparity`` it is ``1 / l = s * d + t`` (the
prediction is affine in inverse depth), so every estimator works on y_j = 1 / l_j there;
``ratio`` fits the scale alone (t = 0, the paper's formula), ``clustered`` refits scale and
shift on its cluster and ``robust`` fits both. A shift is only fitted where the frame's
lidar depths spread enough to tell it from the scale (``MIN_SPREAD``): a robot facing a wall
gets the scale alone instead of a confident nonsense shift.

Estimators (selected in the recipe):

- ``ratio``: the paper's alpha = sum(l_j) / sum(d_j). With ``gate`` set, pairs whose own
  ratio is further than 3 robust sigmas of the frame's log ratios (at least
  ``RATIO_GATE_MIN``, at most ``gate``) from the median ratio are not valid pairs; with
  ``gate=None`` it is the paper's formula over all pairs.
- ``clustered``: the paper's per-pair ratios alpha_j = l_j / d_j, clustered in log space
  with DBSCAN (or mean-shift); alpha = sum(l) / sum(d) over the dominant cluster. A core
  point needs ``min_samples`` pairs, and at least ``min_fraction`` of all pairs, within
  ``eps``: with a fixed count, the one-sided outliers of a dense lidar (hundreds of pairs)
  chained onto the true cluster and moved the scale by 20 %.
- ``robust``: RANSAC on minimal samples then iteratively reweighted least squares with a
  Tukey loss, in log space for scale only and in disparity space for scale and shift.

Then ``smooth_scales`` runs over the whole sequence: frames whose estimate is far from the
running median are outliers, frames with too few pairs are flagged, and both get the
smoothed value of their good neighbours (or are skipped).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np

Method = Literal["ratio", "clustered", "robust"]
METHODS: tuple[str, ...] = ("ratio", "clustered", "robust")

# Relative spread (10th to 90th percentile over the median) of the lidar depths (inverse
# depths for disparity) below which a shift is not fitted: at one depth scale and shift are
# one unknown.
MIN_SPREAD = 0.2

# Narrowest log-ratio gate of ``ratio``: its gate is 3 robust sigmas of a frame's ratios,
# and exact pairs (no spread) still need a band to pass.
RATIO_GATE_MIN = 0.03

# quality flags
OK = "ok"
FEW_PAIRS = "few_pairs"
LOW_INLIERS = "low_inliers"
OUTLIER_FRAME = "outlier_frame"


@dataclass
class ScaleEstimate:
    """One frame's fit: ``z = scale * d`` (depth) or ``1 / z = scale * d + shift`` (disp)."""

    scale: float
    shift: float = 0.0
    inliers: int = 0
    pairs: int = 0
    quality: str = OK
    method: str = ""

    @property
    def ok(self) -> bool:
        return self.quality == OK

    def as_dict(self) -> dict[str, float | int | str]:
        return asdict(self)


def _clean_pairs(lidar: np.ndarray, pred: np.ndarray, disparity: bool) -> (
    tuple[np.ndarray, np.ndarray]
):
    l = np.asarray(lidar, dtype=np.float64).reshape(-1)
    d = np.asarray(pred, dtype=np.float64).reshape(-1)
    ok = np.isfinite(l) & np.isfinite(d) & (l > 0)
    if not disparity:
        ok &= d > 0
    return l[ok], d[ok]


def _failed(n: int, method: str, quality: str = FEW_PAIRS) -> ScaleEstimate:
    return ScaleEstimate(float("nan"), 0.0, 0, n, quality, method)


def estimate_ratio(lidar: np.ndarray, pred: np.ndarray, disparity: bool = False,
                   gate: float | None = 0.2, min_pairs: int = 10) -> ScaleEstimate:
    """The paper's alpha = sum(l) / sum(d) over valid pairs (see module docstring):
    ``gate`` is the widest log-ratio gate, None for all pairs."""
    l, d = _clean_pairs(lidar, pred, disparity)
    if disparity:
        l, d = 1.0 / l, d  # fit 1/z = s * d
        keep = d > 0
        l, d = l[keep], d[keep]
    n = len(l)
    if n < min_pairs:
        return _failed(n, "ratio")
    valid = np.ones(n, bool)
    if gate is not None:
        r = np.log(l / d)  # [n]
        dev = np.abs(r - np.median(r))  # [n]
        # The gate narrows to 3 robust sigmas of the frame's own ratios: at the fixed 0.2,
        # outliers within 22 % of the scale (pairs seen just past an edge) counted as
        # valid, 2-4 % scale error flagged ok with 30 % of them at 1 % noise.
        width = min(gate, max(RATIO_GATE_MIN, 3.0 * 1.4826 * float(np.median(dev))))
        valid = dev < width
    s = float(l[valid].sum() / d[valid].sum())
    return _finish(s, 0.0, int(valid.sum()), n, "ratio", min_pairs)


def _spread(y: np.ndarray) -> float:
    """(p90 - p10) / median of the lidar side ``y`` [N] (1 / l for disparity): pairs at one
    depth cannot separate a shift from a scale, whatever offset the prediction carries."""
    lo, med, hi = np.percentile(y, [10, 50, 90])
    return float((hi - lo) / abs(med)) if med != 0 else 0.0


def _affine_refit(x: np.ndarray, y: np.ndarray, start: np.ndarray,
                  threshold: float = 0.05, iterations: int = 200,
                  seed: int = 0) -> tuple[float, float] | None:
    """(s, t) of ``y = s x + t`` with residuals relative to y: the best 2-point line among
    the pairs ``start`` [n] bool (support counted over all pairs), least squares on its
    inliers, then Tukey reweighting of all pairs (inlier band ``threshold``); None where
    the pairs cannot separate them (too little spread in the start pairs or in the fit's
    own inliers, not a positive scale).
    The reweighting matters: with a shift the per-pair ratios drift with depth, so a ratio
    cluster can take in outliers whose plain least squares tilts the line (scaled depth
    12-24 % off with 10-30 % outliers). So does the 2-point start: with a large positive
    shift the far true ratios fan out of the cluster, which is then the near pairs plus
    past-edge outliers, and reweighting from its least-squares line settled on a wrong
    one (shift 0.5 of the median inverse depth, 30 % outliers: 20 of 20 frames
    low_inliers; at 0.4, 15 of 20 and one flagged ok 3 % off)."""
    if start.sum() < 3 or _spread(y[start]) < MIN_SPREAD:
        return None
    pool = np.flatnonzero(start)
    rng = np.random.default_rng(seed)
    line = _best_line(x, y, pool[rng.integers(0, len(pool), (iterations, 2))], threshold)
    if line is not None:
        start = line[2]
    A = np.stack([x, np.ones(len(x))], -1)  # [n, 2]
    w = np.where(start, 1.0 / (y * y), 0.0)
    s = t = 0.0
    for it in range(11):
        if it:
            w = _tukey_weights((s * x + t - y) / y, 2.0 * threshold) / (y * y)
            if (w > 0).sum() < 3:
                break
        AtW = A.T * w
        try:
            s, t = (float(v) for v in np.linalg.solve(AtW @ A, AtW @ y))
        except np.linalg.LinAlgError:
            return None
    # The start pairs' spread is not enough (as in _robust_affine): facing a wall, pairs
    # seen just past its edge chain onto its cluster and spread it, and the line through
    # the wall took any slope (scale halved, shift 5x, flagged ok: 1 m read 1.32 m).
    inliers = np.abs((s * x + t - y) / y) < threshold  # [n]
    if s <= 0 or inliers.sum() < 3 or _spread(y[inliers]) < MIN_SPREAD:
        return None
    return s, t


def _best_line(x: np.ndarray, y: np.ndarray, idx: np.ndarray,
               threshold: float) -> tuple[float, float, np.ndarray] | None:
    """(s, t, inliers [n] bool) of the line ``y = s x + t`` through the pairs of pairs
    ``idx`` [m, 2] with a positive slope that the most pairs x [n], y [n] lie within
    ``threshold`` of (relative to y, so that near and far pairs count alike); None when
    no candidate has a positive slope."""
    x1, x2, y1, y2 = x[idx[:, 0]], x[idx[:, 1]], y[idx[:, 0]], y[idx[:, 1]]
    with np.errstate(divide="ignore", invalid="ignore"):
        s_c = (y2 - y1) / (x2 - x1)
        t_c = y1 - s_c * x1
    okc = np.isfinite(s_c) & (s_c > 0)
    if not okc.any():
        return None
    s_c, t_c = s_c[okc], t_c[okc]
    rel = np.abs(s_c[:, None] * x[None, :] + t_c[:, None] - y[None, :]) / y[None, :]
    best = int(np.argmax((rel < threshold).sum(1)))
    return float(s_c[best]), float(t_c[best]), rel[best] < threshold


def estimate_clustered(lidar: np.ndarray, pred: np.ndarray, disparity: bool = False,
                       algorithm: Literal["dbscan", "meanshift"] = "dbscan",
                       eps: float = 0.03, min_samples: int = 5, bandwidth: float = 0.05,
                       min_pairs: int = 10, min_fraction: float = 0.03,
                       fit_shift: bool | None = None) -> ScaleEstimate:
    """Dominant cluster of per-pair log ratios; alpha = sum(l) / sum(d) inside it.

    ``eps`` (DBSCAN) and ``bandwidth`` (mean-shift) are in log-ratio units: 0.03 groups
    ratios within about 3 % of each other. A DBSCAN core point needs ``min_samples``
    neighbours and ``min_fraction`` of the pairs. The dominant cluster is the one holding
    the densest ratio, and its inliers are the pairs within 2 ``eps`` of it; alpha sums
    over those, or over 2.5 robust sigmas of the cluster's ratios about it where they
    spread wider. A DBSCAN cluster is a chain of ratios each within eps of the next, and
    once outliers are dense enough to be core points it ran from the true ratio into
    them (a dense lidar's 30 % of pairs seeing up to 1.5x further past edges moved the
    scale by up to 8 %; ratios with no common scale chained into one cluster flagged ok).
    ``fit_shift`` (default: for disparity) refits scale and shift starting from the best
    2-point line among the cluster's pairs (``_affine_refit``).
    """
    l, d = _clean_pairs(lidar, pred, disparity)
    if disparity:
        l = 1.0 / l
        keep = d > 0
        l, d = l[keep], d[keep]
    n = len(l)
    if n < min_pairs:
        return _failed(n, "clustered")
    r = np.log(l / d).reshape(-1, 1)
    import sklearn

    # The inputs are already finite and the parameters fixed: skipping sklearn's checks
    # saves a few ms per frame, a tenth of the 30 frames/s budget.
    with sklearn.config_context(assume_finite=True, skip_parameter_validation=True):
        if algorithm == "dbscan":
            from sklearn.cluster import DBSCAN

            core = max(min_samples, int(np.ceil(min_fraction * n)))
            labels = DBSCAN(eps=eps, min_samples=min(core, n),
                            algorithm="kd_tree").fit_predict(r)
        elif algorithm == "meanshift":
            # About 50x slower than DBSCAN per frame (hundreds of ms): for studies only.
            from sklearn.cluster import MeanShift

            labels = MeanShift(bandwidth=bandwidth, bin_seeding=True).fit_predict(r)
        else:
            raise ValueError(f"unknown clustering {algorithm!r}; use 'dbscan' or 'meanshift'")
    good = labels >= 0
    if not good.any():
        return _failed(n, "clustered", LOW_INLIERS)
    ratios = r.ravel()
    order = np.argsort(ratios)
    rs = ratios[order]  # [n] sorted
    around = np.searchsorted(rs, rs + eps, "right") - np.searchsorted(rs, rs - eps, "left")
    densest = int(order[int(np.argmax(around))])
    # The densest ratio has the most neighbours, so it is a core point when any is; a
    # mean-shift label may still miss it, and then the largest cluster stands.
    best = int(labels[densest]) if labels[densest] >= 0 else int(
        np.argmax(np.bincount(labels[good])))
    cluster = labels == best
    centre = float(np.median(ratios[cluster & (np.abs(ratios - ratios[densest]) <= eps)])
                   if labels[densest] >= 0 else np.median(ratios[cluster]))
    # At least 2 eps, wider where the cluster's own ratios spread (a network's smooth
    # distortion spreads a frame's true ratios by several percent: 2 eps alone cut a fifth
    # of them and the simulated benchmark's median scale error rose 0.81 -> 0.99 %).
    # The inliers (what the frame's quality is judged on) stay those within 2 eps: ratios
    # with no common scale spread the cluster, and a band as wide took them all in.
    spread = 1.4826 * float(np.median(np.abs(ratios[cluster] - centre)))  # robust sigma
    summed = cluster & (np.abs(ratios - centre) < max(2.0 * eps, 2.5 * spread))
    members = cluster & (np.abs(ratios - centre) < 2.0 * eps)
    if not members.any():
        return _failed(n, "clustered", LOW_INLIERS)
    s, t = float(l[summed].sum() / d[summed].sum()), 0.0
    if disparity if fit_shift is None else fit_shift:
        # With a shift the ratios drift with the prediction, but smoothly: the cluster still
        # holds the pairs on the curve, and the reweighted refit drops the outliers.
        fit = _affine_refit(d, l, cluster)
        if fit is not None:
            s, t = fit
            members = np.abs((s * d + t - l) / l) < 0.05
    return _finish(s, t, int(members.sum()), n, "clustered", min_pairs)


def _tukey_weights(res: np.ndarray, c: float) -> np.ndarray:
    u = np.clip(np.abs(res) / c, 0, 1)
    return (1 - u * u) ** 2


def estimate_robust(lidar: np.ndarray, pred: np.ndarray, disparity: bool = False,
                    fit_shift: bool | None = None, threshold: float = 0.05,
                    iterations: int = 200, seed: int = 0, min_pairs: int = 10) -> ScaleEstimate:
    """RANSAC + Tukey IRLS. ``threshold`` is the inlier band: in log depth for scale only,
    relative to the inverse lidar depth for scale and shift (0.05 = 5 %)."""
    l, d = _clean_pairs(lidar, pred, disparity)
    n = len(l)
    if n < min_pairs:
        return _failed(n, "robust")
    fit_shift = disparity if fit_shift is None else fit_shift
    rng = np.random.default_rng(seed)
    if fit_shift and _spread(1.0 / l if disparity else l) < MIN_SPREAD:
        fit_shift = False  # pairs at one depth: the shift is not observable (module doc)
    if fit_shift:
        fit = _robust_affine(l, d, disparity, threshold, iterations, rng)
        if fit is not None:
            s, t, inliers = fit
            return _finish(s, t, inliers, n, "robust", min_pairs)
    # The scale alone (no shift asked for, or none observable).
    y, x = (1.0 / l, d) if disparity else (l, d)
    keep = x > 0
    y, x = y[keep], x[keep]
    if len(x) < min_pairs:  # disparities <= 0 are beyond infinity for a scale alone
        return _failed(len(x), "robust")
    r = np.log(y / x)  # [n] log ratio: the scale model is a constant in log space
    # RANSAC with 1-point samples: the candidate with most ratios within the band.
    cand = r[rng.integers(0, len(r), min(iterations, len(r)))]
    support = (np.abs(r[None, :] - cand[:, None]) < threshold).sum(1)
    logs = float(cand[int(np.argmax(support))])
    for _ in range(10):
        w = _tukey_weights(r - logs, 2.0 * threshold)
        if w.sum() <= 0:
            break
        logs = float((w * r).sum() / w.sum())
    inl = np.abs(r - logs) < threshold
    return _finish(float(np.exp(logs)), 0.0, int(inl.sum()), n, "robust", min_pairs)


def _robust_affine(l: np.ndarray, d: np.ndarray, disparity: bool, threshold: float,
                   iterations: int, rng: np.random.Generator) -> tuple[float, float, int] | None:
    """(scale, shift, inliers) on y = 1 / l (disparity) or y = l (depth with an offset):
    RANSAC on pairs of pairs, then Tukey IRLS; None when the inliers lie at one depth.
    The spread of all pairs is not enough: facing a wall, the pairs seen past its edge
    spread them (0.52 against the wall's 0.03), and a line through the one cluster took
    any slope (scale halved, shift 5x, flagged ok: 2 m read as 1.3-2.9 m)."""
    n = len(l)
    y = 1.0 / l if disparity else l
    x = d
    line = _best_line(x, y, rng.integers(0, n, (iterations, 2)), threshold)
    if line is None or _spread(y[line[2]]) < MIN_SPREAD:
        return None
    s, t = line[0], line[1]
    A = np.stack([x, np.ones(n)], -1)  # [n, 2]
    for _ in range(10):
        res = (s * x + t - y) / y
        w = _tukey_weights(res, 2.0 * threshold) / (y * y)
        if (w > 0).sum() < 2:
            break
        AtW = A.T * w
        try:
            s, t = np.linalg.solve(AtW @ A, AtW @ y)
        except np.linalg.LinAlgError:
            break
    inl = np.abs((s * x + t - y) / y) < threshold
    return float(s), float(t), int(inl.sum())


def _finish(scale: float, shift: float, inliers: int, n: int, method: str,
            min_pairs: int, min_inlier_ratio: float = 0.3) -> ScaleEstimate:
    q = OK
    # Pairs enough (fewer failed before any fit) but too few agreeing is low_inliers, not
    # few_pairs: that label sent users to the lidar's coverage and the extrinsic.
    if (not np.isfinite(scale) or scale <= 0 or inliers < min_pairs
            or inliers < min_inlier_ratio * n):
        q = LOW_INLIERS
    return ScaleEstimate(scale, shift, inliers, n, q, method)


def estimate_scale(method: Method, lidar: np.ndarray, pred: np.ndarray,
                   disparity: bool = False, **options: object) -> ScaleEstimate:
    """Dispatch to ``estimate_<method>``; ``options`` are that estimator's keywords.

    ``lidar`` [N] metres and ``pred`` [N] the prediction at the same pixels; ``disparity``
    says the prediction is relative disparity (Depth Anything's relative models): a wrong
    value still fits, to a meaningless scale flagged ok, so check the output kind with
    ``depth_order_agreement`` (the fuse stage refuses the run on it). ``ratio`` fits no
    shift, which relative disparity has: use ``clustered`` or ``robust`` for those."""
    fn = {"ratio": estimate_ratio, "clustered": estimate_clustered,
          "robust": estimate_robust}.get(method)
    if fn is None:
        raise ValueError(f"unknown scale estimator {method!r}; use one of {METHODS}")
    return fn(lidar, pred, disparity, **options)  # type: ignore[operator]


def depth_order_agreement(pairs: Iterable[tuple[np.ndarray, np.ndarray]],
                          min_pairs: int = 10) -> tuple[float, int]:
    """(median over frames of the rank correlation between lidar depth and prediction,
    frames counted) for (lidar [N], prediction [N]) per frame. Depth rises with the lidar's
    (near +1), disparity falls (near -1), whatever each frame's scale and shift: the sign
    tells a network's output kind apart from a wrong ``output`` setting."""
    from scipy.stats import spearmanr

    rhos = []
    for lidar, pred in pairs:
        ok = np.isfinite(lidar) & np.isfinite(pred) & (lidar > 0)
        if ok.sum() >= min_pairs and np.ptp(pred[ok]) > 0 and np.ptp(lidar[ok]) > 0:
            rhos.append(float(spearmanr(lidar[ok], pred[ok])[0]))
    return (float(np.median(rhos)) if rhos else float("nan")), len(rhos)


# ---------------------------------------------------------------------------- over time


@dataclass
class SmoothedScale:
    """Final per-frame values after temporal smoothing."""

    scale: np.ndarray  # [F] NaN where the frame is skipped
    shift: np.ndarray  # [F]
    raw_scale: np.ndarray  # [F] per-frame estimates (NaN where none)
    flag: list[str]  # [F] ok | outlier_frame | few_pairs | low_inliers
    used: np.ndarray  # [F] bool: frame has a usable scale


def smooth_scales(estimates: list[ScaleEstimate], window: int = 9,
                  outlier_tol: float = 0.1, mode: Literal["median", "none"] = "median",
                  fill: Literal["smoothed", "skip"] = "smoothed",
                  agreement: Callable[[int, float, float], float] | None = None) -> (
                      SmoothedScale):
    """Reject outlier frames and smooth the scale (and shift) over ``window`` frames.

    A good frame is an outlier when its log scale is more than ``outlier_tol`` from the
    median of the ``window`` good frames nearest it, itself included (the window shifted
    inside the sequence at its ends and past a lidar gap; at least three of them; with
    shifts, frames fitted with a shift only, and a frame fitted with the scale alone
    keeps it).
    ``mode="median"`` gives every good frame the median of its own value and the good
    frames' around it, as many before as after it within the window (the scale wanders
    slowly, a single frame's fit does not); ``"none"`` keeps good
    frames' own values, and so do estimates with a shift in either mode (a scale and shift
    pair is the image's own). Flagged frames take the smoothed value (with shifts: the pair
    of the frame nearest the median) when ``fill="smoothed"``, or are skipped.

    ``agreement(i, scale, shift)``: the fraction of frame i's own lidar pairs that a (scale,
    shift) explains (``pair_agreement``). With it, a frame off its neighbours is kept, with
    its own values in either mode, when its pairs back its own fit (at least half of them)
    and reject the neighbours' (twice as many agree with its own): a relative network's
    output constant can jump between two images, and the neighbours' scale then made that
    frame's depth 30 % wrong where its own was 2 % off. A wrong fit (a cluster on a person)
    has no such backing. Among scale-and-shift fits, a frame fitted with a scale alone is
    flagged when a neighbour's pair explains its pairs (at least half, twice as many as its
    own fit): a person at one depth, not a wall filling the view.
    """
    n = len(estimates)
    raw = np.array([e.scale for e in estimates], dtype=np.float64)
    shift = np.array([e.shift for e in estimates], dtype=np.float64)
    flags = [e.quality for e in estimates]
    good = np.array([e.ok and np.isfinite(e.scale) and e.scale > 0 for e in estimates], bool)
    logs = np.where(good, np.log(np.where(good, raw, 1.0)), np.nan)
    half = max(0, window // 2)

    def nearest_frames(idx: np.ndarray, i: int, k: int) -> np.ndarray:
        """The k of the sorted frame indices ``idx`` nearest frame i, nearest first (ties
        to the earlier one) [<= k]: a run of ``idx`` grown from i, so a frame costs k steps,
        not a sort of the whole drive."""
        hi = int(np.searchsorted(idx, i))
        lo = hi - 1
        out: list[int] = []
        while len(out) < k and (lo >= 0 or hi < len(idx)):
            if hi >= len(idx) or (lo >= 0 and i - idx[lo] <= idx[hi] - i):
                out.append(int(idx[lo]))
                lo -= 1
            else:
                out.append(int(idx[hi]))
                hi += 1
        return np.array(out, dtype=np.int64)

    def window_median(values: np.ndarray, mask: np.ndarray, i: int) -> float:
        lo, hi = max(0, i - half), min(n, i + half + 1)
        m = mask[lo:hi]
        if not m.any():
            # Widen until some good frame is found: a long gap takes its nearest neighbours.
            near = nearest_frames(np.flatnonzero(mask), i, max(1, half))
            if len(near) == 0:
                return float("nan")
            return float(np.median(values[near]))
        return float(np.median(values[lo:hi][m]))

    def balanced_median(values: np.ndarray, mask: np.ndarray, i: int) -> float:
        """Median of good frame i and as many good frames before it as after it within the
        window: at the sequence's ends and beside a lidar gap a one-sided window took the
        median from one side (a scale drifting 1.2 % per frame put the end frames 2-3 %
        off, where their own fits were 0.7 % off)."""
        before = np.flatnonzero(mask[max(0, i - half):i]) + max(0, i - half)
        after = np.flatnonzero(mask[i + 1:min(n, i + half + 1)]) + i + 1
        k = min(len(before), len(after))
        sel = np.r_[before[len(before) - k:], i, after[:k]].astype(np.int64)
        return float(np.median(values[sel]))

    def nearest_good(values: np.ndarray, mask: np.ndarray, i: int, target: float) -> int:
        lo, hi = max(0, i - half), min(n, i + half + 1)
        idx = np.arange(lo, hi)[mask[lo:hi]]
        if not len(idx):  # the widened window of window_median: its nearest good frames
            idx = nearest_frames(np.flatnonzero(mask), i, max(1, half))
        return int(idx[np.argmin(np.abs(values[idx] - target))])

    # In a sequence of (scale, shift) fits, a frame fitted with the scale alone (a wall
    # filling the view: estimate_scale keeps its shift at 0) holds another quantity: its
    # scale absorbed the shift. It is neither compared with the pairs around it (it was
    # flagged and handed a neighbour's pair: 0.35 % -> 35 % depth error on the wall) nor
    # lent to another frame.
    fitted_shift = shift != 0  # [F]
    backed = np.zeros(n, bool)  # [F] off the neighbours, backed by its own pairs
    affine = bool(fitted_shift[good].any())
    comparable = good & fitted_shift if affine else good  # [F]
    comparable_idx = np.flatnonzero(comparable)
    for i in range(n):
        if not comparable[i]:
            if good[i] and affine and agreement is not None and comparable.any():
                # A scale alone among scale-and-shift fits: a wall filling the view, or a
                # cluster on a person at one depth (70 % depth error). A neighbour's pair
                # that explains the frame's own pairs (those agreement counts: not on
                # moving obstacles) far better than its fit tells the second.
                j = nearest_good(logs, comparable, i, window_median(logs, comparable, i))
                theirs = agreement(i, float(raw[j]), float(shift[j]))
                if theirs >= 0.5 and theirs >= 2.0 * agreement(i, float(raw[i]), 0.0):
                    flags[i] = OUTLIER_FRAME
            continue
        # The window is the 2 half + 1 comparable frames nearest i: kept at full length,
        # shifted inside the sequence at its ends and past a lidar gap. Cut there, it held
        # 5 frames at the first one, and a run of 3 wrong frames at the start (someone in
        # front of the robot as the recording starts) made the median: frame 0 kept a
        # scale 50 % off, in both modes; so did the first frame after a gap.
        near = nearest_frames(comparable_idx, i, 2 * half + 1)  # [<= window]
        # With two frames in the window, the median is their mean: both would be flagged
        # when they differ, and neither is known to be the wrong one.
        if len(near) < 3:
            continue
        med = float(np.median(logs[near]))
        if abs(logs[i] - med) > outlier_tol:
            if agreement is not None:
                j = int(near[np.argmin(np.abs(logs[near] - med))]) if affine else -1
                theirs = (raw[j], shift[j]) if j >= 0 else (float(np.exp(med)), 0.0)
                own = agreement(i, float(raw[i]), float(shift[i]))
                if own >= 0.5 and own >= 2.0 * agreement(i, *theirs):
                    backed[i] = True
                    continue
            flags[i] = OUTLIER_FRAME
    good2 = good & np.array([f == OK for f in flags], bool)
    out_s = np.full(n, np.nan)
    out_t = np.zeros(n)
    # A scale and a shift hold together, and an affine (disparity) network's pair changes
    # from image to image (Depth Anything normalises each one): a neighbour's pair, or one
    # frame's scale with another's shift, fits neither (AbsRel 0.0007 -> 0.009 on exact
    # affine disparity). Good frames keep their own pair; the others take the pair of the
    # frame whose scale is nearest the window's median.
    lenders = good2 & fitted_shift if affine and (good2 & fitted_shift).any() else good2
    for i in range(n):
        if good2[i] and (mode == "none" or affine or backed[i]):
            out_s[i], out_t[i] = raw[i], shift[i]
            continue
        if not good2[i] and fill == "skip":
            continue
        if good2[i] and not affine:
            out_s[i], out_t[i] = float(np.exp(balanced_median(logs, good2, i))), 0.0
            continue
        m = window_median(logs, lenders, i)
        if np.isfinite(m) and affine:
            j = nearest_good(logs, lenders, i, m)
            out_s[i], out_t[i] = raw[j], shift[j]
            continue
        out_s[i] = np.exp(m) if np.isfinite(m) else np.nan
        out_t[i] = 0.0
    used = np.isfinite(out_s)
    return SmoothedScale(out_s, out_t, raw, flags, used)


def pair_agreement(lidar: np.ndarray, pred: np.ndarray, disparity: bool, scale: float,
                   shift: float, tol: float, min_spread: float = 1.0) -> float:
    """Fraction of the pairs (lidar [N] metres, prediction [N]; those with a valid lidar
    depth and a finite prediction) whose depth under (``scale``, ``shift``) lies within
    ``tol`` of the lidar's in log; a pair the fit puts behind the camera disagrees. 0 when
    the agreeing pairs span less than ``min_spread`` in depth (90th over 10th percentile):
    one object at one depth (a person in front of the camera) backs any scale."""
    lidar = np.asarray(lidar, np.float64)
    pred = np.asarray(pred, np.float64)
    valid = np.isfinite(lidar) & (lidar > 0) & np.isfinite(pred)
    if not valid.any():
        return 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        v = scale * pred[valid] + shift
        depth = 1.0 / v if disparity else v
        agree = (depth > 0) & (np.abs(np.log(depth / lidar[valid])) < tol)
    if min_spread > 1.0 and agree.sum() >= 2:
        lo, hi = np.percentile(lidar[valid][agree], [10, 90])
        if hi < min_spread * lo:
            return 0.0
    return float(np.mean(agree))
