"""Gradient-boosted trees on the calibration rows, from the weighted sum's logit.

:func:`boost` fits :class:`~pcc_ros.pipeline.trees.TermTrees` by Newton boosting of the logistic
loss (each tree's leaves are ``-sum(gradient) / (sum(hessian) + l2)``, shrunk by ``rate``),
starting from a given logit per row -- the fitted weighted sum's, so the trees learn only what the
sum leaves over. Splits are searched on quantile bins of each term (histograms of gradient and
hessian per node, one ``bincount`` per tree level for every node and term at once), trees are
grown complete to ``depth`` level by level, and a node splits only where both sides keep
``min_leaf`` rows. No sampling: the same rows give the same trees.

``monotone`` (one of -1, 0, +1 per term) keeps the trees' logit from falling as a ``+1`` term grows
(rising, for ``-1``): a split on such a term must order its two sides' values that way, and each
side's subtree is bounded by their midpoint (the leaves clipped into their node's bounds), so no
later split can undo it. For terms whose direction the physics gives, so that trees fitted on
simulation do not bend against it on a sensor they never saw.
"""

from __future__ import annotations

import numpy as np

from pcc_ros.pipeline.trees import TermTrees


def bin_edges(x: np.ndarray, bins: int) -> list[np.ndarray]:
    """Per column, the candidate thresholds: the distinct interior quantiles (at most ``bins - 1``)."""
    qs = np.linspace(0, 1, bins + 1)[1:-1]
    return [np.unique(np.quantile(col, qs)) for col in x.T]


def boost(x: np.ndarray, false: np.ndarray, weight: np.ndarray, base: np.ndarray, terms: tuple[str, ...],
          depth: int = 3, rounds: int = 300, rate: float = 0.05, min_leaf: int = 40, l2: float = 1.0,
          bins: int = 64, monotone: tuple[int, ...] | None = None) -> TermTrees:
    """Trees over the columns ``x (N, len(terms))`` (NaN read as 0) adding to the logit ``base (N,)``
    towards the labels ``false (N,)``, each row weighing ``weight``; ``monotone``: per term, the
    direction the logit must follow (0: free)."""
    x = np.nan_to_num(np.asarray(x, dtype=np.float64), nan=0.0)
    y = np.asarray(false, dtype=np.float64)
    w = np.asarray(weight, dtype=np.float64)
    n, f = x.shape
    edges = bin_edges(x, bins)
    b = max(1, max(len(e) for e in edges) + 1)  # bin k: edges[k-1] < value <= edges[k]
    code = np.stack([np.searchsorted(e, x[:, j], side="left") for j, e in enumerate(edges)], axis=1)
    flat = code + (np.arange(f) * b)[None, :]  # (N, F) bin index over all terms
    sign = np.zeros(f) if monotone is None else np.asarray(monotone, dtype=np.float64)
    if sign.shape != (f,) or not np.isin(sign, (-1.0, 0.0, 1.0)).all():
        raise ValueError(f"monotone: one of -1, 0, +1 per term ({f}), got {monotone}")
    inner = 2 ** depth - 1
    feature = np.zeros((rounds, inner), dtype=np.int64)
    threshold = np.full((rounds, inner), np.inf)
    leaf = np.zeros((rounds, inner + 1))
    logit = np.asarray(base, dtype=np.float64).copy()
    for r in range(rounds):
        p = 1.0 / (1.0 + np.exp(-logit))
        g, h = w * (p - y), w * p * (1.0 - p)
        node = np.zeros(n, dtype=np.int64)  # heap index of each row's node at this level
        low, high = np.full(2 * inner + 1, -np.inf), np.full(2 * inner + 1, np.inf)  # value bounds per node
        for level in range(depth):
            first, width = 2 ** level - 1, 2 ** level
            slot = node - first
            index = (slot[:, None] * (f * b) + flat).ravel()
            size = width * f * b
            hist = [np.bincount(index, weights=np.repeat(v, f), minlength=size).reshape(width, f, b)
                    for v in (g, h)]
            count = np.bincount(index, minlength=size).reshape(width, f, b)
            gl, hl, nl = (np.cumsum(a, axis=2)[:, :, :-1] for a in (*hist, count))
            gt, ht, nt = (a.sum(axis=2, keepdims=True) for a in (*hist, count))
            gain = gl ** 2 / (hl + l2) + (gt - gl) ** 2 / (ht - hl + l2) - gt ** 2 / (ht + l2)
            gain[(nl < min_leaf) | (nt - nl < min_leaf)] = -np.inf
            lo, hi = low[first:first + width, None, None], high[first:first + width, None, None]
            wl = np.clip(-gl / (hl + l2), lo, hi)
            wr = np.clip(-(gt - gl) / (ht - hl + l2), lo, hi)
            gain[sign[None, :, None] * (wr - wl) < 0] = -np.inf
            for s in range(width):
                j, k = np.unravel_index(np.argmax(gain[s]), gain[s].shape)
                node_id = first + s
                left, right = 2 * node_id + 1, 2 * node_id + 2
                low[[left, right]], high[[left, right]] = low[node_id], high[node_id]
                if gain[s, j, k] > 1e-12 and k < len(edges[j]):
                    feature[r, node_id], threshold[r, node_id] = j, edges[j][k]
                    mid = 0.5 * (wl[s, j, k] + wr[s, j, k])
                    if sign[j] > 0:
                        high[left], low[right] = min(high[node_id], mid), max(low[node_id], mid)
                    elif sign[j] < 0:
                        low[left], high[right] = max(low[node_id], mid), min(high[node_id], mid)
            go_right = x[np.arange(n), feature[r, node]] > threshold[r, node]
            node = 2 * node + 1 + go_right
        slot = node - inner
        gs = np.bincount(slot, weights=g, minlength=inner + 1)
        hs = np.bincount(slot, weights=h, minlength=inner + 1)
        leaf[r] = np.clip(-rate * gs / (hs + l2), rate * low[inner:], rate * high[inner:])
        logit += leaf[r, slot]
    return TermTrees(tuple(terms), feature, threshold, leaf)
