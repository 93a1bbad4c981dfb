"""Assignment and overlap for the tracker, vectorised with numpy (no scipy at run time).

`assign`: exact minimum-cost assignment, shortest augmenting paths with row and column
potentials (Kuhn-Munkres in the Jonker-Volgenant form), each step one numpy pass over the
columns. `match_edges`: the tracker's matchings, where only some (row, column) pairs may
match at all (an IoU or distance gate): the gated graph splits into connected components
that are solved apart, so a frame of many boxes costs many small assignments, not one
large one. `iou_pairs`: the pairs of boxes that overlap at least a threshold, computed a
block of rows at a time so that memory stays bounded however many boxes come (an N x N
matrix of 10,000 boxes took 5.5 GB, issue 36 item 1).
"""

from __future__ import annotations

import numpy as np

# Rows of an IoU block: BLOCK_ROWS x columns float64 values per temporary.
BLOCK_ROWS = 256


def assign(cost: np.ndarray) -> list[tuple[int, int]]:
    """Row-column pairs of a minimum-cost matching that covers min(n, m) rows or columns."""
    n, m = cost.shape
    if n == 0 or m == 0:
        return []
    if n > m:
        return sorted((i, j) for j, i in assign(cost.T))
    # Column 0 of c pads the virtual start, so that c[i, j] is column j's cost.
    c = np.hstack([np.zeros((n, 1)), np.asarray(cost, dtype=float)])
    inf = float("inf")
    # 1-based, column 0 is the virtual start of each augmenting path.
    u = np.zeros(n + 1)
    v = np.zeros(m + 1)
    owner = np.zeros(m + 1, dtype=np.int64)  # row that holds each column, 0 for none
    way = np.zeros(m + 1, dtype=np.int64)
    for i in range(1, n + 1):
        owner[0] = i
        j0 = 0
        minv = np.full(m + 1, inf)
        used = np.zeros(m + 1, dtype=bool)
        while True:
            used[j0] = True
            i0 = owner[j0]
            free = ~used
            free[0] = False
            cur = c[i0 - 1] - u[i0] - v
            better = free & (cur < minv)
            minv[better] = cur[better]
            way[better] = j0
            masked = np.where(free, minv, inf)
            j1 = int(np.argmin(masked))  # the first of equal minima, as a scan would
            delta = masked[j1]
            u[owner[used]] += delta  # the used columns' owners are distinct rows
            v[used] -= delta
            minv[free] -= delta
            j0 = j1
            if owner[j0] == 0:
                break
        while j0:
            j1 = int(way[j0])
            owner[j0] = owner[j1]
            j0 = j1
    return sorted((int(owner[j]) - 1, j - 1) for j in range(1, m + 1) if owner[j])


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of every box in a (N, 4) with every box in b (M, 4), boxes x1 y1 x2 y2."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    x1 = np.maximum(a[:, None, 0], b[None, :, 0])
    y1 = np.maximum(a[:, None, 1], b[None, :, 1])
    x2 = np.minimum(a[:, None, 2], b[None, :, 2])
    y2 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    out: np.ndarray = np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)
    return out


def iou_pairs(a: np.ndarray, b: np.ndarray, min_iou: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, columns, IoU) of the boxes of a and b that overlap by at least min_iou (> 0),
    sorted by row then column. A block of BLOCK_ROWS boxes of a (in x order) is compared
    only with the boxes of b whose x range meets the block's: memory of a block at a time,
    and boxes spread over a frame cost far less than every pair."""
    empty = np.zeros(0, dtype=np.int64)
    if len(a) == 0 or len(b) == 0:
        return empty, empty, np.zeros(0)
    a_order = np.argsort(a[:, 0], kind="stable")
    b_order = np.argsort(b[:, 0], kind="stable")
    bs = b[b_order]
    rows, cols, vals = [], [], []
    for start in range(0, len(a), BLOCK_ROWS):
        at = a_order[start:start + BLOCK_ROWS]
        blk = a[at]
        end = np.searchsorted(bs[:, 0], blk[:, 2].max(), side="right")
        near = np.flatnonzero(bs[:end, 2] >= blk[:, 0].min())
        iou = iou_matrix(blk, bs[near])
        r, c = np.nonzero(iou >= min_iou)
        rows.append(at[r])
        cols.append(b_order[near[c]])
        vals.append(iou[r, c])
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    order = np.lexsort((c, r))
    return r[order], c[order], v[order]


def components(n: int, m: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The connected component of each edge of a bipartite graph of n rows and m columns
    (edges rows[k]-cols[k]): the smallest node number in it (rows 0..n-1, columns n..)."""
    label = np.arange(n + m)
    a, b = rows, cols + n
    while True:
        # Each node takes the smallest label among its edges, then jumps to its label's
        # label: a chain of length L settles in about log L rounds.
        low = np.minimum(label[a], label[b])
        new = label.copy()
        np.minimum.at(new, a, low)
        np.minimum.at(new, b, low)
        new = new[new]
        if np.array_equal(new, label):
            out: np.ndarray = label[a]
            return out
        label = new


def match_edges(n: int, m: int, rows: np.ndarray, cols: np.ndarray, weight: np.ndarray
                ) -> list[tuple[int, int]]:
    """A maximum-weight matching among the given edges (weights > 0), exactly: each
    connected component of the edges is one assignment (a pair that is not an edge costs
    nothing, an edge minus its weight). Pairs (row, column), sorted."""
    if len(rows) == 0:
        return []
    comp = components(n, m, rows, cols)
    order = np.argsort(comp, kind="stable")
    cuts = np.flatnonzero(np.diff(comp[order])) + 1
    out: list[tuple[int, int]] = []
    for idx in np.split(order, cuts):
        if len(idx) == 1:  # one track, one box: the usual case, no assignment needed
            out.append((int(rows[idx[0]]), int(cols[idx[0]])))
            continue
        r_ids, r_at = np.unique(rows[idx], return_inverse=True)
        c_ids, c_at = np.unique(cols[idx], return_inverse=True)
        if len(r_ids) == 1 or len(c_ids) == 1:  # a star: its heaviest edge (the first)
            best = idx[int(np.argmax(weight[idx]))]
            out.append((int(rows[best]), int(cols[best])))
            continue
        cost = np.zeros((len(r_ids), len(c_ids)))
        cost[r_at, c_at] = -weight[idx]
        edge = np.zeros(cost.shape, dtype=bool)
        edge[r_at, c_at] = True
        out += [(int(r_ids[r]), int(c_ids[c])) for r, c in assign(cost) if edge[r, c]]
    return sorted(out)
